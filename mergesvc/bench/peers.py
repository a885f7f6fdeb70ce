"""KISS-Matcher (MIT-SPARK, run from its own package: the `peers` extra) as a method beside
mergesvc's in `bench match --peer` and `bench generalize`.

The peer is given what a user of it would give it: each submap object's most cosine-similar
map objects as candidate pairs (the cosines computed as mergesvc computes its own: float32
products over the map's cached norms). KISS-Matcher prunes them (ROBIN's max core) and solves
the transform (GNC-TLS); each submap object is then matched to its candidate lying nearest
where that transform puts it, within a gate, one map object each. Its answer is accepted when
its solver calls the transform valid and it holds MIN_MATCHES matches (what a 6-DoF transform
needs; fewer are no evidence of a place). The default settings (`KissSettings`) are the best of
a sweep (docs/benchmarks/peers.md).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.model import (
    Match,
    MatchResult,
    ObjectArrays,
    ObjectMap,
    RejectReason,
    Submap,
    Transform,
)
from mergesvc.core.pipeline import MatchOutcome
from mergesvc.core.solvers.problem import UNMATCHED
from mergesvc.core.threads import blas_threads
from mergesvc.errors import InputError

KISS_METHOD = "kiss-matcher"
MIN_MATCHES = 3


@dataclass(frozen=True)
class KissSettings:
    """top_k: candidate pairs per submap object, by cosine; noise_m: KISS-Matcher's voxel
    size, from which it scales its pruning and solver noise bounds (its clamping at 1 m off);
    gate_m: how far from where the transform puts a submap object its match may lie. (`bench
    match --help` states these defaults.)"""

    top_k: int = 1
    noise_m: float = 2.0
    gate_m: float = 6.0


def load_kiss() -> Any:
    """The kiss_matcher module; InputError saying how to install it when it is absent."""
    try:
        import kiss_matcher
    except ImportError as e:
        raise InputError(
            "KISS-Matcher is not installed: pip install 'mergesvc[peers]' (the kiss-matcher "
            "package) to run the peer") from e
    return kiss_matcher


def kiss_available() -> bool:
    """Whether the peer can run here."""
    try:
        load_kiss()
    except InputError:
        return False
    return True


def kiss_outcome(
    map_: ObjectMap | ObjectArrays, sub: Submap | ObjectArrays,
    settings: KissSettings | None = None, clock: Callable[[], float] = time.perf_counter,
) -> MatchOutcome:
    """KISS-Matcher's answer as a pipeline outcome (timings_ms["total"]: candidates, the
    peer's pruning and solve, and the matching, from the arrays)."""
    km = load_kiss()
    cfg = settings or KissSettings()
    m = map_ if isinstance(map_, ObjectArrays) else map_.arrays()
    s = sub if isinstance(sub, ObjectArrays) else sub.arrays()
    with blas_threads(s.n * m.n):  # the BLAS threads mergesvc's own match would use
        return _kiss(km, m, s, cfg, clock)


def _kiss(km: Any, m: ObjectArrays, s: ObjectArrays, cfg: KissSettings,
          clock: Callable[[], float]) -> MatchOutcome:
    t0 = clock()
    norms = np.where(m.norms_n > 0, m.norms_n, 1.0)
    S = (s.unit_rows().astype(np.float32) @ m.embeddings_nd.T) / norms[None, :]
    k = min(cfg.top_k, m.n)
    top = np.argpartition(-S, k - 1, axis=1)[:, :k]
    rows, cols = np.repeat(np.arange(s.n), k), top.ravel()
    src = s.position_xyz_m[rows].astype(np.float32)
    tgt = m.position_xyz_m[cols].astype(np.float32)
    matcher = km.KISSMatcher(km.KISSMatcherConfig(voxel_size=cfg.noise_m,
                                                  enable_noise_bound_clamping=False))
    sol = matcher.prune_and_solve(list(src.reshape(-1, 3, 1)), list(tgt.reshape(-1, 3, 1)))
    assignment = np.full(s.n, UNMATCHED, dtype=np.int64)
    transform = None
    if sol.valid:
        R = np.asarray(sol.rotation, dtype=np.float64)
        t = np.asarray(sol.translation, dtype=np.float64).ravel()
        residual = np.linalg.norm(src @ R.T + t - tgt, axis=1)
        taken = np.zeros(m.n, dtype=bool)
        for p in np.argsort(residual, kind="stable").tolist():
            if residual[p] > cfg.gate_m:
                break
            r, c = int(rows[p]), int(cols[p])
            if assignment[r] == UNMATCHED and not taken[c]:
                assignment[r], taken[c] = c, True
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        transform = Transform(translation=(float(t[0]), float(t[1]), float(t[2])),
                              quaternion_wxyz=(float(w), float(x), float(y), float(z)))
    hit = np.flatnonzero(assignment != UNMATCHED)
    matches = [Match(submap_object=s.ids[i], map_object=m.ids[int(assignment[i])],
                     score=round(float(S[i, assignment[i]]), 6)) for i in hit.tolist()]
    accepted = bool(sol.valid) and len(matches) >= MIN_MATCHES
    result = MatchResult(
        accepted=accepted,
        reason=RejectReason.VERIFIED if accepted else RejectReason.TOO_FEW_MATCHES,
        matches=matches, transform=transform, covariance=None,
        timings_ms={"total": round((clock() - t0) * 1e3, 3)})
    return MatchOutcome(result=result, assignment=assignment, proposed=assignment.copy())


__all__ = ["KISS_METHOD", "MIN_MATCHES", "KissSettings", "kiss_available", "kiss_outcome",
           "load_kiss"]
