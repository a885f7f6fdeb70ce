"""What the merge service keeps in memory of every object and every accepted factor, compactly.

The service holds every session's objects (each from the latest submap holding it) and every
accepted factor for the whole mission, packed so that what is read back is what came in:

  - `PackedVector`: a float64 vector in the fewest bytes that give back the very same values,
    bit for bit: int8 codes times one scale, a table of at most 256 distinct values with one
    byte per value, float32, else float64. Matching computes on the unpacked float64 values;
  - `HeldObject`: an object as the service holds it (its embedding and variance packed; the
    ObjectNode built again when asked);
  - `HeldFactor`, `FactorTable`: an accepted factor's numbers in one float64 array and its
    object pairs; the table is the service's `factors` (factor id -> Factor, built again equal
    to the one accepted when read). What it saves: docs/benchmarks/soak.md.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator, MutableMapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mergesvc.core.frames import frame_name
from mergesvc.core.model import (
    Correspondence,
    Factor,
    FactorStatus,
    ObjectNode,
    Transform,
)
from mergesvc.errors import InputError

_TABLE_MAX = 256  # distinct values a one-byte index can name


def _bits(x: np.ndarray) -> np.ndarray:
    return x.view(np.uint64)


class PackedVector:
    """A 1-d float64 vector held in fewer bytes when that loses nothing; `unpack()` gives back
    the very same float64 values (bit for bit, signed zeros included). See the module
    docstring for the forms, the smallest exact one is kept."""

    __slots__ = ("_codes", "_table")

    def __init__(self, codes: np.ndarray, table: float | np.ndarray | None) -> None:
        self._codes = codes  # float64 / float32 values, int8 codes or uint8 indices
        self._table = table  # None, the int8 codes' scale, or the uint8 indices' values

    @classmethod
    def pack(cls, values: Any) -> PackedVector:
        x = np.ascontiguousarray(values, dtype=np.float64)
        if x.ndim != 1:
            raise InputError(f"a packed vector is 1-d, got shape {x.shape}")
        n = x.size
        bits = _bits(x)
        best = cls(x.copy(), None)
        if n and np.isfinite(x).all():
            peak = float(np.abs(x).max())
            if peak > 0.0:
                scale = peak / 127.0
                codes = np.rint(x / scale)
                if np.abs(codes).max() <= 127.0:
                    c8 = codes.astype(np.int8)
                    if np.array_equal(_bits(c8.astype(np.float64) * scale), bits):
                        best = cls(c8, scale)
                        if n >= 3:  # nothing is smaller
                            return best
        with np.errstate(over="ignore"):
            x32 = x.astype(np.float32)
        if 4 * n < best.nbytes and np.array_equal(_bits(x32.astype(np.float64)), bits):
            best = cls(x32, None)
        if n:
            table, index = np.unique(bits, return_inverse=True)
            if len(table) <= _TABLE_MAX and n + 8 * len(table) < best.nbytes:
                best = cls(index.astype(np.uint8).reshape(n), table.view(np.float64))
        return best

    def unpack(self) -> np.ndarray:
        """The float64 values (a new array)."""
        c, t = self._codes, self._table
        if t is None:
            return c.astype(np.float64)
        if isinstance(t, float):
            return c.astype(np.float64) * t
        return t[c]

    @property
    def nbytes(self) -> int:
        """Bytes of the values held (the codes and their scale or table)."""
        t = self._table
        return self._codes.nbytes + (0 if t is None else 8 if isinstance(t, float) else t.nbytes)

    @property
    def form(self) -> str:
        """How the values are held: float64, float32, int8 (times a scale) or table."""
        if self._table is None:
            return str(self._codes.dtype)
        return "int8" if isinstance(self._table, float) else "table"

    def __len__(self) -> int:
        return int(self._codes.size)

    def __repr__(self) -> str:
        return f"PackedVector({len(self)} values as {self.form}, {self.nbytes} bytes)"


def _intern(s: str | None) -> Any:
    return None if s is None else sys.intern(s)


@dataclass(frozen=True, slots=True)
class HeldObject:
    """An object of a session as the service holds it: from the submap `seq` (the latest that
    held it), its position in the frame of that submap's keyframe; its embedding and a
    per-dimension variance packed (`PackedVector`, lossless), a single variance as it came.
    `node` is the ObjectNode it was made of (an equal one, built when asked)."""

    seq: int
    keyframe: int
    id: str
    position: tuple[float, float, float]
    embedding: PackedVector
    variance: float | PackedVector
    n_obs: int = 1
    label: str | None = None

    @classmethod
    def of(cls, seq: int, keyframe: int, node: ObjectNode) -> HeldObject:
        var = node.variance
        return cls(seq, keyframe, sys.intern(node.id), node.position,
                   PackedVector.pack(node.embedding),
                   PackedVector.pack(var) if isinstance(var, list) else var,
                   node.n_obs, _intern(node.label))

    @property
    def dim(self) -> int:
        return len(self.embedding)

    def variance_value(self) -> float | list[float]:
        """The variance as the ObjectNode has it: one number, or one per dimension."""
        v = self.variance
        return v.unpack().tolist() if isinstance(v, PackedVector) else v

    def node_at(self, position: tuple[float, float, float]) -> ObjectNode:
        """The object as an ObjectNode at `position` (its values checked when it arrived)."""
        return ObjectNode.model_construct(
            id=self.id, position=position, embedding=self.embedding.unpack().tolist(),
            variance=self.variance_value(), n_obs=self.n_obs, label=self.label)

    @property
    def node(self) -> ObjectNode:
        return self.node_at(self.position)


_T = 7  # translation (3), quaternion wxyz (4)
_COV = _T + 36  # then the 6x6 covariance, then one score per correspondence


@dataclass(frozen=True, slots=True)
class HeldFactor:
    """An accepted factor as the service holds it: ids, keyframes and status as they are, its
    numbers (T_a_b, covariance, correspondence scores) in one float64 array, its object pairs
    as one flat tuple (object_a, object_b, object_a, ...). `factor()` is the Factor again,
    equal to the one held."""

    factor_id: str
    robot_a: str
    session_a: str
    robot_b: str
    session_b: str
    keyframe_a: int | None
    keyframe_b: int | None
    status: FactorStatus | None
    numbers: np.ndarray
    pairs: tuple[str, ...]

    @classmethod
    def of(cls, f: Factor) -> HeldFactor:
        numbers = np.concatenate([
            np.asarray(f.T_a_b.translation, dtype=np.float64),
            np.asarray(f.T_a_b.quaternion_wxyz, dtype=np.float64),
            np.asarray(f.covariance, dtype=np.float64).reshape(36),
            np.asarray([c.score for c in f.correspondences], dtype=np.float64),
        ])
        pairs = tuple(sys.intern(s) for c in f.correspondences for s in (c.object_a, c.object_b))
        return cls(f.factor_id, sys.intern(f.robot_a), sys.intern(f.session_a),
                   sys.intern(f.robot_b), sys.intern(f.session_b), f.keyframe_a, f.keyframe_b,
                   f.status, numbers, pairs)

    @property
    def frame_a(self) -> str:
        """Session a's name "{robot}/{session}"."""
        return frame_name(self.robot_a, self.session_a)

    @property
    def frame_b(self) -> str:
        return frame_name(self.robot_b, self.session_b)

    def object_pairs(self) -> Iterator[tuple[str, str]]:
        """(object_a, object_b) of every correspondence, in order."""
        p = self.pairs
        return zip(p[0::2], p[1::2], strict=True)

    def factor(self) -> Factor:
        v = self.numbers
        scores = v[_COV:].tolist()
        return Factor(
            factor_id=self.factor_id,
            robot_a=self.robot_a, session_a=self.session_a,
            robot_b=self.robot_b, session_b=self.session_b,
            T_a_b=Transform(translation=tuple(v[:3].tolist()),
                            quaternion_wxyz=tuple(v[3:_T].tolist())),
            covariance=v[_T:_COV].reshape(6, 6).tolist(),
            correspondences=[Correspondence(object_a=a, object_b=b, score=s)
                             for (a, b), s in zip(self.object_pairs(), scores, strict=True)],
            status=self.status,
            keyframe_a=self.keyframe_a, keyframe_b=self.keyframe_b,
        )


class FactorTable(MutableMapping[str, Factor]):
    """factor id -> Factor, holding each as a `HeldFactor`: reading one builds the Factor
    again (equal to the one stored). `held()` gives the records themselves, without building
    anything (what the global map needs: frames and object pairs)."""

    def __init__(self) -> None:
        self._held: dict[str, HeldFactor] = {}

    def __getitem__(self, factor_id: str) -> Factor:
        return self._held[factor_id].factor()

    def __setitem__(self, factor_id: str, factor: Factor) -> None:
        if factor_id != factor.factor_id:
            raise InputError(f"factor {factor.factor_id!r} filed under {factor_id!r}")
        self._held[factor.factor_id] = HeldFactor.of(factor)

    def __delitem__(self, factor_id: str) -> None:
        del self._held[factor_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self._held)

    def __len__(self) -> int:
        return len(self._held)

    def __contains__(self, factor_id: object) -> bool:
        return factor_id in self._held

    def held(self) -> Iterator[HeldFactor]:
        return iter(self._held.values())


__all__ = ["FactorTable", "HeldFactor", "HeldObject", "PackedVector"]
