"""The link's own framing: message fragments and selective-repeat acks, with their CRCs.

A message gets a CRC-32 trailer and is cut into fragments, one per modem frame (`split_message`,
`join_fragments`); each fragment carries a 4-byte header and a CRC-16 (`encode_fragment`). The
receiver answers with ack mini-frames listing, per message, "complete" or the fragments held
(`encode_ack`). Pure bytes: no channel, clock or Zenoh here.
"""

from __future__ import annotations

import binascii
import math
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from mergesvc.errors import DecodeError, LinkError

MINIFRAME_BYTES = 96
"""Largest mini-frame (used for acks)."""
FRAGMENT_HEADER_BYTES = 6
"""Per-frame header: msg id (12 bit) | fragment index (10 bit) | last index (10 bit), CRC-16."""
MESSAGE_TRAILER_BYTES = 4
"""CRC-32 of the whole message, appended before fragmentation."""
MSG_ID_MODULO = 1 << 12
MAX_FRAGMENTS = 1 << 10
MAX_MESSAGE_BYTES = 65536
"""Largest message the ARQ layer accepts (bytes, before the CRC-32 trailer)."""
ACK_ENTRY_HEADER_BYTES = 5
"""Header of an ack entry with a bitmap: msg id + flags (2), base (2), bitmap length (1)."""
_ACK_COMPLETE_BYTES = 2
CRC16_BYTES = 2
"""The CRC-16 that ends every frame (fragments and acks)."""
_FLAG_COMPLETE = 0x1


@dataclass(frozen=True)
class Fragment:
    """One frame's worth of a message: `index` of `count` fragments of message `msg_id`."""

    msg_id: int
    index: int
    count: int
    payload: bytes


def _crc16(data: bytes) -> bytes:
    return binascii.crc_hqx(data, 0xFFFF).to_bytes(2, "big")


def encode_fragment(fragment: Fragment) -> bytes:
    """Header (4 bytes: msg id 12 bit, index 10 bit, last index 10 bit) + payload + CRC-16."""
    if not (
        0 <= fragment.msg_id < MSG_ID_MODULO
        and 1 <= fragment.count <= MAX_FRAGMENTS
        and 0 <= fragment.index < fragment.count
    ):
        raise ValueError(
            f"fragment header out of range: {fragment.msg_id}/{fragment.index}/{fragment.count}"
        )
    word = (fragment.msg_id << 20) | (fragment.index << 10) | (fragment.count - 1)
    body = word.to_bytes(4, "big") + fragment.payload
    return body + _crc16(body)


def decode_fragment(frame: bytes) -> Fragment:
    """Inverse of `encode_fragment`; raises DecodeError on a CRC mismatch or a bad header."""
    if len(frame) < FRAGMENT_HEADER_BYTES:
        raise DecodeError(f"fragment of {len(frame)} bytes is shorter than its header")
    body, crc = frame[:-CRC16_BYTES], frame[-CRC16_BYTES:]
    if _crc16(body) != crc:
        raise DecodeError("fragment CRC-16 mismatch")
    word = int.from_bytes(body[:4], "big")
    msg_id, index, count = word >> 20, (word >> 10) & 0x3FF, (word & 0x3FF) + 1
    if index >= count:
        raise DecodeError(f"fragment index {index} >= count {count}")
    return Fragment(msg_id=msg_id, index=index, count=count, payload=bytes(body[4:]))


def split_message(msg_id: int, message: bytes, fragment_payload_bytes: int) -> list[Fragment]:
    """Message + CRC-32 trailer cut into fragments of at most `fragment_payload_bytes`."""
    data = message + zlib.crc32(message).to_bytes(MESSAGE_TRAILER_BYTES, "big")
    count = math.ceil(len(data) / fragment_payload_bytes)
    if count > MAX_FRAGMENTS:
        raise LinkError(
            f"message of {len(message)} bytes needs {count} > {MAX_FRAGMENTS} fragments"
        )
    return [
        Fragment(
            msg_id, i, count, data[i * fragment_payload_bytes : (i + 1) * fragment_payload_bytes]
        )
        for i in range(count)
    ]


def join_fragments(payloads: Sequence[bytes]) -> bytes:
    """Fragment payloads in index order -> message; DecodeError if the CRC-32 does not match."""
    data = b"".join(payloads)
    if len(data) < MESSAGE_TRAILER_BYTES:
        raise DecodeError("reassembled message shorter than its CRC-32 trailer")
    message, crc = data[:-MESSAGE_TRAILER_BYTES], data[-MESSAGE_TRAILER_BYTES:]
    if zlib.crc32(message).to_bytes(MESSAGE_TRAILER_BYTES, "big") != crc:
        raise DecodeError("reassembled message CRC-32 mismatch")
    return message


@dataclass(frozen=True)
class AckEntry:
    """Receiver state of one message: complete, or all fragments below `base` plus a bitmap.

    Bit i of `bitmap` (byte i // 8, LSB first) is set when fragment `base + i` was received.
    """

    msg_id: int
    complete: bool
    base: int = 0
    bitmap: bytes = b""

    @property
    def encoded_bytes(self) -> int:
        return _ACK_COMPLETE_BYTES if self.complete else ACK_ENTRY_HEADER_BYTES + len(self.bitmap)

    def received(self, count: int) -> Iterable[int]:
        """Fragment indices this entry acknowledges, for a message of `count` fragments."""
        if self.complete:
            yield from range(count)
            return
        yield from range(min(self.base, count))
        for i in range(8 * len(self.bitmap)):
            if self.bitmap[i // 8] >> (i % 8) & 1 and self.base + i < count:
                yield self.base + i


def encode_ack(entries: Sequence[AckEntry]) -> bytes:
    """Entries + CRC-16 in one mini-frame (at most MINIFRAME_BYTES)."""
    out = bytearray()
    for e in entries:
        out += ((e.msg_id << 4) | (_FLAG_COMPLETE if e.complete else 0)).to_bytes(2, "big")
        if not e.complete:
            out += e.base.to_bytes(2, "big") + len(e.bitmap).to_bytes(1, "big") + e.bitmap
    out += _crc16(bytes(out))
    if len(out) > MINIFRAME_BYTES:
        raise ValueError(
            f"ack of {len(out)} bytes does not fit a {MINIFRAME_BYTES}-byte mini-frame"
        )
    return bytes(out)


def decode_ack(frame: bytes) -> list[AckEntry]:
    """Inverse of `encode_ack`; DecodeError on a CRC mismatch or truncated entry."""
    if len(frame) < CRC16_BYTES or _crc16(frame[:-CRC16_BYTES]) != frame[-CRC16_BYTES:]:
        raise DecodeError("ack CRC-16 mismatch")
    body, pos, entries = frame[:-CRC16_BYTES], 0, []
    while pos < len(body):
        if pos + 2 > len(body):
            raise DecodeError("truncated ack entry")
        word = int.from_bytes(body[pos : pos + 2], "big")
        pos += 2
        if word & _FLAG_COMPLETE:
            entries.append(AckEntry(msg_id=word >> 4, complete=True))
            continue
        if pos + 3 > len(body):
            raise DecodeError("truncated ack entry")
        base, n = int.from_bytes(body[pos : pos + 2], "big"), body[pos + 2]
        bitmap = bytes(body[pos + 3 : pos + 3 + n])
        if len(bitmap) != n:
            raise DecodeError("truncated ack bitmap")
        pos += 3 + n
        entries.append(AckEntry(msg_id=word >> 4, complete=False, base=base, bitmap=bitmap))
    return entries


def ack_entry(msg_id: int, received: Iterable[int], max_bitmap_bytes: int) -> AckEntry:
    """The selective-repeat ack of a message partly received: `base` the first fragment
    missing, a bitmap of the fragments received beyond it (at most `max_bitmap_bytes`)."""
    got = set(received)
    base = 0
    while base in got:
        base += 1
    beyond = [i - base for i in got if i > base]
    n_bytes = min(max_bitmap_bytes, (max(beyond) // 8 + 1) if beyond else 0)
    bitmap = bytearray(n_bytes)
    for i in beyond:
        if i < 8 * n_bytes:
            bitmap[i // 8] |= 1 << (i % 8)
    return AckEntry(msg_id=msg_id, complete=False, base=base, bitmap=bytes(bitmap))


__all__ = [
    "ACK_ENTRY_HEADER_BYTES",
    "CRC16_BYTES",
    "FRAGMENT_HEADER_BYTES",
    "MAX_FRAGMENTS",
    "MAX_MESSAGE_BYTES",
    "MESSAGE_TRAILER_BYTES",
    "MINIFRAME_BYTES",
    "MSG_ID_MODULO",
    "AckEntry",
    "Fragment",
    "ack_entry",
    "decode_ack",
    "decode_fragment",
    "encode_ack",
    "encode_fragment",
    "join_fragments",
    "split_message",
]
