"""The matching pipeline: the only place the stages are chained.

verified: candidates -> affinity K over candidate pairs -> solver -> hard assignment with
          no-match -> exact search on the candidate set -> rigid fit -> could chance explain
          it (chance.py) -> accept / reject (a problem small enough for the exact search to
          answer outright skips the solver)
paper:    node affinity (all pairs) -> dense K (pygmtools) -> solver -> Hungarian, every node
          matched (Singh & Leonard's pipeline, the baseline)

Each stage lives in its own module; K of either mode is built in affinity.py (candidate_K;
paper_node_affinity + paper_K), the candidates in candidates.py, the rigid fit in verify.py.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from mergesvc.core.affinity import (
    CandidateK,
    candidate_K,
    edge_pair_weight,
    edge_scales,
    extend_K,
    paper_K,
    paper_node_affinity,
)
from mergesvc.core.candidates import (
    Calibration,
    Candidates,
    expand_near,
    pair_scores,
    retrieve,
)
from mergesvc.core.chance import candidate_ranks, chance_log10
from mergesvc.core.config import MatchConfig, MatchMode, SolverName, match_config
from mergesvc.core.model import (
    Match,
    MatchResult,
    ObjectArrays,
    ObjectMap,
    RejectReason,
    Transform,
)
from mergesvc.core.search import multiplied_pairs
from mergesvc.core.solvers import dense, heuristic, ngm
from mergesvc.core.solvers.exact import ExactResult, solve_exact
from mergesvc.core.solvers.hungarian import harden, harden_dense, prune_negative
from mergesvc.core.solvers.margin import row_margins
from mergesvc.core.solvers.near import NearOptimal, near_optimal
from mergesvc.core.solvers.problem import UNMATCHED, AssignmentProblem, block
from mergesvc.core.threads import blas_threads
from mergesvc.core.verify import (
    RigidFit,
    align,
    consistent_subset,
    fit_about_vertical,
    fit_rigid,
    transform_points,
)
from mergesvc.core.vertical import FrameVertical, VerticalRelation, frame_vertical, relate
from mergesvc.core.windows import consensus, one_to_one, partition
from mergesvc.errors import SchemaError

log = logging.getLogger(__name__)

# problems this small get every near-optimal assignment at once (solvers/near.py)
_NEAR_MAX_ROWS = 8
_NEAR_MAX_CANDIDATES = 128


class StageTimer:
    """Wall time per stage in milliseconds, in the order the stages ran."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self._clock = clock
        self._start = clock()
        self._last = self._start
        self.ms: dict[str, float] = {}

    def lap(self, stage: str) -> None:
        now = self._clock()
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._last) * 1e3
        self._last = now

    def total(self) -> dict[str, float]:
        return {**self.ms, "total": (self._clock() - self._start) * 1e3}


@dataclass
class MatchOutcome:
    """MatchResult plus what the benchmark and the service need to look inside.

    assignment: (n1,) map index per submap node, UNMATCHED (-1) where left unmatched; after
    verification only the inliers remain. proposed: the assignment before the rigid fit.
    """

    result: MatchResult
    assignment: np.ndarray
    proposed: np.ndarray
    exact: ExactResult | None = None
    fit: RigidFit | None = None
    n_candidates: int = 0
    extra: dict[str, float] = field(default_factory=dict)


def _as_arrays(objs: ObjectMap | ObjectArrays) -> ObjectArrays:
    return objs if isinstance(objs, ObjectArrays) else objs.arrays()


def match(
    map_: ObjectMap | ObjectArrays,
    submap: ObjectMap | ObjectArrays,
    config: MatchConfig | None = None,
    clock: Callable[[], float] = time.perf_counter,
) -> MatchOutcome:
    """Match a submap against a map. See the module docstring for the two modes."""
    config = config or MatchConfig()
    timer = StageTimer(clock)
    m_arr, s_arr = _as_arrays(map_), _as_arrays(submap)
    if m_arr.dim != s_arr.dim:
        raise SchemaError(
            f"embedding dimensions differ: map has {m_arr.dim}, submap has {s_arr.dim}"
        )
    timer.lap("prepare")
    # the BLAS's threads pay off on a whole-map product only: not on an indexed map's stages
    paper = config.mode is MatchMode.PAPER
    with blas_threads(m_arr.n * s_arr.n if paper else
                      multiplied_pairs(m_arr, config.candidates, s_arr.n)):
        if paper:
            return _match_paper(m_arr, s_arr, config, timer)
        return _match_verified(m_arr, s_arr, config, timer)


# ------------------------------------------------------------------ verified mode


def _solve_candidates(
    signed: AssignmentProblem, positive: AssignmentProblem, config: MatchConfig
) -> np.ndarray:
    """Heuristic solve + no-match hardening + pruning. Returns (n1,) local col or UNMATCHED."""
    name, scfg = config.solver.name, config.solver
    if name is SolverName.RRWM:
        soft = heuristic.rrwm(positive, scfg.max_iter, scfg.rrwm_alpha, scfg.rrwm_beta)
    elif name is SolverName.SM:
        soft = heuristic.spectral(positive, scfg.max_iter)
    elif name is SolverName.IPFP:
        soft = heuristic.ipfp(signed, heuristic.spectral(positive, scfg.max_iter), scfg.max_iter)
    elif name is SolverName.NGM:  # NGM takes edge affinities in [0, 1]: undo their weight
        soft = ngm.solve(positive, edge_scale=1.0 / edge_pair_weight(positive.n1, config.affinity))
    else:  # exact: start from the node scores alone
        soft = np.diag(signed.K).copy()
    assignment = harden(signed, soft, unmatched_value=0.0)
    return prune_negative(signed, assignment)


def _match_scores(
    positive: AssignmentProblem, assignment: np.ndarray, edge_w: float
) -> dict[int, float]:
    """Per matched row, in [0, 1]: mean of its node score and of its edge agreement a_e with
    the other matched rows (node score alone when it is the only match)."""
    rows = (assignment != UNMATCHED).nonzero()[0]
    if len(rows) == 0:
        return {}
    K = block(positive.K, positive.assignment_to_indices(assignment))
    node = np.clip(K.diagonal(), 0.0, 1.0)
    if len(rows) == 1:
        return {int(rows[0]): float(node[0])}
    agree = (K.sum(axis=1) - K.diagonal()) / (edge_w * (len(rows) - 1))
    return {int(i): float(0.5 * node[k] + 0.5 * agree[k]) for k, i in enumerate(rows)}


@dataclass
class _Proposal:
    """K over one candidate set and the solver's hard answer on it (local col indices)."""

    cands: Candidates
    signed: AssignmentProblem
    positive: AssignmentProblem
    local: np.ndarray  # (n2_local,) local col -> map index
    assignment: np.ndarray  # (n1,) local col or UNMATCHED
    # the exact search's answer over these candidates when it already ran (`_exact`)
    exact: tuple[ExactResult, NearOptimal | None] | None = None

    def to_map(self, assignment: np.ndarray) -> np.ndarray:
        return np.where(assignment == UNMATCHED, UNMATCHED, self.local[assignment])


@dataclass
class _Pass:
    """The verified answer over one candidate set (map indices, not local ones)."""

    cands: Candidates
    proposed: np.ndarray  # (n1,) after the margin test, before the rigid fit
    final: np.ndarray  # (n1,) inliers of the rigid fit
    reason: RejectReason
    fit: RigidFit
    exact: ExactResult | None
    scores: dict[int, float]
    chance: float = math.nan  # core/chance.py's log10 count of an accepted fit (else nan)


def _inlier_gate(sub_xyz: np.ndarray, sigma_m: float, config: MatchConfig) -> np.ndarray:
    """(k,) residual gate: inlier_sigmas x (sigma (+) rel_tol x lever arm from the centroid)."""
    if len(sub_xyz) == 0:
        return np.zeros(0)
    lever_m = np.linalg.norm(sub_xyz - sub_xyz.mean(axis=0), axis=1)
    return config.verify.inlier_sigmas * np.hypot(sigma_m, config.affinity.edge_rel_tol * lever_m)


def _propose(
    sub: ObjectArrays,
    map_: ObjectArrays,
    cands: Candidates,
    config: MatchConfig,
    sigma_m: float,
    timer: StageTimer,
    start: np.ndarray | None = None,
    prev: _Proposal | None = None,
) -> _Proposal:
    """Affinity K over the candidates -> solver -> hard assignment with no-match.

    start: (n1,) map indices of an earlier answer, kept when it scores better here.
    prev: the proposal over the first prev.cands.m of these candidates: its K is kept."""
    if prev is not None:
        signed, positive, local = extend_K(
            CandidateK(prev.signed, prev.positive, prev.local), sub, map_, cands.rows,
            cands.map_nodes, cands.score, config.affinity, sigma_m,
            config.verify.conflict_sigmas)
    else:
        signed, positive, local = candidate_K(
            sub, map_, cands.rows, cands.map_nodes, cands.score, config.affinity, sigma_m,
            config.verify.conflict_sigmas,
        )
    timer.lap("affinity")
    if prev is not None and prev.exact is not None and prev.exact[1] is not None and \
            signed.n1 <= _NEAR_MAX_ROWS and signed.m <= _NEAR_MAX_CANDIDATES:
        # the exact search over prev's candidates stands when no assignment holding a new one
        # comes within the margin of its optimum (as the search over all of them would find,
        # or better: that one may run out of states and fall back to the branch and bound)
        near = prev.exact[1].extend(signed, _margin(config))
        best = None if near is None else near.best(prev.exact[0].nodes_expanded)
        timer.lap("exact")
        if best is not None:
            return _Proposal(cands, signed, positive, local, best.assignment, (best, near))
    seed = None
    if start is not None:
        at = np.searchsorted(local, start)
        hit = (start != UNMATCHED) & (at < len(local))
        hit[hit] = local[at[hit]] == start[hit]
        seed = np.where(hit, at, UNMATCHED)
        if not signed.is_feasible(seed):
            seed = None
    verified = config.verify.exact or config.solver.name is SolverName.EXACT
    if seed is not None and verified:
        # the exact search follows and starts from the seed (improved by its local search):
        # a second heuristic solve would only hand it another incumbent
        assignment = prune_negative(signed, seed)
    elif verified and signed.n1 <= _NEAR_MAX_ROWS and signed.m <= _NEAR_MAX_CANDIDATES:
        # small enough for the exact search to answer outright, from the node scores' own
        # assignment: the heuristic would only hand it an incumbent (and the guided step a
        # worse answer to probe)
        start = prune_negative(signed, harden(signed, signed.K.diagonal().copy(), 0.0))
        found = _exact(signed, start, config)
        assignment = found[0].assignment if found[0].score >= signed.score(start) - 1e-9 \
            else start
        timer.lap("exact")
        return _Proposal(cands, signed, positive, local, assignment, found)
    else:
        assignment = _solve_candidates(signed, positive, config)
        if seed is not None and signed.score(seed) > signed.score(assignment):
            assignment = seed
    timer.lap("solve")
    return _Proposal(cands, signed, positive, local, assignment)


def _fit(
    sub: ObjectArrays, map_: ObjectArrays, proposed: np.ndarray, sigma_m: float,
    config: MatchConfig, rel: VerticalRelation | None,
) -> RigidFit:
    """Rigid fit of the proposed matches and its tilt test: 6-DoF from 3 matches; with the
    verticals related, 4-DoF for 2 matches or for matches on a line."""
    rows = (proposed != UNMATCHED).nonzero()[0]
    sub_xyz, map_xyz = sub.position_xyz_m[rows], map_.position_xyz_m[proposed[rows]]
    gate = _inlier_gate(sub_xyz, sigma_m, config)
    v = config.verify
    least = _least_vertical_matches(sub.n, config)
    if len(rows) < v.min_matches:
        # fewer than a 6-DoF fit needs: 4-DoF about the known vertical
        if rel is None or len(rows) < least:
            return fit_rigid(sub_xyz, map_xyz, gate, v.min_matches)  # too few
        return _fit_vertical(sub_xyz, map_xyz, gate, sigma_m, rel, config,
                             min_matches=len(rows))
    # fit a mutually consistent set (greedy peeling, not a maximum clique); the rest are outliers
    keep = consistent_subset(sub_xyz, map_xyz, gate)
    n_keep = int(keep.sum())
    # fewer pairs than a 6-DoF fit needs, or pairs on a line: 4-DoF, keeping a majority of
    # the consistent pairs
    few = max(least, n_keep // 2 + 1)
    if n_keep < v.min_matches:
        if rel is None or n_keep < few:
            return RigidFit(RejectReason.RESIDUAL_TOO_LARGE, None, None, keep,
                            np.full(len(keep), np.nan), np.nan)
        fit = _fit_vertical(sub_xyz[keep], map_xyz[keep], gate[keep], sigma_m, rel, config)
        return _widen(fit, keep)
    fit = fit_rigid(sub_xyz[keep], map_xyz[keep], gate[keep], min_matches=v.min_matches,
                    sigma_floor_m=0.1 * sigma_m)
    if fit.reason is RejectReason.DEGENERATE_GEOMETRY and rel is not None and n_keep >= few:
        fit = _fit_vertical(sub_xyz[keep], map_xyz[keep], gate[keep], sigma_m, rel, config,
                            min_matches=few)
    elif fit.accepted:
        fit = _upright(fit, sub_xyz[keep], map_xyz[keep], gate[keep], rel, sigma_m, config)
    return _widen(fit, keep)


def _least_vertical_matches(n_sub: int, config: MatchConfig) -> int:
    """Matches a 4-DoF fit needs: min_matches_vertical, and at least half the submap's objects
    (2 matches out of 20 objects are no evidence)."""
    return max(config.verify.min_matches_vertical, (n_sub + 1) // 2)


def _widen(fit: RigidFit, keep: np.ndarray) -> RigidFit:
    """A fit over the pairs where keep (k,) is true, as a fit over all k (the rest outliers)."""
    if keep.all():
        return fit
    inliers = np.zeros(len(keep), dtype=bool)
    inliers[np.flatnonzero(keep)[fit.inliers]] = True
    residual = np.full(len(keep), np.nan)
    residual[keep] = fit.residual_m
    return RigidFit(fit.reason, fit.T_map_submap, fit.covariance_66, inliers, residual,
                    fit.rmse_m)


def vertical_relation(
    sub: ObjectArrays, map_: ObjectArrays, config: MatchConfig
) -> VerticalRelation | None:
    """How the two frames' verticals relate (declared, inferred or shared; see vertical.py)."""
    v = config.verify

    def one(arr: ObjectArrays) -> FrameVertical | None:
        if arr.up_xyz is None and not v.infer_vertical:
            return None
        # a map's layout is the same for every submap: its vertical is found once
        key = ("vertical", v.infer_min_objects, v.infer_max_flatness)
        if key not in arr.cache:
            arr.cache[key] = frame_vertical(arr, v.infer_min_objects, v.infer_max_flatness)
        return arr.cache[key]

    # only a submap too small to show its vertical shares the map's: a larger one whose layout
    # is not flat enough has no vertical
    share = v.share_vertical and v.infer_vertical and sub.n < v.infer_min_objects
    return relate(one(map_), one(sub), share=share)


def _mirror_fits(sub_xyz: np.ndarray, map_xyz: np.ndarray, tolerance_m: np.ndarray) -> bool:
    """Whether the mirror image of the matched submap centres fits as well: then their layout
    is too flat for distances to tell its handedness (three matches always are)."""
    centred = sub_xyz - sub_xyz.mean(axis=0)
    n = np.linalg.svd(centred, full_matrices=False)[2][-1]
    mirrored = sub_xyz - 2.0 * np.outer(centred @ n, n)
    T = align(mirrored, map_xyz)
    if T is None:
        return True
    return bool(np.all(np.linalg.norm(transform_points(T, mirrored) - map_xyz, axis=1)
                       <= tolerance_m))


def _upright(
    fit: RigidFit,
    sub_xyz: np.ndarray,
    map_xyz: np.ndarray,
    tolerance_m: np.ndarray,
    rel: VerticalRelation | None,
    sigma_m: float,
    config: MatchConfig,
) -> RigidFit:
    """Tilt test of an accepted 6-DoF fit; the fit itself, a 4-DoF one, or a rejection.

    sub_xyz, map_xyz, tolerance_m: all pairs of the fit ((k, 3), (k, 3), (k,)); only its
    inliers are judged. Declared verticals: the transform must keep up up. Otherwise, when
    the matched layout is clearly 3-D its handedness is observed and only the vertical axis
    is checked; when it is flat (its mirror image fits too: three matches always are) the
    known sign decides. A flat fit that tilts gets a second chance as a gravity-aligned 4-DoF
    fit that must keep every pair the 6-DoF fit kept (a declared vertical may drop outliers,
    down to a majority): three points nearly on a line leave the rotation about that line to
    the noise, which the vertical pins down. No vertical, no test.
    """
    v = config.verify
    if fit.T_map_submap is None or rel is None:
        return fit
    inl = fit.inliers
    if v.gravity_aligned and rel.declared and rel.signed:
        # both verticals come from the sensors: fit about them, dropping outliers down to a
        # majority as a declared vertical may (falls back to the 6-DoF fit's tilt test)
        keep = max(v.min_matches_vertical, int(inl.sum()) // 2 + 1)
        four = _fit_vertical(sub_xyz[inl], map_xyz[inl], tolerance_m[inl], sigma_m, rel, config,
                             min_matches=keep)
        if four.accepted:
            return _widen(four, inl)
    if v.max_tilt_deg is None:
        return fit
    R = fit.T_map_submap.rotation().matrix()
    flat = rel.declared or _mirror_fits(sub_xyz[inl], map_xyz[inl], tolerance_m[inl])
    judged = rel if flat else VerticalRelation(rel.up_map, rel.up_sub, False, False)
    if judged.tilt_deg(R) <= v.max_tilt_deg:
        return fit
    # a flat fit that tilts may be the noise's roll about a line of matches (three points
    # nearly in a row): refit about the vertical, keeping every pair
    if flat and rel.signed:
        # the refit must keep every pair the 6-DoF fit kept: a vertical whose sign was only
        # assumed (inferred or shared) must not force a fit onto a subset; a declared one may
        # drop outliers, down to a majority
        n_in = int(inl.sum())
        keep = max(v.min_matches, n_in // 2 + 1) if rel.declared else n_in
        four = _fit_vertical(sub_xyz[inl], map_xyz[inl], tolerance_m[inl], sigma_m, rel, config,
                             min_matches=keep)
        if four.accepted:
            return _widen(four, inl)
    return RigidFit(RejectReason.TILTED, fit.T_map_submap, fit.covariance_66, inl,
                    fit.residual_m, fit.rmse_m)


def _fit_vertical(
    sub_xyz: np.ndarray, map_xyz: np.ndarray, tolerance_m: np.ndarray, sigma_m: float,
    rel: VerticalRelation, config: MatchConfig, min_matches: int | None = None,
) -> RigidFit:
    """Gravity-aligned 4-DoF fit keeping at least min_matches inliers (default
    verify.min_matches_vertical); with only the vertical axis known, both signs are tried and
    exactly one must fit (the matches' vertical offsets tell), else `ambiguous`."""
    v = config.verify
    fits = [
        fit_about_vertical(
            sub_xyz, map_xyz, tolerance_m, sign * rel.up_sub, rel.up_map,
            np.radians(v.vertical_sigma_deg), sigma_floor_m=0.1 * sigma_m,
            min_matches=min_matches or v.min_matches_vertical,
            # a yaw needs the matches to spread across the vertical by more than the noise
            min_spread_m=sigma_m,
        )
        for sign in ((1.0,) if rel.signed else (1.0, -1.0))
    ]
    good = [f for f in fits if f.accepted]
    if len(good) > 1:
        return RigidFit(RejectReason.AMBIGUOUS, None, None, good[0].inliers,
                        good[0].residual_m, good[0].rmse_m)
    return good[0] if good else fits[0]


def _unmatch_gains(problem: AssignmentProblem, assignment: np.ndarray) -> np.ndarray:
    """(n1,) objective lost by unmatching each matched row, the others kept; nan if unmatched.

    An upper bound on the row's margin over "no match" (the others could adapt)."""
    out = np.full(problem.n1, np.nan)
    rows = (assignment != UNMATCHED).nonzero()[0]
    if len(rows) == 0:
        return out
    K = block(problem.K, problem.assignment_to_indices(assignment))
    out[rows] = K.sum(axis=0) + K.sum(axis=1) - K.diagonal()
    return out


def _margin(config: MatchConfig) -> float:
    """How far below the optimum the exact search keeps assignments: the margin test's."""
    return config.verify.margin if config.verify.margin_max_matches > 0 else 0.0


def _exact(
    signed: AssignmentProblem, incumbent: np.ndarray, config: MatchConfig
) -> tuple[ExactResult, NearOptimal | None]:
    """The optimum over the candidates: on tiny problems every assignment within the margin
    of the incumbent at once (solvers/near.py; the margin test reads its margins from the
    same set), else, or when that set grows too large, the branch and bound."""
    v = config.verify
    if signed.n1 <= _NEAR_MAX_ROWS and signed.m <= _NEAR_MAX_CANDIDATES:
        floor = max(signed.score(incumbent), 0.0)  # leaving every row unmatched scores 0
        found = near_optimal(signed, floor - max(_margin(config), 1e-9))
        if found is not None:
            near, states = found
            best = near.best(states)
            if best is not None:
                return best, near
    exact = solve_exact(signed, allow_unmatched=True, incumbent=incumbent,
                        max_nodes=v.max_nodes, time_limit_s=v.time_limit_s,
                        gap=v.optimality_gap)
    return exact, None


def _verify(
    sub: ObjectArrays,
    map_: ObjectArrays,
    prop: _Proposal,
    config: MatchConfig,
    sigma_m: float,
    timer: StageTimer,
    rel: VerticalRelation | None,
    probed: tuple[np.ndarray, RigidFit] | None = None,
) -> _Pass:
    """Exact search over the candidates -> margin test -> rigid fit -> accept or reject.

    probed: (n1,) map indices already fitted (the guided step's probe) and that fit, reused
    when the proposal to fit is the same (the fit depends on nothing else)."""
    assignment = prop.assignment
    exact = near = None
    if prop.exact is not None:
        exact, near = prop.exact
    elif config.verify.exact or config.solver.name is SolverName.EXACT:
        exact, near = _exact(prop.signed, assignment, config)
        if exact.score >= prop.signed.score(assignment) - 1e-9:
            assignment = exact.assignment
        timer.lap("exact")
    scores = _match_scores(prop.positive, assignment, edge_pair_weight(sub.n, config.affinity))
    proposed = prop.to_map(assignment)
    n_proposed = int(np.sum(proposed != UNMATCHED))
    if 0 < n_proposed <= config.verify.margin_max_matches and config.verify.margin > 0:
        # Few matches: each must beat its best alternative clearly (look-alikes in a pool).
        # a candidate at the place of the chosen map object is the same object seen twice
        # (a duplicate in the map), not an alternative configuration
        chosen_xyz = np.full((sub.n, 3), np.inf)
        m_rows = np.flatnonzero(proposed != UNMATCHED)
        chosen_xyz[m_rows] = map_.position_xyz_m[proposed[m_rows]]
        cand_xyz = map_.position_xyz_m[prop.local[prop.signed.cols]]
        dist = np.linalg.norm(cand_xyz - chosen_xyz[prop.signed.rows], axis=1)
        same = dist <= config.verify.inlier_sigmas * sigma_m
        if near is not None:
            margins = near.margins(assignment, config.verify.margin, same=same)
        else:
            margins = row_margins(prop.signed, assignment, config.verify.margin, same=same)
        # leaving the object unmatched is an alternative too (a false detection that happens
        # to fit a look-alike adds little): its gain over that must clear the margin as well
        margins = np.fmin(margins, _unmatch_gains(prop.signed, assignment))
        ambiguous = margins < config.verify.margin  # nan (unmatched) compares False
        proposed = np.where(ambiguous, UNMATCHED, proposed)
        timer.lap("margin")
    if probed is not None and np.array_equal(probed[0], proposed):
        fit = probed[1]
    else:
        fit = _fit(sub, map_, proposed, sigma_m, config, rel)
    reason = fit.reason
    needed = config.verify.min_matches
    if rel is not None:
        needed = min(needed, _least_vertical_matches(sub.n, config))
    if reason is RejectReason.TOO_FEW_MATCHES and n_proposed >= needed:
        reason = RejectReason.AMBIGUOUS
    final = proposed.copy()
    chance = math.nan
    if fit.accepted:
        rows = np.flatnonzero(proposed != UNMATCHED)
        final[rows[~fit.inliers]] = UNMATCHED
        chance, reason = _chance(sub, map_, prop.cands, final, fit, reason, config)
    if exact is not None and not exact.optimal and reason is RejectReason.VERIFIED:
        reason = RejectReason.SEARCH_INCOMPLETE
    timer.lap("verify")
    return _Pass(prop.cands, proposed, final, reason, fit, exact, scores, chance)


def _chance(sub: ObjectArrays, map_: ObjectArrays, cands: Candidates, final: np.ndarray,
            fit: RigidFit, reason: RejectReason, config: MatchConfig
            ) -> tuple[float, RejectReason]:
    """core/chance.py's count for an accepted fit's inliers (final: their map indices), and
    the reason: too_few_matches when the count is over the limit for this submap's size."""
    rows = np.flatnonzero(final != UNMATCHED)
    ranks = candidate_ranks(cands, rows, final[rows], sub.n)
    predicted = transform_points(fit.T_map_submap, sub.position_xyz_m[rows])
    chance = chance_log10(map_, sub.n, ranks, predicted, fit.residual_m[fit.inliers])
    v = config.verify
    limit = v.max_chance_log10
    if limit is not None and sub.n >= v.chance_large_objects:
        limit = min(limit, v.max_chance_log10_large)
    if limit is not None and chance > limit:
        reason = RejectReason.TOO_FEW_MATCHES
    return chance, reason


def _match_verified(
    map_: ObjectArrays, sub: ObjectArrays, config: MatchConfig, timer: StageTimer
) -> MatchOutcome:
    unmatched = np.full(sub.n, UNMATCHED, dtype=np.int64)
    windowed = sub.n > config.windows.above_objects
    cand_cfg = config.candidates
    if windowed:
        cand_cfg = cand_cfg.model_copy(
            update={"prefilter": min(cand_cfg.prefilter, config.windows.shortlist)})
    cands, calib = retrieve(sub, map_, cand_cfg, config.affinity, config.seed)
    timer.lap("candidates")
    if cands.m == 0:
        return _finish(RejectReason.NO_CANDIDATES, sub, map_, unmatched, unmatched, {}, timer)
    sigma_m, _ = edge_scales(map_, config.affinity)
    rel = vertical_relation(sub, map_, config)
    if windowed:
        return _match_windowed(map_, sub, cands, calib, config, sigma_m, timer, rel)
    result = _verified_pass(map_, sub, cands, calib, config, sigma_m, timer, rel)
    outcome = _finish(
        result.reason, sub, map_, result.final, result.proposed, result.scores, timer, result.fit
    )
    outcome.exact = result.exact
    outcome.n_candidates = result.cands.m
    outcome.extra["chance_log10"] = result.chance
    return outcome


def _verified_pass(
    map_: ObjectArrays,
    sub: ObjectArrays,
    cands: Candidates,
    calib: Calibration,
    config: MatchConfig,
    sigma_m: float,
    timer: StageTimer,
    rel: VerticalRelation | None,
) -> _Pass:
    """Solve, guided step, exact search and fit of one submap (or one window of one)."""
    prop = _propose(sub, map_, cands, config, sigma_m, timer)
    probed = None
    if config.candidates.guided:
        # Guided matching: when the solver's answer fits a rigid transform, add the map objects
        # lying where it puts each submap object (look-alike instances whose true match ranked
        # below the top-k by appearance alone) and solve again from that answer; the exact
        # search then verifies once, over the enlarged candidate set.
        first = prop.to_map(prop.assignment)
        probe = _fit(sub, map_, first, sigma_m, config, rel)
        if not probe.accepted and prop.exact is not None:
            # the optimum over the first candidates need not fit where the heuristic's answer
            # does (look-alikes whose true instances are not candidates yet): probe that too
            heuristic_answer = prop.to_map(_solve_candidates(prop.signed, prop.positive, config))
            if not np.array_equal(heuristic_answer, first):
                other = _fit(sub, map_, heuristic_answer, sigma_m, config, rel)
                if other.accepted:
                    first, probe = heuristic_answer, other
        probed = (first, probe)
        timer.lap("verify")
        if probe.accepted:
            predicted = transform_points(probe.T_map_submap, sub.position_xyz_m)
            gate = _inlier_gate(sub.position_xyz_m, sigma_m, config)
            more = expand_near(cands, sub, map_, predicted, gate, calib)
            timer.lap("candidates")
            if more.m > cands.m:
                start = first.copy()
                rows = (start != UNMATCHED).nonzero()[0]
                start[rows[~probe.inliers]] = UNMATCHED
                prop = _propose(sub, map_, more, config, sigma_m, timer, start=start,
                                prev=prop)
    return _verify(sub, map_, prop, config, sigma_m, timer, rel, probed)


def _match_windowed(
    map_: ObjectArrays,
    sub: ObjectArrays,
    cands: Candidates,
    calib: Calibration,
    config: MatchConfig,
    sigma_m: float,
    timer: StageTimer,
    rel: VerticalRelation | None,
) -> MatchOutcome:
    """A large submap in spatial windows (core/windows.py): each window solved and fitted on
    its own (an exact search on a short budget when windows.exact), then the transform most
    windows' matches agree on, every proposed match that fits it (one map object per submap
    object), the objects left placed by that transform, and one fit."""
    wcfg = match_config(config, candidates={
        "guided": config.candidates.guided and config.windows.guided}, verify={
        "exact": config.verify.exact and config.windows.exact,
        "time_limit_s": min(config.windows.time_limit_s, config.verify.time_limit_s or np.inf),
        "margin_max_matches": config.verify.margin_max_matches if config.windows.margin else 0})
    proposed = np.full(sub.n, UNMATCHED, dtype=np.int64)
    scores: dict[int, float] = {}
    hypotheses = []
    n_cands = 0
    # each row's candidates are one run of the list (retrieve sorts it by row)
    order = np.argsort(cands.rows, kind="stable")
    starts = np.searchsorted(cands.rows[order], np.arange(sub.n + 1))
    for w in partition(sub.position_xyz_m, config.windows.window_objects):
        counts = starts[w + 1] - starts[w]
        if not counts.any():
            continue
        first = np.repeat(starts[w] - np.cumsum(counts) + counts, counts)
        keep = order[first + np.arange(int(counts.sum()))]
        wc = Candidates(np.repeat(np.arange(len(w)), counts), cands.map_nodes[keep],
                        cands.affinity[keep], cands.score[keep])
        wcal = replace(calib, floor_n=calib.floor_n[w])
        res = _verified_pass(map_, sub.subset(w), wc, wcal, wcfg, sigma_m, timer, rel)
        n_cands += res.cands.m
        # a window whose matches fit (proven optimal or not) offers its transform and its
        # inliers, any other its proposal: the common transform judges them all
        got = res.final if res.fit.accepted else res.proposed
        hit = got != UNMATCHED
        proposed[w[hit]] = got[hit]
        scores.update({int(w[i]): v for i, v in res.scores.items()})
        if res.fit.accepted:
            hypotheses.append(res.fit.T_map_submap)
    rows = (proposed != UNMATCHED).nonzero()[0]
    sub_xyz, map_xyz = sub.position_xyz_m[rows], map_.position_xyz_m[proposed[rows]]
    gate = _inlier_gate(sub_xyz, sigma_m, config)
    T, inl = consensus(sub_xyz, map_xyz, gate, hypotheses)
    final = np.full(sub.n, UNMATCHED, dtype=np.int64)
    if T is not None:
        residual = np.linalg.norm(transform_points(T, sub_xyz) - map_xyz, axis=1)
        inl &= one_to_one(rows, proposed[rows], np.where(inl, residual, np.inf))
        final[rows[inl]] = proposed[rows[inl]]
        # objects whose window was not verified (or left them out): the map object the
        # common transform puts them on, when it looks like them (score >= node_threshold)
        final = _fill_by_transform(sub, map_, final, T, sigma_m, calib, config)
    timer.lap("windows")
    fit = _fit_large(sub, map_, final, sigma_m, config, rel)
    reason = fit.reason if T is not None else RejectReason.AMBIGUOUS
    chance = math.nan
    if fit.accepted:
        kept = np.flatnonzero(final != UNMATCHED)
        final[kept[~fit.inliers]] = UNMATCHED
        # objects placed by the common transform are not candidates: they rank after them
        chance, reason = _chance(sub, map_, cands, final, fit, reason, config)
    if reason is not RejectReason.VERIFIED:
        final[:] = UNMATCHED
    timer.lap("verify")
    outcome = _finish(reason, sub, map_, final, proposed, scores, timer, fit)
    outcome.n_candidates = n_cands
    outcome.extra["chance_log10"] = chance
    return outcome


def _fill_by_transform(
    sub: ObjectArrays, map_: ObjectArrays, final: np.ndarray, T: gtsam.Pose3, sigma_m: float,
    calib: Calibration, config: MatchConfig,
) -> np.ndarray:
    """(n1,) assignment with each unmatched submap object given the best-scoring free map
    object within its residual gate of where T puts it, if that scores node_threshold or
    more; best scores first, one map object each."""
    open_rows = np.flatnonzero(final == UNMATCHED)
    if len(open_rows) == 0:
        return final
    gate = _inlier_gate(sub.position_xyz_m, sigma_m, config)[open_rows]
    near = map_.kdtree.query_ball_point(
        transform_points(T, sub.position_xyz_m[open_rows]), gate)
    rows = np.repeat(open_rows, [len(v) for v in near])
    nodes = np.fromiter((b for v in near for b in v), dtype=np.int64, count=len(rows))
    taken = np.zeros(map_.n, dtype=bool)
    taken[final[final != UNMATCHED]] = True
    free = ~taken[nodes]
    rows, nodes = rows[free], nodes[free]
    if len(rows) == 0:
        return final
    _, score = pair_scores(sub, map_, rows, nodes, calib)
    good = score >= config.affinity.node_threshold
    out = final.copy()
    for p in np.flatnonzero(good)[np.argsort(-score[good], kind="stable")].tolist():
        r, b = int(rows[p]), int(nodes[p])
        if out[r] == UNMATCHED and not taken[b]:
            out[r], taken[b] = b, True
    return out


def _fit_large(
    sub: ObjectArrays, map_: ObjectArrays, proposed: np.ndarray, sigma_m: float,
    config: MatchConfig, rel: VerticalRelation | None,
) -> RigidFit:
    """`_fit` for matches already consistent with one transform (windows' consensus): no
    pairwise consistency peeling (O(k^2)), the 6-DoF fit and its tilt test."""
    rows = (proposed != UNMATCHED).nonzero()[0]
    sub_xyz, map_xyz = sub.position_xyz_m[rows], map_.position_xyz_m[proposed[rows]]
    gate = _inlier_gate(sub_xyz, sigma_m, config)
    fit = fit_rigid(sub_xyz, map_xyz, gate, min_matches=config.verify.min_matches,
                    sigma_floor_m=0.1 * sigma_m)
    if fit.accepted:
        fit = _upright(fit, sub_xyz, map_xyz, gate, rel, sigma_m, config)
    return fit


# ------------------------------------------------------------------ paper mode


def _match_paper(
    map_: ObjectArrays, sub: ObjectArrays, config: MatchConfig, timer: StageTimer
) -> MatchOutcome:
    n1, n2 = sub.n, map_.n
    A = paper_node_affinity(sub, map_, config.affinity)
    timer.lap("node_affinity")
    sigma_m, radius_m = edge_scales(map_, config.affinity)
    K = paper_K(A, sub, map_, sigma_m, radius_m)
    timer.lap("affinity")
    exact = None
    if config.solver.name is SolverName.EXACT:
        problem = AssignmentProblem.dense(dense.column_major_to_row_major(K, n1, n2), n1, n2)
        del K
        exact = solve_exact(
            problem,
            allow_unmatched=False,
            max_nodes=config.verify.max_nodes,
            time_limit_s=config.verify.time_limit_s,
        )
        assignment = exact.assignment
        soft = A
    else:
        if config.solver.name is SolverName.NGM:
            soft = ngm.solve_dense(K, n1, n2)
        else:
            soft = dense.solve_dense(config.solver.name.value, K, n1, n2, config.solver.max_iter)
        del K
        assignment = harden_dense(soft)
    timer.lap("solve")
    rows = np.flatnonzero(assignment != UNMATCHED)
    scores = {int(i): float(soft[i, assignment[i]]) for i in rows}
    sigma_fit = np.full(len(rows), np.inf)  # paper mode verifies nothing: no residual gate
    fit = fit_rigid(
        sub.position_xyz_m[rows],
        map_.position_xyz_m[assignment[rows]],
        sigma_fit,
        min_matches=3,
        sigma_floor_m=0.1 * sigma_m,
    )
    timer.lap("transform")
    outcome = _finish(
        RejectReason.NOT_VERIFIED, sub, map_, assignment, assignment, scores, timer, fit
    )
    outcome.exact = exact
    outcome.n_candidates = n1 * n2
    return outcome


# ------------------------------------------------------------------ result


def _finish(
    reason: RejectReason,
    sub: ObjectArrays,
    map_: ObjectArrays,
    assignment: np.ndarray,
    proposed: np.ndarray,
    scores: dict[int, float],
    timer: StageTimer,
    fit: RigidFit | None = None,
) -> MatchOutcome:
    matches = [
        Match(
            submap_object=sub.ids[i],
            map_object=map_.ids[int(assignment[i])],
            score=round(scores.get(int(i), 0.0), 6),
        )
        for i in np.flatnonzero(assignment != UNMATCHED)
    ]
    transform = covariance = None
    if fit is not None and fit.T_map_submap is not None and fit.covariance_66 is not None:
        T = fit.T_map_submap
        q = T.rotation().toQuaternion()
        transform = Transform(
            translation=tuple(float(x) for x in T.translation()),
            quaternion_wxyz=(q.w(), q.x(), q.y(), q.z()),
        )
        covariance = fit.covariance_66.tolist()
    accepted = reason in (RejectReason.VERIFIED, RejectReason.NOT_VERIFIED)
    result = MatchResult(
        accepted=accepted and (reason is RejectReason.VERIFIED or bool(matches)),
        reason=reason,
        matches=matches,
        transform=transform,
        covariance=covariance,
        timings_ms={k: round(v, 3) for k, v in timer.total().items()},
    )
    return MatchOutcome(result=result, assignment=assignment, proposed=proposed, fit=fit)
