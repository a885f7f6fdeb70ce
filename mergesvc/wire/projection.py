"""The fleet-shared PCA `Projection` of embeddings, and the quantiser of its coefficients.

`compact` transform-codes embeddings on a `Projection`: coefficients c_j / sigma_j are coded
with a midrise uniform quantiser (step from Max's Gaussian table) at the bits given to each
component by greedy reverse water-filling (`Projection.bit_allocation`).
"""

from __future__ import annotations

import hashlib
import heapq
import math
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.core.model import MAX_EMBEDDING_DIM
from mergesvc.errors import CodecError, DecodeError, InputError, SchemaError, one_line
from mergesvc.wire.fields import NAN_OR_INF

MAX_COEF_BITS = 8  # most bits one PCA coefficient can get
MAX_PROJECTION_FILE_BYTES = 256 * 2**20

# Max (1960): step of the MSE-optimal uniform quantiser of a unit Gaussian, by bits.
_MAX_STEP = {1: 1.596, 2: 0.9957, 3: 0.5860, 4: 0.3352, 5: 0.1881, 6: 0.1041, 7: 0.0569, 8: 0.0308}


@dataclass(frozen=True, eq=False)
class Projection:
    """Fleet-shared PCA of embeddings: mean (d,), orthonormal basis (k, d), and the standard
    deviation of each coefficient over the data it was fitted on (k,), all float32.

    `id` is a short content hash (8 hex digits): a compact message names the projection it
    was coded with, and a decoder refuses a message whose projection it does not have.
    `fit_variance`: the total variance of the data it was fitted on (every direction's, the
    ones left out included), so that `variance_kept` can be told; None when not known. It is
    not part of the id.
    """

    mean_d: np.ndarray
    basis_kd: np.ndarray
    scale_k: np.ndarray
    fit_variance: float | None = None
    id: str = field(init=False)

    def __post_init__(self) -> None:
        try:
            mean = np.ascontiguousarray(self.mean_d, dtype="<f4")
            basis = np.ascontiguousarray(self.basis_kd, dtype="<f4")
            scale = np.ascontiguousarray(self.scale_k, dtype="<f4")
        except (ValueError, TypeError) as exc:
            raise SchemaError(f"projection arrays must be numeric: {one_line(exc)}") from exc
        if mean.ndim != 1 or not 1 <= mean.size <= MAX_EMBEDDING_DIM:
            raise SchemaError(f"projection mean must be (d,), d <= {MAX_EMBEDDING_DIM}")
        d = mean.size
        if basis.ndim != 2 or basis.shape[1] != d or not 1 <= basis.shape[0] <= d:
            raise SchemaError(f"projection basis must be (k, {d}) with 1 <= k <= {d}")
        if scale.shape != (basis.shape[0],):
            raise SchemaError(f"projection scale must be ({basis.shape[0]},)")
        for name, a in (("mean", mean), ("basis", basis), ("scale", scale)):
            if not np.all(np.isfinite(a)):
                raise SchemaError(f"projection {name} has {NAN_OR_INF}")
        if np.any(scale <= 0):
            raise SchemaError("projection scale must be positive")
        if self.fit_variance is not None:
            fv = float(self.fit_variance)
            if not (math.isfinite(fv) and fv > 0):
                raise SchemaError("projection fit variance must be positive and finite")
            object.__setattr__(self, "fit_variance", fv)
        gram = basis.astype(np.float64) @ basis.T.astype(np.float64)
        if np.abs(gram - np.eye(len(basis))).max() > 1e-4:
            raise SchemaError("projection basis rows must be orthonormal")
        for name, a in (("mean_d", mean), ("basis_kd", basis), ("scale_k", scale)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        h = hashlib.sha256(b"mergesvc-projection-1")
        h.update(struct.pack("<II", basis.shape[0], d))
        for a in (mean, basis, scale):
            h.update(a.tobytes())
        object.__setattr__(self, "id", h.hexdigest()[:8])
        object.__setattr__(self, "_alloc", {})

    @property
    def k(self) -> int:
        return self.basis_kd.shape[0]

    @property
    def dim(self) -> int:
        return self.mean_d.shape[0]

    @property
    def variance_kept(self) -> float | None:
        """The share of the fit data's variance its k components hold (None: not known)."""
        if self.fit_variance is None:
            return None
        return min(1.0, float(np.sum(self.scale_k.astype(np.float64) ** 2)) / self.fit_variance)

    @classmethod
    def fit(
        cls, embeddings_nd: Any, k: int | None = None, max_samples: int | None = None,
        seed: int = 0,
    ) -> Projection:
        """PCA of (n, d) embeddings; keeps min(k, n - 1, d) components (fewer if the data
        has lower rank). More than `max_samples` rows: a random subset of that many, drawn
        with numpy's Generator(seed). Fit it on data the fleet already shares (a survey, maps
        of earlier missions), not on what it will code, and share the file: a fit on another
        machine may differ in the last bits, and so in its id (docs/wire.md §5.3)."""
        E = np.asarray(embeddings_nd, dtype=np.float64)
        if E.ndim != 2 or E.shape[0] < 2 or not 1 <= E.shape[1] <= MAX_EMBEDDING_DIM:
            raise CodecError(f"a projection needs (n >= 2, d) embeddings, got {E.shape}")
        if not np.all(np.isfinite(E)):
            raise CodecError(f"embeddings have {NAN_OR_INF}")
        if max_samples is not None and E.shape[0] > max_samples:
            if max_samples < 2:
                raise CodecError(f"max_samples must be >= 2, got {max_samples}")
            rows = np.random.default_rng(seed).choice(E.shape[0], max_samples, replace=False)
            E = E[np.sort(rows)]
        mean = E.mean(axis=0)
        _, S, Vt = np.linalg.svd(E - mean, full_matrices=False)
        scale = S / math.sqrt(E.shape[0])  # std of each coefficient over the fit data
        rank = int(np.sum(scale > 1e-6 * scale[0])) if scale[0] > 0 else 0
        if rank == 0:
            raise CodecError("cannot fit a projection: all embeddings are identical")
        k = rank if k is None else min(int(k), rank)
        if k < 1:
            raise CodecError("a projection needs k >= 1")
        basis = Vt[:k]
        # a deterministic sign per component: the largest entry is positive
        basis = basis * np.sign(basis[np.arange(k), np.abs(basis).argmax(axis=1)])[:, None]
        return cls(mean, basis, scale[:k], float(np.sum(scale**2)))

    def coefficients(self, embeddings_nd: np.ndarray) -> np.ndarray:
        """(n, d) -> (n, k): basis (e - mean)."""
        return (np.asarray(embeddings_nd, np.float64) - self.mean_d) @ self.basis_kd.T.astype(
            np.float64
        )

    def reconstruct(self, coeffs_nk: np.ndarray) -> np.ndarray:
        """(n, k) -> (n, d): mean + basis^T c."""
        return self.mean_d.astype(np.float64) + coeffs_nk @ self.basis_kd.astype(np.float64)

    def bit_allocation(self, budget_bits: int) -> np.ndarray:
        """Bits per component (k,) summing to min(budget, 8 k): greedy reverse water-filling,
        each bit to the component whose quantisation error is largest (std / 2^bits).
        Exact arithmetic on the stored float32 scales, so both ends agree bit for bit."""
        cache: dict[int, np.ndarray] = self._alloc  # type: ignore[attr-defined]
        if budget_bits not in cache:
            if len(cache) >= 8:  # budgets come from messages: keep the cache small
                cache.clear()
            bits = np.zeros(self.k, dtype=np.int64)
            heap = [(-float(s), j) for j, s in enumerate(self.scale_k)]
            heapq.heapify(heap)
            for _ in range(min(budget_bits, MAX_COEF_BITS * self.k)):
                neg, j = heapq.heappop(heap)
                bits[j] += 1
                if bits[j] < MAX_COEF_BITS:
                    heapq.heappush(heap, (neg / 2, j))
            bits.setflags(write=False)
            cache[budget_bits] = bits
        return cache[budget_bits]

    def save(self, path: Path | str) -> Path:
        """Write an .npz (mean, basis, scale, id, version; fit_variance when known); returns
        the path."""
        p = Path(path)
        extra = {} if self.fit_variance is None else {"fit_variance": np.array(self.fit_variance)}
        try:
            with p.open("wb") as f:
                np.savez(
                    f,
                    mean=self.mean_d,
                    basis=self.basis_kd,
                    scale=self.scale_k,
                    id=np.array(self.id),
                    version=np.array(1),
                    **extra,
                )
        except OSError as exc:
            raise InputError(f"cannot write {p}: {exc.strerror or exc}") from exc
        return p

    @classmethod
    def load(cls, path: Path | str) -> Projection:
        """Read and validate a projection file; its stored id must match its content."""
        p = Path(path)
        try:
            if p.stat().st_size > MAX_PROJECTION_FILE_BYTES:
                raise SchemaError(f"{p}: larger than {MAX_PROJECTION_FILE_BYTES} bytes")
            z = np.load(p, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):  # a lone .npy array: no context manager
                raise DecodeError(f"{p} is not a projection file: one array, not an .npz archive")
            with z:
                arrays = {k: z[k] for k in ("mean", "basis", "scale", "id")}
                fv = z["fit_variance"] if "fit_variance" in z.files else None
        except OSError as exc:
            raise DecodeError(f"cannot read projection {p}: {exc.strerror or exc}") from exc
        except (ValueError, KeyError, EOFError, zipfile.BadZipFile, NotImplementedError,
                zlib.error) as exc:  # zipfile: an unsupported zip version or compression
            # method is NotImplementedError, a corrupt deflate stream zlib.error; numpy's own
            # words for a file of pickled objects would invite loading it unsafely: never
            why = ("it holds pickled objects, which are never loaded" if "pickle" in str(exc)
                   else one_line(exc))
            raise DecodeError(f"{p} is not a projection file: {why} (`mergesvc projection "
                              f"make` writes one)") from exc
        try:
            fit_variance = None if fv is None else float(fv)
        except (TypeError, ValueError) as exc:
            raise SchemaError(f"{p}: fit_variance is not a number") from exc
        proj = cls(arrays["mean"], arrays["basis"], arrays["scale"], fit_variance)
        if str(arrays["id"]) != proj.id:
            raise SchemaError(
                f"{p}: stored id {str(arrays['id'])!r} does not match its content ({proj.id})"
            )
        return proj


@dataclass(frozen=True)
class CompactCode:
    """How a compact message coded its embeddings (the payload's `[projection_id,
    budget_bits, step16]` header, docs/wire.md §5)."""

    projection_id: str
    budget_bits: int
    step16: int


def compact_view(embeddings_nd: np.ndarray, proj: Projection, code: CompactCode) -> np.ndarray:
    """(n, d) embeddings as a compact message coded with `code` decodes them: quantised on
    `proj` and reconstructed. Idempotent: an embedding decoded from such a message is given
    back (to float rounding)."""
    step = code.step16 / 16
    codes = quantize_coefficients(proj.coefficients(embeddings_nd), proj, code.budget_bits, step)
    return proj.reconstruct(dequantize_coefficients(codes, proj, code.budget_bits, step))


def compact_cosine(embeddings_nd: np.ndarray, proj: Projection, code: CompactCode) -> np.ndarray:
    """(n,) cosine between each embedding and what a compact message coded with `code`
    decodes it to: how well the projection fits the data (1: exactly; an all-zero
    embedding counts as 1 when it decodes to zero, else 0)."""
    E = np.asarray(embeddings_nd, dtype=np.float64)
    V = compact_view(E, proj, code)
    num = np.einsum("nd,nd->n", E, V)
    den = np.linalg.norm(E, axis=1) * np.linalg.norm(V, axis=1)
    both_zero = (np.linalg.norm(E, axis=1) == 0) & (np.linalg.norm(V, axis=1) == 0)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), both_zero.astype(np.float64))


def _coef_step(bits: np.ndarray, step_scale: float) -> np.ndarray:
    """Quantiser step per component in units of its std (0 where no bits)."""
    return np.array([step_scale * _MAX_STEP[b] if b else 0.0 for b in bits])


def quantize_coefficients(
    coeffs_nk: np.ndarray, proj: Projection, budget_bits: int, step_scale: float
) -> np.ndarray:
    """Midrise uniform codes (n, k) of c_j / sigma_j with the allocated bits per component."""
    bits = proj.bit_allocation(budget_bits)
    step = np.where(bits > 0, _coef_step(bits, step_scale), 1.0)
    half = np.where(bits > 0, 1 << np.maximum(bits - 1, 0), 0)
    q = np.floor(coeffs_nk / proj.scale_k.astype(np.float64) / step) + half
    return np.clip(q, 0, (1 << bits) - 1).astype(np.uint64)


def dequantize_coefficients(
    codes_nk: np.ndarray, proj: Projection, budget_bits: int, step_scale: float
) -> np.ndarray:
    """Inverse of quantize_coefficients: bin centres; components without bits decode to 0."""
    bits = proj.bit_allocation(budget_bits)
    step = _coef_step(bits, step_scale) * proj.scale_k.astype(np.float64)
    half = np.where(bits > 0, 1 << np.maximum(bits - 1, 0), 0)
    return np.where(bits > 0, (codes_nk.astype(np.float64) - half + 0.5) * step, 0.0)


__all__ = [
    "MAX_COEF_BITS",
    "MAX_PROJECTION_FILE_BYTES",
    "CompactCode",
    "Projection",
    "compact_cosine",
    "compact_view",
    "dequantize_coefficients",
    "quantize_coefficients",
]
