"""The global pose graph: nodes (robot-session frames, or their keyframes joined by odometry)
aligned by inter-robot factors, solved with GTSAM's GncLMOptimizer and the truncated-least-squares
loss; the objects of aligned frames are fused in fusion.py.

Guarantees (docs/pose_graph.md gives the rules in full): known inliers and bridges are never
judged (rule 1); a factor GNC flags is a confirmed outlier only where two other paths contradict
it, else it is ambiguous and kept (rules 2, 3); the poses are a least-squares solve without the
confirmed outliers (rule 4). Folding (rule 5) and freezing (rule 6) are policies it holds
(core/folding.py, core/freezing.py). `optimize` returns its last solution again while nothing
changed. Pure: no I/O.
"""

from __future__ import annotations

import copy
import logging
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.calibration import (
    Component,
    scale_covariance,
    scale_covariances,
    updated_scale,
    variance_components,
)
from mergesvc.core.chi2 import chi2_quantile
from mergesvc.core.config import GraphConfig
from mergesvc.core.connectivity import UnionFind, two_edge_connected
from mergesvc.core.connectivity import bridges as find_bridges
from mergesvc.core.folding import Folding, Measurement
from mergesvc.core.frames import FrameId, KeyframeId, frame_name
from mergesvc.core.freezing import Freezing
from mergesvc.core.graph_factor import GraphFactor
from mergesvc.core.graph_job import Optimizer, SolveJob, build, pose_arrays, run_job
from mergesvc.core.graph_start import initial_poses
from mergesvc.core.model import Factor, FactorStatus
from mergesvc.core.poses import as_pose3, check_covariance, pose3_from_model
from mergesvc.core.rigid import RigidTest, chain_shape, chains, rigid_test
from mergesvc.errors import InputError, SolverError, one_line

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GraphSolution:
    """Result of PoseGraph.optimize.

    T_anchor_frame: pose of each node (frame or keyframe) of the anchor's component in the
    anchor frame (p_anchor = T p_frame). covariance_66: its marginal covariance (6, 6), GTSAM
    order (rotation, translation), in the tangent space at the estimate (right perturbation);
    missing when Marginals failed, empty when optimize(marginals=False). components: connected
    components (node lists), the anchor's first.
    weights: GNC weight of each factor of the anchor's component (1.0 for known inliers; a
    folded factor's is its representative's, rule 5), folded factors included.
    outlier_factor_ids: confirmed outliers (retract them); ambiguous_factor_ids: flagged by GNC
    but not identifiable (kept); unchecked_factor_ids: bridges, which nothing can contradict.
    errors: 0.5 * squared Mahalanobis residual of each factor solved at the final estimate
    (not the settled factors between two frozen nodes, rule 6, which are not solved).
    frozen_nodes: how many nodes are fixed at the poses of an earlier solve (rule 6).
    rigid_tests: each odometry chain's rigid-before-bent test (core/rigid.py), when on.
    folded: folded factor -> its representative (rule 5), in the anchor's component.
    gnc_ran: some factor was judged (not all known inliers); gnc_skipped: judged by the
    least-squares gate alone (every factor within the TLS threshold: GNC not iterated).
    """

    anchor: str
    T_anchor_frame: dict[str, gtsam.Pose3]
    covariance_66: dict[str, np.ndarray]
    components: list[list[str]]
    weights: dict[str, float]
    outlier_factor_ids: list[str]
    ambiguous_factor_ids: list[str]
    unchecked_factor_ids: list[str]
    errors: dict[str, float]
    folded: dict[str, str] = field(default_factory=dict)
    gnc_ran: bool = False
    gnc_skipped: bool = False
    marginals_error: str | None = None
    frozen_nodes: int = 0
    rigid_tests: tuple[RigidTest, ...] = ()

    @property
    def disconnected_frames(self) -> list[str]:
        """Frames not connected to the anchor (no pose in the anchor frame)."""
        return [f for comp in self.components[1:] for f in comp]

    @property
    def inlier_factor_ids(self) -> list[str]:
        out = set(self.outlier_factor_ids)
        return [f for f in self.weights if f not in out]


class PoseGraph:
    """Nodes (frames "{robot}/{session}" or keyframes "{robot}/{session}#{k}") joined by
    factors T_a_b (p_a = T_a_b p_b). The API says "frame" for a node of either kind.

    The anchor is the node given, else the first node added; it holds the gauge (a prior).
    Nodes map to gtsam keys symbol('f', i) in insertion order.
    """

    def __init__(self, anchor: str | None = None, config: GraphConfig | None = None) -> None:
        self.config = config or GraphConfig()
        self._frames: dict[str, int] = {}
        self._names: list[str] = []  # node names by index: factors hold these string objects
        self._factors: dict[str, GraphFactor] = {}  # the solved ones (folded: self._folding)
        self._anchor = anchor
        self._revision = 0  # bumped by every change: optimize() reuses a solution while equal
        self._solved: tuple[tuple[int, str, GraphConfig, bool], GraphSolution] | None = None
        self._cold_next = False  # a factor was removed: the next solve starts cold
        self._folding = Folding(self._factors)  # rule 5
        self._freezing = Freezing()  # rule 6
        # calibration: noise group -> sigma scale per axis (6,), applied when solving
        self._scales: dict[str, np.ndarray] = {}
        self._components: dict[str, Any] = {}  # the last estimate's sums, per group
        self._recalibrated = False  # the last solve moved a scale: solve again
        self._calibrated_at = 0  # factors in the graph at the last calibration
        self._solved_scales: dict[str, np.ndarray] = {}
        # False: solve with the scales as they are (a restart solving what it restored; the
        # graph then counts as calibrated at its size, when it holds scales)
        self.calibrating = True
        # runs each optimisation (core/graph_job.py): here, or in another process
        self.optimizer: Optimizer = run_job
        if anchor is not None:
            self.add_frame(anchor)

    # the policies' state, as the solve reads it
    @property
    def _frozen(self) -> dict[str, gtsam.Pose3]:
        return self._freezing.frozen

    @property
    def _sealed(self) -> dict[str, float]:
        return self._freezing.sealed

    @property
    def _deps(self) -> dict[str, list[str]]:
        return self._folding.deps

    @property
    def _fused(self) -> dict[str, Measurement]:
        return self._folding.fused

    # -- building ----------------------------------------------------------------------------

    @property
    def anchor(self) -> str | None:
        return self._anchor

    @anchor.setter
    def anchor(self, frame: str) -> None:
        self._freezing.check_anchor(frame)
        self.add_frame(frame)
        if frame != self._anchor:
            self._anchor = frame
            self._revision += 1

    @property
    def frames(self) -> list[str]:
        """Every node (frame or keyframe), in insertion order."""
        return list(self._frames)

    @property
    def nodes(self) -> list[str]:
        """Every node, in insertion order (the same as `frames`)."""
        return list(self._frames)

    def has_node(self, name: str) -> bool:
        return name in self._frames

    @property
    def revision(self) -> int:
        """A counter that changes whenever a node, a factor or the anchor is added or removed."""
        return self._revision

    def factor_nodes(self, factor_id: str) -> tuple[str, str, bool]:
        """(node a, node b, known_inlier) of a factor, folded or not; InputError if unknown."""
        f = self._factors.get(factor_id)
        if f is not None:
            return f.frame_a, f.frame_b, f.known_inlier
        if factor_id in self._folding.folded:
            a, b = self._folding.folded[factor_id][:2]
            return a, b, False
        raise InputError(f"unknown factor {factor_id!r}")

    @property
    def factor_ids(self) -> list[str]:
        """Every factor held: the solved ones in order of arrival, then the folded ones."""
        return [*self._factors, *self._folding.folded]

    def representative(self, factor_id: str) -> str | None:
        """The factor a folded factor is folded into (rule 5); None for a solved one.
        InputError if unknown."""
        rep = self._folding.representative(factor_id)
        if rep is None and factor_id not in self._factors:
            raise InputError(f"unknown factor {factor_id!r}")
        return rep

    @property
    def frozen_count(self) -> int:
        """How many nodes are frozen (rule 6)."""
        return len(self._freezing.frozen)

    @property
    def folded_count(self) -> int:
        """How many factors are folded (held but not solved, rule 5)."""
        return len(self._folding.folded)

    def key(self, frame: str) -> int:
        """The gtsam key of a frame."""
        try:
            return gtsam.symbol("f", self._frames[frame])
        except KeyError:
            raise InputError(f"unknown frame {frame!r}") from None

    def add_frame(self, frame: str) -> bool:
        """Register a frame (also done by add_factor); True if new."""
        if not isinstance(frame, str) or not frame:
            raise InputError("frame must be a non-empty string")
        if frame in self._frames:
            return False
        self._frames[frame] = len(self._frames)
        self._names.append(frame)
        self._revision += 1
        if self._anchor is None:
            self._anchor = frame
        return True

    def add_factor(
        self,
        factor_id: str,
        frame_a: str,
        frame_b: str,
        T_a_b: gtsam.Pose3 | np.ndarray,
        covariance_66: np.ndarray | Sequence[Sequence[float]],
        *,
        known_inlier: bool = False,
        group: str | None = None,
    ) -> bool:
        """Add the measurement T_a_b (pose of frame b in frame a) with its (6, 6) covariance in
        GTSAM Pose3 tangent order (rotation rad, translation m). True if new; replaying the same
        factor is a no-op, reusing an id for a different factor raises InputError.
        known_inlier: never judged by GNC (e.g. a factor an operator confirmed). group: its
        noise group (e.g. one robot's odometry), whose covariances the calibration scales
        together (None: never scaled)."""
        if not isinstance(factor_id, str) or not factor_id:
            raise InputError("factor_id must be a non-empty string")
        if frame_a == frame_b:
            raise InputError(f"factor {factor_id}: frame_a and frame_b are both {frame_a!r}")
        T = as_pose3(T_a_b, f"factor {factor_id}: T_a_b")
        C = check_covariance(covariance_66, f"factor {factor_id}: covariance_66")
        old = self._factors.get(factor_id)
        if old is None and factor_id in self._folding.folded:
            old = self._folding.unfold(factor_id)
        if old is not None:
            if (
                (old.frame_a, old.frame_b, old.known_inlier)
                == (frame_a, frame_b, bool(known_inlier))
                and (old.T_a_b is None  # sealed (rule 6): its measurement is not held
                     or (old.T_a_b.equals(T, 1e-9)
                         and np.allclose(old.covariance_66, C, rtol=1e-9, atol=0)))
            ):
                return False
            raise InputError(f"factor id {factor_id!r} is already used by a different factor")
        self.add_frame(frame_a)
        self.add_frame(frame_b)
        # the node names the graph holds already (one string per node, not one per factor)
        self._insert(GraphFactor(factor_id, self._names[self._frames[frame_a]],
                                 self._names[self._frames[frame_b]], T, C, bool(known_inlier),
                                 group))
        self._revision += 1
        return True

    def _insert(self, f: GraphFactor) -> None:
        """A factor into the graph: folded into the factor it agrees with (rule 5), or solved."""
        found = self._folding.find(f, self.config, self._freezing.sealed)
        if found is not None:
            self._folding.fold(f, *found)
            return
        self._factors[f.factor_id] = f
        self._folding.solved(f)

    def _measurement(self, g: GraphFactor) -> Measurement:
        """What the solve uses of a solved factor: its own measurement, or fused with those
        folded into it (rule 5)."""
        return self._folding.measurement(g)

    def add_factor_model(
        self, factor: Factor, *, known_inlier: bool = False, keyframe_nodes: bool | None = None,
        group: str | None = None,
    ) -> bool:
        """Add a wire `Factor` (skipped, returning False, if its status is retracted).

        keyframe_nodes: None (default) ties keyframe nodes "{frame}#{k}" when the factor
        carries keyframes and the session frames otherwise; True always ties keyframes (a
        factor without keyframes then ties keyframe 0 of both sessions: their frames' origins,
        the service's graph); False always the frames (keyframes ignored)."""
        if factor.status is FactorStatus.RETRACTED:
            return False
        fa = FrameId(factor.robot_a, factor.session_a)
        fb = FrameId(factor.robot_b, factor.session_b)
        if keyframe_nodes is None:
            keyframe_nodes = factor.keyframe_a is not None
        if keyframe_nodes:
            a = str(KeyframeId(fa, factor.keyframe_a or 0))
            b = str(KeyframeId(fb, factor.keyframe_b or 0))
        else:
            a, b = frame_name(fa.robot, fa.session), frame_name(fb.robot, fb.session)
        return self.add_factor(
            factor.factor_id, a, b, pose3_from_model(factor.T_a_b), factor.covariance,
            known_inlier=known_inlier, group=group,
        )

    def remove_factor(self, factor_id: str) -> bool:
        """Drop a factor (e.g. retracted); its frames stay. True if it was present. The factors
        folded into it go back to the graph (rule 5: folded again, or solved); a representative
        keeps the folded ones' measurements as they were carried when they folded (their
        odometry may be sealed since, rule 6). Raising, it changes nothing."""
        if self._folding.representative(factor_id) is not None:
            self._folding.remove(factor_id)  # (a failure changes nothing)
        else:
            f = self._factors.get(factor_id)
            if f is None:
                return False
            undo = self._checkpoint() if self._folding.releases(f) else None
            try:
                del self._factors[factor_id]
                for back in self._folding.release(f):
                    self._insert(back)
            except BaseException:
                if undo is not None:
                    undo()
                raise
            self._freezing.sealed.pop(factor_id, None)
        self._revision += 1
        self._cold_next = True  # the last solution may hold what this factor pulled
        return True

    def _checkpoint(self) -> Callable[[], None]:
        """A function that puts the factors (solved and folded) back as they are now."""
        factors, folding = dict(self._factors), self._folding.checkpoint()

        def undo() -> None:
            self._factors.clear()
            self._factors.update(factors)
            folding()

        return undo

    # -- structure ---------------------------------------------------------------------------

    def components(self, limit: int | None = None) -> list[list[str]]:
        """Connected components, frames in insertion order; the anchor's component first.
        limit: only the first `limit` nodes added (and the factors between them)."""
        names = list(self._frames)[:limit]
        uf = UnionFind(len(names))
        for f in self._factors.values():
            a, b = self._frames[f.frame_a], self._frames[f.frame_b]
            if a < len(names) and b < len(names):
                uf.union(a, b)
        groups: dict[int, list[str]] = defaultdict(list)
        for i, name in enumerate(names):
            groups[uf.find(i)].append(name)
        comps = list(groups.values())
        if self._anchor is not None:
            comps.sort(key=lambda c: self._anchor not in c)  # stable: others keep their order
        return comps

    # -- solving -----------------------------------------------------------------------------

    def optimize(self, anchor: str | None = None, *, marginals: bool = True) -> GraphSolution:
        """Solve the component of `anchor` (default: the graph's anchor) by the rules of
        docs/pose_graph.md.

        marginals=False skips the marginal covariances (covariance_66 stays empty): they cost
        about as much as the GNC solve on long keyframe chains, and the service does not use
        them. With frozen nodes (rule 6) only the live nodes get one.

        Returns the previous solution (the same object) when neither the graph, the anchor nor
        the config changed since. Raises InputError for an unknown anchor (or another anchor
        than the frozen nodes' frame), SolverError when GTSAM fails."""
        anchor = self._anchor_of(anchor)
        key = (self._revision, anchor, self.config, marginals)
        if self._solved is not None and self._solved[0] == key:
            return self._solved[1]
        return self._remember(key, self._solve(anchor, marginals))

    def _remember(self, key: tuple[Any, ...] | None, sol: GraphSolution) -> GraphSolution:
        """`sol` is the last solution (the next solve starts from it, warm); returned again for
        `key` (None: for no key, a step of `settle`)."""
        self._solved = (key, sol)
        self._cold_next = False
        return sol

    def settle(self, step: int | None = None) -> GraphSolution:
        """Solve a graph that was loaded at once (a restart's restore) as it grew: the first
        `step` nodes added, then `step` more at a time (default: half of max_live_nodes), each
        solve warm-started from the last, then the whole graph (`optimize(marginals=False)`).
        With max_live_nodes (rule 6) the old nodes freeze on the way as they did in the live
        run, and no solve holds much more than max_live_nodes + step nodes; without it, one
        solve of the whole graph."""
        anchor = self._anchor_of(None)
        cap = self.config.max_live_nodes
        step = step if step is not None else max(1, cap // 2)
        if not isinstance(step, int) or isinstance(step, bool) or step <= 0:
            raise InputError(f"settle: step must be a positive whole number, not {step!r}")
        if cap > 0:  # (every prefix holds the anchor)
            for limit in self._freezing.settle_limits(self._frames[anchor], len(self._frames),
                                                      step):
                self._remember(None, self._solve(anchor, False, limit=limit))
        return self.optimize(marginals=False)

    def _anchor_of(self, anchor: str | None) -> str:
        anchor = anchor if anchor is not None else self._anchor
        if anchor is None:
            raise InputError("the pose graph is empty: no anchor frame")
        if anchor not in self._frames:
            raise InputError(f"unknown anchor frame {anchor!r}")
        self._freezing.check_anchor(anchor)
        return anchor

    def _solve(self, anchor: str, marginals: bool, limit: int | None = None) -> GraphSolution:
        """One solve; with calibration on, solved again (warm) while a scale moved by more
        than `calibration.resolve_change`, at most `calibration.resolves` times."""
        sol = self._solve_once(anchor, marginals, limit)
        for _ in range(self.config.calibration.resolves if self._recalibrated else 0):
            self._remember(None, sol)
            self._calibrated_at = 0  # a re-solve calibrates again
            sol = self._solve_once(anchor, marginals, limit)
            if not self._recalibrated:
                break
        return sol

    def set_noise_scale(self, group: str, sigma_scale: Sequence[float] | float) -> None:
        """Scale a group's covariances per axis (sigma, GTSAM order; one number: every axis)
        from the next solve on; the calibration goes on from there for the groups it
        calibrates."""
        s = np.broadcast_to(np.asarray(sigma_scale, dtype=np.float64), (6,)).copy()
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise InputError(f"noise scale must be positive, got {s.tolist()}")
        self._scales[group] = s
        self._revision += 1

    @property
    def noise_scales(self) -> dict[str, np.ndarray]:
        """Each noise group's sigma scale per axis (GTSAM order), as the calibration left it
        (groups it never estimated are absent: scale 1)."""
        return {g: s.copy() for g, s in self._scales.items()}

    def calibrated(self) -> dict[str, tuple[np.ndarray, Component | None]]:
        """Each group the calibration estimates (`calibration.groups`) that has a scale: its
        sigma scale per axis and the sums of the last calibration (None when the scale was
        restored or set, not estimated since): the redundancy its residuals checked each
        axis with, from which `scale_standard_error` gives the scale's precision."""
        groups, comps = self.config.calibration.groups, self._components  # one read of each
        return {g: (s.copy(), copy.deepcopy(comps.get(g)))
                for g, s in list(self._scales.items()) if g.split(":", 1)[0] in groups}

    def scaled_covariance(self, factor_id: str) -> np.ndarray:
        """A solved factor's covariance as the solve uses it (its group's scale applied;
        fused with its folded ones, rule 5). InputError if unknown or sealed."""
        f = self._factors.get(factor_id)
        if f is None or f.T_a_b is None:
            raise InputError(f"no solved factor {factor_id!r}")
        _, C = self._measurement(f)
        s = self._scales.get(f.group) if f.group is not None else None
        return C if s is None else scale_covariance(C, s)

    def _calibrate(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                   groups: list[str | None]) -> None:
        """One variance-component step (core/calibration.py) on the final solve; sets
        `_recalibrated` when a scale moved enough to solve again."""
        cal = self.config.calibration
        self._recalibrated = False
        if not any(g is not None for g in groups):
            return
        try:
            comps = variance_components(graph, values, groups, cal)
        except SolverError as exc:
            log.warning("noise calibration skipped: %s", exc)
            return
        for g, comp in comps.items():
            if g.split(":", 1)[0] not in cal.groups:
                continue
            old = self._scales.get(g, np.ones(6))
            new = updated_scale(old, comp, cal)
            self._scales[g] = new
            if np.max(np.abs(np.log(new / old))) > np.log1p(cal.resolve_change):
                self._recalibrated = True
        self._components = comps

    @property
    def solved_noise_scales(self) -> dict[str, np.ndarray]:
        """The noise scales the last solution was solved with (the calibration may have moved
        them since): what a restart needs to solve the same graph the same way."""
        return {g: s.copy() for g, s in self._solved_scales.items()}

    def _solve_once(self, anchor: str, marginals: bool,
                    limit: int | None = None) -> GraphSolution:
        self._solved_scales = {g: s.copy() for g, s in self._scales.items()}
        if limit is not None and self._frames[anchor] >= limit:
            raise InputError(f"the first {limit} nodes do not hold the anchor {anchor!r}")
        comps = self.components(limit)
        comps.sort(key=lambda c: anchor not in c)
        comp = comps[0]
        local = {f: i for i, f in enumerate(comp)}
        frozen, sealed = self._freezing.frozen, self._freezing.sealed
        deps = self._folding.deps  # rule 5: representative -> its folded factors
        live = [n for n in comp if n not in frozen]
        # the component's factors; rules 1 and 3 are judged on all of them (a frozen part
        # still says which factors are bridges and which close loops twice over)
        every = [f for f in self._factors.values() if f.frame_a in local and f.frame_b in local]
        edges = [(local[f.frame_a], local[f.frame_b]) for f in every]
        # the factors solved: all of them, or with frozen nodes (rule 6) those with a live end
        # (and any not yet sealed); a frozen end is held fixed by a prior at its frozen pose
        solved = [j for j, f in enumerate(every) if f.factor_id not in sealed
                  or f.frame_a not in frozen or f.frame_b not in frozen]
        facs = [every[j] for j in solved]
        boundary = sorted({n for f in facs for n in (f.frame_a, f.frame_b) if n in frozen},
                          key=self._frames.__getitem__)
        cfg = self.config

        # Rule 1: bridges (and user-confirmed factors) are known inliers.
        bridges_all = find_bridges(len(comp), edges)
        bridges = {i for i, j in enumerate(solved) if j in bridges_all}
        known = {i for i, f in enumerate(facs) if i in bridges or f.known_inlier}

        seeds = {n: frozen[n] for n in boundary}
        if anchor not in frozen or not boundary:
            seeds[anchor] = gtsam.Pose3()
        measured = [self._measurement(f) for f in facs]
        covs = np.array([C for _, C in measured]).reshape(-1, 6, 6)
        by_group: dict[str, list[int]] = defaultdict(list)
        for i, f in enumerate(facs):
            if f.group is not None and f.group in self._scales:
                by_group[f.group].append(i)
        for g, idx in by_group.items():  # each group's scale, on all its factors at once
            covs[idx] = scale_covariances(covs[idx], self._scales[g])
        initial = self._initial_values(anchor, seeds, live, facs)
        job = SolveJob(
            np.array([self.key(n) for n in seeds], dtype=np.uint64),
            pose_arrays(list(seeds.values())), cfg.anchor_sigma,
            np.array([(self.key(f.frame_a), self.key(f.frame_b)) for f in facs],
                     dtype=np.uint64).reshape(-1, 2),
            pose_arrays([T for T, _ in measured]), covs,
            np.zeros(0, dtype=np.uint64), np.zeros((0, 4, 4))).with_initial(initial)
        graph, _ = build(job)
        m = len(seeds)  # factor i is graph index m + i

        # Rule 2: GNC with the TLS loss.
        gnc_ran = len(known) < len(facs)
        least_squares: gtsam.Values | None = None  # converged over every factor, if solved
        gnc_skipped = False
        if gnc_ran and cfg.least_squares_gate:
            least_squares = self.optimizer(replace(job, what="least-squares")).values()
            barc = 0.5 * chi2_quantile(cfg.inlier_probability, 6)  # GTSAM's cost threshold
            gnc_skipped = all(graph.at(m + i).error(least_squares) < barc
                              for i in range(len(facs)) if i not in known)
        if gnc_skipped:
            assert least_squares is not None
            estimate = least_squares
            w = np.ones(len(facs))
        elif gnc_ran:
            res = self.optimizer(replace(
                job, what="GNC pose-graph", gnc_probability=cfg.inlier_probability,
                gnc_known=(*range(m), *(m + i for i in sorted(known)))))
            estimate = res.values()
            assert res.weights is not None
            w = res.weights
        else:
            estimate = initial
            w = np.ones(len(facs))

        # Rule 3: confirm a flagged factor only if unflagged factors join its nodes twice over,
        # the known inliers contracted (paths may share them: they cannot be wrong).
        flagged = [i for i in range(len(facs)) if w[i] < cfg.outlier_weight]
        weight = {f.factor_id: w[i] for i, f in enumerate(facs)}
        super_uf = UnionFind(len(comp))
        for j, f in enumerate(every):
            if f.known_inlier:
                super_uf.union(*edges[j])
        group = [super_uf.find(i) for i in range(len(comp))]
        kept = [  # a factor's folded ones (rule 5) are parallel paths of it: one copy says so
            (group[edges[j][0]], group[edges[j][1]])
            for j, f in enumerate(every)
            if not f.known_inlier
            and weight.get(f.factor_id, sealed.get(f.factor_id, 1.0))
            >= cfg.outlier_weight
            for _ in range(2 if f.factor_id in deps else 1)
        ]
        twice = two_edge_connected(len(comp), [(u, v) for u, v in kept if u != v])
        outliers = [
            i for i in flagged
            if twice[group[local[facs[i].frame_a]]] == twice[group[local[facs[i].frame_b]]]
        ]
        ambiguous = [i for i in flagged if i not in set(outliers)]
        if flagged:
            log.info(
                "GNC flagged %d factor(s): outliers %s, ambiguous %s",
                len(flagged),
                [facs[i].factor_id for i in outliers],
                [facs[i].factor_id for i in ambiguous],
            )

        # Rule 4: final least squares without the confirmed outliers.
        final = gtsam.NonlinearFactorGraph()
        for j in range(m):
            final.add(graph.at(j))
        rejected = set(outliers)
        for i in range(len(facs)):
            if i not in rejected:
                final.add(graph.at(m + i))
        if not (gnc_skipped and not rejected):  # else: `final` is `graph`, solved already
            estimate = self.optimizer(job.without(sorted(rejected), "pose-graph")
                                      .with_initial(estimate)).values()
        self._recalibrated = False
        n_solved = final.size()
        if not self.calibrating and self._scales:  # scales given (restored) for this graph
            self._calibrated_at = max(self._calibrated_at, n_solved)
        if cfg.calibration.enabled and self.calibrating and (
                n_solved >= (1.0 + cfg.calibration.every_growth) * self._calibrated_at):
            self._calibrated_at = n_solved
            self._calibrate(final, estimate, [None] * m + [
                facs[i].group for i in range(len(facs)) if i not in rejected])

        tests: list[RigidTest] = []
        if cfg.rigid_chains is not None:  # (the marginals stay those of the bendable graph)
            estimate, tests = self._keep_rigid(job, estimate, facs, rejected, frozen)

        def with_folded(fid: str) -> list[str]:  # a factor, then those folded into it
            return [fid, *deps.get(fid, ())]

        poses = {n: frozen[n] if n in frozen else estimate.atPose3(self.key(n)) for n in comp}
        covs, marg_err = self._marginals(final, estimate, live) if marginals else ({}, None)
        verdict = dict.fromkeys((facs[i].factor_id for i in sorted(bridges)), "unchecked")
        verdict.update((facs[i].factor_id, "ambiguous") for i in ambiguous)
        verdict.update((facs[i].factor_id, "outlier") for i in outliers)
        held = {f.factor_id: (1.0 if w[i] == 1.0 else float(w[i]),  # one 1.0 for most
                              verdict.get(f.factor_id, ""),
                              float(graph.at(m + i).error(estimate)))
                for i, f in enumerate(facs)}
        # a sealed factor (rule 6: kept by GNC, or a known inlier) keeps its weight; unchecked
        # while it is a bridge
        was = {f.factor_id: (v, "unchecked" if j in bridges_all else "", 0.0)
               for j, f in enumerate(every) if (v := sealed.get(f.factor_id)) is not None}
        every_v = {**was, **held}  # the frozen part's verdicts first, as it was solved first

        def of(kind: str) -> list[str]:
            return [d for fid, v in every_v.items() if v[1] == kind for d in with_folded(fid)]

        sol = GraphSolution(
            anchor=anchor,
            T_anchor_frame=poses,
            covariance_66=covs,
            components=comps,
            weights={d: v[0] for fid, v in every_v.items() for d in with_folded(fid)},
            outlier_factor_ids=[fid for fid, v in every_v.items() if v[1] == "outlier"],
            ambiguous_factor_ids=of("ambiguous"),
            unchecked_factor_ids=of("unchecked"),
            errors={fid: v[2] for fid, v in held.items()},
            gnc_ran=gnc_ran,
            gnc_skipped=gnc_skipped,
            folded={d: fid for fid in every_v for d in deps.get(fid, ())},
            marginals_error=marg_err,
            frozen_nodes=len(comp) - len(live),
            rigid_tests=tuple(tests),
        )
        if cfg.max_live_nodes > 0:  # rule 6
            sealed_now = self._freezing.update(
                anchor, live, poses, facs, held, lambda n: group[local[n]],
                lambda n: twice[group[local[n]]],
                [n for i in ambiguous for n in (facs[i].frame_a, facs[i].frame_b)],
                cfg.max_live_nodes)
            for f in sealed_now:
                if f.factor_id not in deps:  # never solved again: its ends are enough
                    self._factors[f.factor_id] = f.sealed()
        return sol

    def _keep_rigid(self, job: SolveJob, estimate: gtsam.Values, facs: list[GraphFactor],
                    rejected: set[int], frozen: dict[str, gtsam.Pose3]
                    ) -> tuple[gtsam.Values, list[RigidTest]]:
        """Rigid before bent (core/rigid.py, rule 7): each chain without frozen nodes tested
        against the solution; those kept rigid solved again, together, held to their odometry's
        shape (their chain factors' covariances shrunk). Returns the estimate and each chain's
        test."""
        cfg = self.config
        prefix = cfg.rigid_chains or ""

        def is_chain(g: str | None) -> bool:
            return g is not None and g.startswith(prefix)

        kept = [f for i, f in enumerate(facs) if i not in rejected]
        solved = {f.factor_id: (gtsam.Pose3(job.between_poses[i]), job.between_covs[i])
                  for i, f in enumerate(facs) if i not in rejected}

        def measured(f: GraphFactor) -> tuple[gtsam.Pose3, np.ndarray]:
            return solved[f.factor_id]

        placed = {n: frozen[n] if n in frozen else estimate.atPose3(self.key(n))
                  for f in kept for n in (f.frame_a, f.frame_b)}
        rigid: set[str] = set()
        tests = []
        for chain in chains(kept, is_chain):
            if any(n in frozen for n in chain):
                continue
            try:
                t = rigid_test(chain_shape(chain, kept, measured, is_chain), kept, measured,
                               placed, cfg.rigid_probability)
            except (SolverError, RuntimeError) as exc:  # the chain is solved as it bent
                log.warning("rigid test of the chain of %s failed, left bent: %s", chain[0],
                            one_line(exc))
                continue
            log.debug("chain of %s (%d nodes, %d factors out): rigid %.1f, bent %.1f: %s",
                      chain[0], t.nodes, t.factors, t.rigid_cost, t.bent_cost,
                      "rigid" if t.rigid else "bent")
            tests.append(t)
            if t.rigid:
                rigid.update(chain)
        if not rigid:
            return estimate, tests
        covs = job.between_covs.copy()
        for i, f in enumerate(facs):
            if is_chain(f.group) and f.frame_a in rigid and f.frame_b in rigid:
                covs[i] = covs[i] * cfg.rigid_shrink
        held = replace(job, between_covs=covs).without(
            sorted(rejected), "pose-graph (rigid chains)").with_initial(estimate)
        try:
            return self.optimizer(held).values(), tests
        except SolverError as exc:  # the bent solution stands: rule 7 is not worth a solve
            log.warning("solve with the rigid chains failed, the bent solution kept: %s",
                        one_line(exc))
            return estimate, [replace(t, rigid=False) for t in tests]

    def _initial_values(self, anchor: str, seeds: dict[str, gtsam.Pose3], live: list[str],
                        facs: list[GraphFactor]) -> gtsam.Values:
        """The seeds (the anchor, the frozen nodes the factors touch) at their poses, every live
        node chained from them along a spanning tree of the factors (core/graph_start.py). Warm
        start: a node the last solution (same anchor) placed starts there, except after a
        factor was removed (the last poses may hold what that factor pulled)."""
        last = self._solved[1] if self._solved is not None else None
        warm = (self.config.warm_start and last is not None and last.anchor == anchor
                and not self._cold_next)
        values = gtsam.Values()
        for node, T in initial_poses(seeds, live, facs,
                                     last.T_anchor_frame if warm else {}).items():
            values.insert(self.key(node), T)
        return values

    def _marginals(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, comp: list[str]
    ) -> tuple[dict[str, np.ndarray], str | None]:
        try:
            marginals = gtsam.Marginals(graph, values)
            out = {}
            for f in comp:
                C = np.asarray(marginals.marginalCovariance(self.key(f)), dtype=np.float64)
                out[f] = 0.5 * (C + C.T)
            return out, None
        except RuntimeError as exc:  # e.g. an indeterminant linear system
            log.warning("pose-graph marginals failed: %s", exc)
            return {}, one_line(exc)


__all__ = ["GraphSolution", "PoseGraph"]
