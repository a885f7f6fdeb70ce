"""Bit packing: the MSB-first bit stream every compact field is written into.

`BitWriter` / `BitReader` pack unsigned fields of 0..56 bits (and raw bytes at byte
boundaries); `bits_for` and `bounded_bits` give field widths as in DCCL (a field in [min, max]
at `resolution` costs ceil(log2((max - min) / resolution + 1)) bits); `zigzag` maps signed
integers to unsigned fields. A reader never reads past its data: every over-read is a
`DecodeError`.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from mergesvc.errors import CodecError, DecodeError

MAX_FIELD_BITS = 56  # widest bit field (any 56-bit field fits one 8-byte read at any offset)


def bits_for(max_value: int) -> int:
    """Bits of an unsigned field holding 0..max_value (0 bits: the field is constant)."""
    return int(max_value).bit_length()


def bounded_bits(lo: float, hi: float, resolution: float) -> int:
    """DCCL: a field in [lo, hi] at `resolution` costs ceil(log2((hi - lo) / resolution + 1))."""
    return bits_for(math.ceil((hi - lo) / resolution))


def zigzag(v: int) -> int:
    """Signed -> unsigned, small magnitudes stay small: 0, -1, 1, -2 -> 0, 1, 2, 3."""
    return 2 * v if v >= 0 else -2 * v - 1


def unzigzag(u: int) -> int:
    return u // 2 if u % 2 == 0 else -(u + 1) // 2


class BitWriter:
    """MSB-first bit packer: unsigned fields of 0..56 bits, and raw bytes at byte boundaries."""

    def __init__(self) -> None:
        self._done: list[bytes] = []
        self._bits: list[np.ndarray] = []
        self._pending = 0
        self.bit_length = 0

    def write(self, value: int, width: int) -> None:
        """One unsigned field, 0 <= value < 2**width."""
        if not 0 <= width <= MAX_FIELD_BITS or not 0 <= value < (1 << width):
            raise CodecError(f"value {value} does not fit a {width}-bit field")
        self.write_fields(np.array([value], dtype=np.uint64), np.array([width]))

    def write_fields(self, values: Any, widths: Any) -> None:
        """Fields in order; values (m,) unsigned ints, widths (m,) or one width for all."""
        v = np.asarray(values).ravel()
        if v.size == 0:
            return
        if v.dtype.kind not in "ui" or (v.dtype.kind == "i" and v.min() < 0):
            raise CodecError(f"bit fields must be unsigned integers, got {v.dtype}")
        v = v.astype(np.uint64)
        w = np.broadcast_to(np.asarray(widths, dtype=np.int64), v.shape).ravel()
        if w.min() < 0 or w.max() > MAX_FIELD_BITS:
            raise CodecError(f"bit field widths must be 0..{MAX_FIELD_BITS}")
        if np.any(v >> w.astype(np.uint64)):
            raise CodecError("a value does not fit its bit field")
        total = int(w.sum())
        if total == 0:
            return
        start = np.repeat(np.cumsum(w) - w, w)
        shift = np.repeat(w, w) - 1 - (np.arange(total) - start)
        self._bits.append(((np.repeat(v, w) >> shift.astype(np.uint64)) & 1).astype(np.uint8))
        self._pending += total
        self.bit_length += total

    def align(self) -> None:
        """Zero bits up to the next byte boundary."""
        pad = -self._pending % 8
        if pad:
            self._bits.append(np.zeros(pad, dtype=np.uint8))
            self._pending += pad
            self.bit_length += pad

    def write_bytes(self, data: bytes) -> None:
        """Raw bytes, after aligning to a byte boundary."""
        self.align()
        if self._bits:
            self._done.append(np.packbits(np.concatenate(self._bits)).tobytes())
            self._bits, self._pending = [], 0
        self._done.append(bytes(data))
        self.bit_length += 8 * len(data)

    def write_f32(self, x: float) -> None:
        self.write(struct.unpack(">I", struct.pack(">f", x))[0], 32)

    def getvalue(self) -> bytes:
        self.write_bytes(b"")
        return b"".join(self._done)


class BitReader:
    """Reads what BitWriter wrote; every over-read is a DecodeError naming `what`."""

    def __init__(self, data: bytes, what: str = "payload") -> None:
        self._data = bytes(data)
        self._buf = np.frombuffer(self._data + bytes(8), dtype=np.uint8)
        self._pos = 0
        self._what = what

    @property
    def remaining_bits(self) -> int:
        return 8 * len(self._data) - self._pos

    def _need(self, bits: int) -> None:
        if bits > self.remaining_bits:
            raise DecodeError(
                f"{self._what} truncated: needs {bits} more bits, {self.remaining_bits} left"
            )

    def read(self, width: int) -> int:
        return int(self.read_fields(np.array([width]))[0])

    def read_fields(self, widths: Any) -> np.ndarray:
        """Fields of the given widths (m,), in order, as uint64 (m,)."""
        w = np.asarray(widths, dtype=np.int64).ravel()
        if w.size == 0:
            return np.zeros(0, dtype=np.uint64)
        if w.min() < 0 or w.max() > MAX_FIELD_BITS:
            raise DecodeError(f"{self._what}: bit field width outside 0..{MAX_FIELD_BITS}")
        ends = np.cumsum(w)
        self._need(int(ends[-1]))
        offsets = self._pos + ends - w
        self._pos += int(ends[-1])
        # one big-endian 8-byte window per field; a 56-bit field at any bit offset fits in it
        byte = offsets >> 3
        v = np.zeros(w.size, dtype=np.uint64)
        for k in range(8):
            v = (v << np.uint64(8)) | self._buf[byte + k].astype(np.uint64)
        v <<= (offsets & 7).astype(np.uint64)
        shift = np.where(w == 0, 0, 64 - w).astype(np.uint64)
        return np.where(w == 0, np.uint64(0), v >> shift)

    def read_array(self, n: int, width: int) -> np.ndarray:
        """n fields of one width, uint64 (n,)."""
        self._need(n * width)
        return self.read_fields(np.full(n, width, dtype=np.int64))

    def align(self) -> None:
        pad = -self._pos % 8
        if pad and self.read(pad) != 0:
            raise DecodeError(f"{self._what}: padding bits are not zero")

    def read_bytes(self, n: int) -> bytes:
        self.align()
        self._need(8 * n)
        start = self._pos // 8
        self._pos += 8 * n
        return self._data[start : start + n]

    def read_f32(self) -> float:
        return struct.unpack(">f", struct.pack(">I", self.read(32)))[0]

    def finish(self) -> None:
        """Require the stream to end here (after zero padding to a byte)."""
        self.align()
        if self.remaining_bits:
            raise DecodeError(f"{self._what}: {self.remaining_bits // 8} unexpected trailing bytes")


__all__ = [
    "MAX_FIELD_BITS",
    "BitReader",
    "BitWriter",
    "bits_for",
    "bounded_bits",
    "unzigzag",
    "zigzag",
]
