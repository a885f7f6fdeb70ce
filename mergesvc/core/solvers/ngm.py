"""NGM, the neural graph-matching network (Wang et al., PAMI 2022) as pygmtools packages it:
a numpy forward pass over the candidate pairs of a Lawler QAP, with weights we trained.

The network is pygmtools' `NGM_Net`: graph convolutions on the association graph (a node per
assignment pair p, an edge per K[p, q] of magnitude at least EDGE_MIN), each layer followed by a
Sinkhorn embedding; a last Sinkhorn with dummy rows. Run on all n1*n2 pairs it computes what
pygmtools' numpy `ngm` computes with the same weights on K with its entries below EDGE_MIN set
to 0 (tests/test_ngm.py); run on a candidate set, the other pairs are absent (zero mass). The
first embedding is the node affinity diag(K) (NGM's first-order input), pygmtools' `x0`.

Weights live in `ngm_weights` (a generated module: the core reads no files); `mergesvc solver
train` writes new ones.
"""

# Why not pygmtools' own numpy `ngm` with our weights: it needs the dense K over all n1*n2
# pairs, which verified mode never builds (it works on ~12 candidates per row), and on dense
# problems it materialises several n1n2 x n1n2 arrays: measured here on random K, 20 x 300
# nodes took 8.5 s and 1.4 GB peak, about 5x K (docs/benchmarks/ngm.md).

from __future__ import annotations

import base64
import functools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from mergesvc.core.solvers.problem import AssignmentProblem
from mergesvc.errors import SolverError

# pygmtools' defaults for NGM, which the shipped weights use
SK_ITERS = 20
SK_TAU = 0.05
# An edge of the association graph is an entry of K of at least this magnitude (pygmtools: any
# non-zero one). Smaller affinities are nothing; float64 subnormals (< 2.2e-308) among them made
# each product with K ~100x slower, and training in float32 cannot tell them from zero.
EDGE_MIN = 1e-30


def param_names(n_layers: int) -> list[str]:
    """The parameter names of an NGM with n_layers layers, as pygmtools / torch name them."""
    names = []
    for i in range(n_layers):
        for f in ("n_func.0", "n_func.2", "n_self_func.0", "n_self_func.2", "classifier"):
            names += [f"gnn_layer_{i}.{f}.weight", f"gnn_layer_{i}.{f}.bias"]
    return [*names, "classifier.weight", "classifier.bias"]


@dataclass(frozen=True)
class NGMWeights:
    """NGM's parameters by name (float64 copies); shapes checked against one another.

    Linear layers are (out, in) weights and (out,) biases, as in torch and pygmtools."""

    arrays: Mapping[str, np.ndarray]
    sk_iters: int = SK_ITERS
    sk_tau: float = SK_TAU

    def __post_init__(self) -> None:
        n = sum(1 for k in self.arrays if k.endswith(".n_func.0.weight"))
        if n == 0 or sorted(self.arrays) != sorted(param_names(n)):
            raise SolverError("NGM weights: parameter names do not form an NGM network")
        object.__setattr__(self, "arrays", {k: np.array(v, dtype=np.float64)
                                            for k, v in self.arrays.items()})
        width_in = 1
        for i in range(n):
            p = f"gnn_layer_{i}."
            w0 = self.arrays[p + "n_func.0.weight"]
            if w0.shape[1] != width_in:
                raise SolverError(f"NGM weights: layer {i} takes {w0.shape[1]} features, "
                                  f"gets {width_in}")
            width_in = w0.shape[0] + self.arrays[p + "classifier.weight"].shape[0]
        if self.arrays["classifier.weight"].shape != (1, width_in):
            raise SolverError("NGM weights: the classifier does not fit the last layer")
        for k, v in self.arrays.items():
            bias = self.arrays.get(k[: -len("weight")] + "bias") if k.endswith("weight") else None
            if bias is not None and (v.ndim != 2 or bias.shape != (v.shape[0],)):
                raise SolverError(f"NGM weights: {k} and its bias do not fit")
            if not np.all(np.isfinite(v)):
                raise SolverError(f"NGM weights: {k} has non-finite values")

    @property
    def n_layers(self) -> int:
        return sum(1 for k in self.arrays if k.endswith(".n_func.0.weight"))

    def linear(self, name: str, x: np.ndarray) -> np.ndarray:
        return x @ self.arrays[name + ".weight"].T + self.arrays[name + ".bias"]

    def mlp(self, name: str, x: np.ndarray) -> np.ndarray:
        """Linear, ReLU, Linear, ReLU (pygmtools' n_func / n_self_func)."""
        h = np.maximum(self.linear(name + ".0", x), 0.0)
        return np.maximum(self.linear(name + ".2", h), 0.0)


def sinkhorn(
    s_m: np.ndarray, rows: np.ndarray, cols: np.ndarray, n1: int, n2: int,
    tau: float = SK_TAU, iters: int = SK_ITERS,
) -> np.ndarray:
    """pygmtools' `sinkhorn(dummy_row=True)` on the (n1, n2) matrix holding s_m (m,) at (rows,
    cols) and nothing elsewhere. Returns (m,) the normalised values at the same entries.

    exp(s / tau); the shorter side padded with dummy lines (log-value -100) until square;
    `iters` alternate normalisations, lines first. pygmtools works in the log domain; here each
    line is shifted by its maximum first, which the first (line) step cancels exactly, and the
    dummy lines, all alike, are one line counted n_dummy times: uniform after that first step.
    """
    S = np.full((n1, n2), -np.inf)
    S[rows, cols] = s_m / tau
    flip = n1 > n2
    if flip:
        S = S.T
    top = S.max(axis=1, keepdims=True)
    X = np.exp(S - np.where(np.isfinite(top), top, 0.0))
    n_dummy = S.shape[1] - S.shape[0]
    d = np.full(S.shape[1], 1.0 / S.shape[1])  # a dummy line after its first normalisation
    for it in range(iters):
        if it % 2 == 0:
            sums = X.sum(axis=1, keepdims=True)
            sums[sums == 0.0] = 1.0  # a line without pairs stays empty
            X /= sums
            d /= d.sum()
        else:
            sums = X.sum(axis=0)
            sums += n_dummy * d
            sums[sums == 0.0] = 1.0
            X /= sums
            d /= sums
    return (X.T if flip else X)[rows, cols]


def association_graph(K: np.ndarray, block_entries: int = 1 << 24) -> csr_matrix:
    """NGM's association graph: K's entries of magnitude at least EDGE_MIN, sparse (m, m).

    Messages are averaged over these edges (pygmtools normalises its 0/1 adjacency by the row
    sums). Read in blocks of rows so that a dense paper-mode K is never copied whole."""
    m = K.shape[0]
    step = max(1, block_entries // max(m, 1))
    parts = []
    for start in range(0, m, step):
        r, c = np.nonzero(np.abs(K[start : start + step]) >= EDGE_MIN)
        parts.append((r + start, c, K[r + start, c]))
    r, c, v = (np.concatenate(x) for x in zip(*parts)) if parts else ([], [], [])
    return csr_matrix((v, (r, c)), shape=(m, m))


def ngm_soft(
    K: np.ndarray, rows: np.ndarray, cols: np.ndarray, n1: int, n2: int,
    weights: NGMWeights | None = None, x0_m: np.ndarray | None = None,
) -> np.ndarray:
    """NGM's soft assignment over m pairs p = (rows[p], cols[p]) in any order. (m,).

    K: (m, m) affinity between the pairs (diagonal: node affinity). x0_m: (m,) first
    embedding, default diag(K); scaled to mean 1 as pygmtools does."""
    w = weights or packaged_weights()
    m = len(rows)
    if K.shape != (m, m) or cols.shape != (m,):
        raise SolverError(f"NGM: K must be ({m}, {m}) over {m} pairs, got {K.shape}")
    if m == 0:
        return np.zeros(0)
    x0 = np.diag(K).astype(np.float64) if x0_m is None else np.asarray(x0_m, np.float64)
    mean = float(x0.mean())
    x = (x0 / mean if mean > 1e-12 else np.ones(m))[:, None]
    A = association_graph(K)
    deg = np.diff(A.indptr)
    inv_deg = np.divide(1.0, deg, out=np.zeros(m), where=deg > 0)[:, None]
    sk = functools.partial(sinkhorn, rows=rows, cols=cols, n1=n1, n2=n2, tau=w.sk_tau,
                           iters=w.sk_iters)
    for i in range(w.n_layers):
        p = f"gnn_layer_{i}."
        x2 = inv_deg * (A @ w.mlp(p + "n_func", x)) + w.mlp(p + "n_self_func", x)
        x_sk = sk(w.linear(p + "classifier", x2)[:, 0])  # Sinkhorn embedding channel
        x = np.concatenate([x2, x_sk[:, None]], axis=1)
    return sk(w.linear("classifier", x)[:, 0])


def solve(problem: AssignmentProblem, weights: NGMWeights | None = None,
          edge_scale: float = 1.0) -> np.ndarray:
    """NGM on a candidate problem, its off-diagonal K scaled by edge_scale (verified mode's
    K carries edge affinities times a weight; NGM takes them in [0, 1]). Returns soft x (m,)."""
    K = problem.K
    if edge_scale != 1.0:
        K = K * edge_scale
        np.fill_diagonal(K, np.diag(problem.K))
    return ngm_soft(K, problem.rows, problem.cols, problem.n1, problem.n2, weights)


def solve_dense(K: np.ndarray, n1: int, n2: int, weights: NGMWeights | None = None
                ) -> np.ndarray:
    """NGM on pygmtools' dense, column-major K (pair (i, a) at a * n1 + i). Returns (n1, n2)."""
    if K.shape != (n1 * n2, n1 * n2):
        raise SolverError(f"NGM: dense K must be ({n1 * n2}, {n1 * n2}), got {K.shape}")
    cols, rows = np.divmod(np.arange(n1 * n2), n1)
    X = np.zeros((n1, n2))
    X[rows, cols] = ngm_soft(K, rows, cols, n1, n2, weights)
    return X


# ------------------------------------------------------------------ weights as a module


def encode_weights(arrays: Mapping[str, np.ndarray]) -> tuple[dict[str, tuple[int, ...]], str]:
    """Parameters -> (shapes by name, in param_names order; base64 of their float32 values)."""
    n = sum(1 for k in arrays if k.endswith(".n_func.0.weight"))
    names = param_names(n)
    blob = b"".join(np.asarray(arrays[k], dtype="<f4").tobytes() for k in names)
    return {k: tuple(int(s) for s in np.shape(arrays[k])) for k in names}, \
        base64.b64encode(blob).decode("ascii")


def decode_weights(shapes: Mapping[str, tuple[int, ...]], data: str) -> dict[str, np.ndarray]:
    """Inverse of encode_weights."""
    try:
        flat = np.frombuffer(base64.b64decode(data, validate=True), dtype="<f4")
    except ValueError as exc:  # bad base64, or not whole float32 values
        raise SolverError(f"NGM weights: the data is not float32 values in base64: {exc}"
                          ) from exc
    out, at = {}, 0
    for k, shape in shapes.items():
        size = int(np.prod(shape))
        if at + size > len(flat):
            raise SolverError("NGM weights: the data is shorter than its shapes")
        out[k] = flat[at : at + size].reshape(shape).astype(np.float64)
        at += size
    if at != len(flat):
        raise SolverError("NGM weights: the data is longer than its shapes")
    return out


def weights_module_source(arrays: Mapping[str, np.ndarray], training: Mapping[str, object]
                          ) -> str:
    """The text of a weights module like ngm_weights.py (what `solver train` writes)."""
    shapes, data = encode_weights(arrays)
    chunks = [data[k : k + 90] for k in range(0, len(data), 90)]
    lines = [
        '"""NGM weights shipped with mergesvc, written by `mergesvc solver train`: do not edit.',
        "",
        "TRAINING says how they were trained; SHAPES names each parameter; DATA holds their",
        "float32 values (little-endian, in SHAPES order) in base64 (core/solvers/ngm.py).",
        '"""',
        "",
        "TRAINING = {",
        *[f"    {k!r}: {v!r}," for k, v in training.items()],
        "}",
        "",
        "SHAPES = {",
        *[f"    {k!r}: {v!r}," for k, v in shapes.items()],
        "}",
        "",
        "DATA = (",
        *[f'    "{c}"' for c in chunks],
        ")",
        "",
    ]
    return "\n".join(lines)


@functools.cache
def packaged_weights() -> NGMWeights:
    """The weights mergesvc ships (ngm_weights.py), decoded once."""
    from mergesvc.core.solvers import ngm_weights

    return NGMWeights(decode_weights(ngm_weights.SHAPES, ngm_weights.DATA))


__all__ = [
    "EDGE_MIN",
    "SK_ITERS",
    "SK_TAU",
    "NGMWeights",
    "association_graph",
    "decode_weights",
    "encode_weights",
    "ngm_soft",
    "packaged_weights",
    "param_names",
    "sinkhorn",
    "solve",
    "solve_dense",
    "weights_module_source",
]
