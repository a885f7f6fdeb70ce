"""Paper mode: pygmtools on the dense K over all n1*n2 node pairs (faithful baseline).

pygmtools' K is column-major: assignment (i, a) sits at index a * n1 + i.
"""

from __future__ import annotations

import functools
from types import ModuleType

import numpy as np

from mergesvc.errors import SolverError

# pygmtools keeps a process-wide default backend; every call here names its backend instead of
# changing that default for whoever else imports pygmtools.
_BACKEND = "numpy"


@functools.cache
def _pygm() -> ModuleType:
    """pygmtools, imported on first use: it pulls in aiohttp and networkx (~0.3 s), and only
    paper mode needs it."""
    import pygmtools

    return pygmtools


def build_dense_K(
    node_aff_n1n2: np.ndarray,
    edges1: np.ndarray,
    lengths1: np.ndarray,
    edges2: np.ndarray,
    lengths2: np.ndarray,
    sigma: float,
) -> np.ndarray:
    """pygmtools.utils.build_aff_mat with the paper's node affinity and Gaussian edge kernel.

    edges*: (ne, 2) undirected i < j pairs; lengths*: (ne,) their lengths in metres.
    Returns K (n1*n2, n1*n2), column-major.
    """
    n1, n2 = node_aff_n1n2.shape

    def directed(edges: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        conn = np.concatenate([edges, edges[:, ::-1]]).astype(np.int64)
        feat = np.concatenate([lengths, lengths])[:, None].astype(np.float64)
        return conn, feat

    conn1, feat1 = directed(edges1, lengths1)
    conn2, feat2 = directed(edges2, lengths2)
    index1 = np.arange(n1, dtype=np.float64)[:, None]
    index2 = np.arange(n2, dtype=np.float64)[:, None]

    def node_fn(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:  # precomputed, batched
        return node_aff_n1n2[None, :, :]

    pygm = _pygm()
    return pygm.utils.build_aff_mat(
        index1, feat1, conn1, index2, feat2, conn2,
        n1=np.array([n1]), ne1=np.array([len(conn1)]),
        n2=np.array([n2]), ne2=np.array([len(conn2)]),
        node_aff_fn=node_fn,
        edge_aff_fn=functools.partial(pygm.utils.gaussian_aff_fn, sigma=sigma, backend=_BACKEND),
        backend=_BACKEND,
    )


def solve_dense(name: str, K: np.ndarray, n1: int, n2: int, max_iter: int = 50) -> np.ndarray:
    """Run a pygmtools solver on dense K. Returns the soft (n1, n2) matrix."""
    pygm = _pygm()
    fns = {"rrwm": pygm.rrwm, "sm": pygm.sm, "ipfp": pygm.ipfp}
    if name not in fns:
        raise SolverError(f"no pygmtools solver {name!r} (have {', '.join(fns)})")
    with np.errstate(divide="ignore", invalid="ignore"):  # ipfp divides 0/0 on flat K
        X = fns[name](K, np.array([n1]), np.array([n2]), max_iter=max_iter, backend=_BACKEND)
    X = np.asarray(X).reshape(n1, n2)
    if not np.all(np.isfinite(X)):
        raise SolverError(f"pygmtools {name} returned non-finite values")
    return X


def column_major_to_row_major(K: np.ndarray, n1: int, n2: int) -> np.ndarray:
    """Reorder pygmtools' K (index a*n1+i) to AssignmentProblem.dense order (index i*n2+a)."""
    perm = (np.arange(n1)[:, None] + n1 * np.arange(n2)[None, :]).ravel()
    return K[np.ix_(perm, perm)]
