"""Global graph stage: poses aligned by a pose graph of inter-robot factors, solved with GTSAM's
GncLMOptimizer and the truncated-least-squares loss (Yang et al., "Graduated Non-Convexity for
Robust Spatial Perception", RA-L 2020). The objects of aligned frames are fused in fusion.py.

Nodes are names: robot-session frames "{robot}/{session}" (one pose per session), or keyframes
"{robot}/{session}#{k}" (frames.KeyframeId: one pose per keyframe of a session, joined by the
vehicle's odometry, added as known inliers). The merge service uses keyframes only.

Outlier rules (a factor can only be judged against other factors that close a loop with it):
  1. The anchor prior, every factor marked `known_inlier` (odometry, operator-confirmed) and
     every bridge factor (removing it splits its component) are known inliers: nothing in the
     graph can contradict a bridge, and a known inlier is never doubted, so GNC must not weigh
     them.
  2. Every other factor gets a GNC TLS weight; weight < `outlier_weight` flags it. Least
     squares over every factor comes first (from the warm start): when every factor to judge
     is within the TLS threshold there, that solution is a minimum of the TLS cost with every
     weight 1 and GNC is not iterated (GTSAM's GNC would start its schedule again from the
     residuals at the initial values, about six full solves for the same verdict on a long
     mission's graph). Otherwise GNC runs from the initial values as before.
  3. A flagged factor is a confirmed outlier only if its two nodes stay joined by at least two
     paths of unflagged factors that share no factor other than known inliers (paths may share
     odometry: it cannot be wrong; computed as 2-edge-connectivity with the known-inlier
     factors contracted). Then keeping it would need at least two other factors to be wrong
     instead of one, so rejecting it is the minimum-outlier explanation. Otherwise (e.g. one
     inconsistent triangle, or two closures between two odometry chains that disagree) the
     choice is arbitrary: the factor is reported as ambiguous, kept, and the service should
     wait for more factors. With keyframe nodes this is rule 3 of the frame-level graph: the
     odometry chains contracted, each session is one node again.
  4. Poses and marginals come from a final Levenberg-Marquardt solve over the prior and every
     factor but the confirmed outliers, started from the GNC estimate (the least-squares
     solution of rule 2 already is that solve when GNC was skipped).

  5. Folding (opt-in: `GraphConfig.fold_hops` > 0): a new factor (not a known inlier) whose two
     ends are each within `fold_hops` known-inlier factors of the two ends of a factor g
     already solved, and which agrees with g (its measurement carried to g's ends along the
     odometry, covariances propagated to first order, the difference to g's measurement within
     the chi-square quantile `inlier_probability`, 6 dof), where that odometry is known well
     (what it adds to the covariance, whitened by the factor's own, at most `fold_drift`: where
     it drifts more, the factor corrects it and is solved), is *folded* into g: held, listed
     and reported, but not a factor of the solve. g is solved with its own measurement fused
     with the carried ones (information-weighted mean, summed information), so what they
     measured still counts and a majority of agreeing closures still outweighs a wrong one in
     GNC. A robot that sees the same objects again and again adds a closure per keyframe that
     says what the graph knows already (the 20-robot soak stream, 3,200 submaps: 4,981 of 7,472
     closures fold, the solved factors 10,550 -> 5,568, the solve's peak memory 66 -> 47 MB),
     so the solve grows more with the places seen than with the time spent there. Off in the
     merge service by default: on KITTI-00 with visual odometry (its drift larger than its
     covariance says) one seed of three lost half its factors in force (docs/benchmarks.md).
     A folded factor shares g's weight (ambiguous or unchecked with it) and counts as a
     parallel path of g in rule 3. When g is a confirmed outlier, g alone is reported: removing
     it sends the folded ones back to the graph (folded again, or solved), and the next solve
     judges them on their own (they agreed with a wrong factor, but a correct one may also
     have been within the test). A factor that disagrees is solved and judged as any other.
     The approximation: a carried measurement's covariance includes the odometry it was
     carried along, which the graph also holds (that correlation is ignored).

  6. Freezing (opt-in: `GraphConfig.max_live_nodes` > 0): a node freezes at its solved pose
     once max_live_nodes nodes have joined the anchor's component in later solves than it did
     (the oldest first; a session that joins late, on one closure nothing can check yet, stays
     live until later closures can judge it), and only when it is placed beyond doubt: joined to
     the anchor twice over by closures GNC kept, odometry contracted (rule 3's structure), and
     no ambiguous closure touches its odometry chain: no node freezes on a single closure, on
     GNC's arbitrary pick between two that disagree, or where a doubtful closure still pulls
     (rule 4 keeps ambiguous closures in the solve; frozen, the pull could not be undone).
     Such nodes stay live as long as that lasts: the bound is soft. Later solves hold a
     frozen node fixed where a factor joins it to a live node (a prior at its frozen pose,
     `anchor_sigma`: treated as exact) and leave out the settled factors between two frozen
     nodes (known inliers and closures GNC kept: they keep the weight of the last solve that
     held them; ambiguous, outlying and unchecked closures stay in the solve and
     are judged again; a sealed factor's measurement is no longer held, and the same id
     added again with the same ends is taken as a replay). So a long mission's solve
     stays the size of its live part (the 20-robot soak: a graph of thousands of keyframes, a
     solve of about a thousand) while a closure to an old place still ties the new part to it.
     Rules 1 and 3 are still decided on every factor of the component (pure graph structure,
     cheap): a frozen part's closures still make bridges and confirm outliers as before.
     What it gives up: a closure no longer moves frozen nodes (a frozen stretch keeps the
     drift it had), and removing a factor does not move them back. Off by default in
     PoseGraph; the merge service bounds its graph. `settle()` solves a graph loaded at once
     (a restart) in insertion order, so that no solve holds the whole graph and the old nodes
     freeze much as they did live (at other moments: near, not equal, poses).

`optimize` returns its last solution again while nothing changed (no node, factor or anchor
added or removed since): callers may call it after every change without paying twice.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from scipy.linalg import eigh
from scipy.stats import chi2

from mergesvc.core.calibration import scale_covariance, updated_scale, variance_components
from mergesvc.core.config import GraphConfig
from mergesvc.core.connectivity import UnionFind, two_edge_connected
from mergesvc.core.connectivity import bridges as find_bridges
from mergesvc.core.frames import FrameId, KeyframeId, frame_name
from mergesvc.core.model import Factor, FactorStatus
from mergesvc.core.poses import as_pose3, pose3_from_model
from mergesvc.core.poses import compose_with_covariance as _compose
from mergesvc.core.poses import inverse_with_covariance as _inverse
from mergesvc.errors import InputError, SolverError, one_line

log = logging.getLogger(__name__)

# Symmetry tolerance of covariance inputs, relative to the largest entry.
_SYM_RTOL = 1e-9


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


def _check_covariance(C: Any, name: str) -> np.ndarray:
    """A valid covariance as a read-only float64 array: `C` itself when it is one already
    (read-only, owning its data, exactly symmetric: a long mission's graph shares its
    odometry's arrays; whoever made it must not make it writable again), else a symmetrised
    copy."""
    S = np.asarray(C, dtype=np.float64)
    if S.shape != (6, 6) or not np.all(np.isfinite(S)):
        raise InputError(f"{name} must be a finite (6, 6) matrix")
    if np.abs(S - S.T).max() > _SYM_RTOL * max(np.abs(S).max(), 1e-300):
        raise InputError(f"{name} must be symmetric")
    # shared only when nobody can write to it: read-only, owning its data, exactly symmetric
    shared = (S is C and not S.flags.writeable and S.base is None
              and np.array_equal(S, S.T))
    if not shared:
        S = 0.5 * (S + S.T)
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InputError(f"{name} must be positive definite") from None
    S.setflags(write=False)
    return S


_TRIU = np.triu_indices(6)


def _pack(T: gtsam.Pose3, C: np.ndarray) -> np.ndarray:
    """A measurement in 28 float64s: translation, quaternion (w, x, y, z), the covariance's
    upper triangle."""
    q = T.rotation().toQuaternion()
    return np.concatenate([np.asarray(T.translation(), dtype=np.float64),
                           [q.w(), q.x(), q.y(), q.z()], C[_TRIU]])


def _unpack(v: np.ndarray) -> tuple[gtsam.Pose3, np.ndarray]:
    T = gtsam.Pose3(gtsam.Rot3.Quaternion(*v[3:7]), v[:3].copy())
    C = np.zeros((6, 6))
    C[_TRIU] = v[7:]
    C = C + np.triu(C, 1).T
    C.setflags(write=False)
    return T, C


def _fuse(items: Sequence[tuple[gtsam.Pose3, np.ndarray]]) -> tuple[gtsam.Pose3, np.ndarray]:
    """Measurements of one relative pose, fused by GTSAM: each a prior on one pose, solved by
    Levenberg-Marquardt from the first (the minimum of the summed squared Mahalanobis errors,
    as the pose graph would weigh them as parallel factors), with its marginal covariance."""
    key = gtsam.symbol("x", 0)
    graph = gtsam.NonlinearFactorGraph()
    for T, C in items:
        graph.add(gtsam.PriorFactorPose3(key, T, gtsam.noiseModel.Gaussian.Covariance(
            np.array(C, dtype=np.float64), False)))
    initial = gtsam.Values()
    initial.insert(key, items[0][0])
    estimate = _levenberg_marquardt(graph, initial, "fusion")
    try:
        cov = np.asarray(gtsam.Marginals(graph, estimate).marginalCovariance(key),
                         dtype=np.float64)
    except RuntimeError as exc:
        raise SolverError(f"fusion marginals failed: {exc}") from exc
    return estimate.atPose3(key), 0.5 * (cov + cov.T)


# --------------------------------------------------------------------------------------------
# Pose graph
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Factor:
    factor_id: str
    frame_a: str
    frame_b: str
    T_a_b: gtsam.Pose3 | None  # None once sealed (rule 6): never solved again
    covariance_66: np.ndarray | None
    known_inlier: bool
    group: str | None = None  # its noise group (calibration), None: not calibrated


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
        self._factors: dict[str, _Factor] = {}
        self._anchor = anchor
        self._revision = 0  # bumped by every change: optimize() reuses a solution while equal
        self._solved: tuple[tuple[int, str, GraphConfig, bool], GraphSolution] | None = None
        self._cold_next = False  # a factor was removed: the next solve starts cold
        # rule 5: folded factor -> (it, its representative); representative -> its folded
        # (node a, node b, representative, measurement packed: _pack, group): a long mission holds
        # thousands, so each is one small array rather than a Pose3 and a 6x6 matrix
        self._folded: dict[str, tuple[str, str, str, np.ndarray, str | None]] = {}
        self._deps: dict[str, list[str]] = {}
        # representative -> its measurement fused with its folded ones'
        self._fused: dict[str, tuple[gtsam.Pose3, np.ndarray]] = {}
        # node -> ids of the solved factors at it: known inliers, and the others (rule 5 only:
        # kept once folding was asked for, built then from the factors)
        self._known_at: dict[str, list[str]] = defaultdict(list)
        self._closures_at: dict[str, list[str]] = defaultdict(list)
        self._at_kept = False
        # rule 6: frozen node -> its pose in the anchor frame (the anchor it was solved with);
        # a settled factor between two frozen nodes -> its weight in the last solve that held it
        self._frozen: dict[str, gtsam.Pose3] = {}
        self._frozen_anchor: str | None = None
        self._sealed: dict[str, float] = {}
        # live node -> how many nodes had joined the anchor's component once it had; how many now
        self._joined: dict[str, int] = {}
        # calibration: noise group -> sigma scale per axis (6,), applied when solving
        self._scales: dict[str, np.ndarray] = {}
        self._components: dict[str, Any] = {}  # the last estimate's sums, per group
        self._recalibrated = False  # the last solve moved a scale: solve again
        self._solved_scales: dict[str, np.ndarray] = {}
        # False: solve with the scales as they are (a restart solving what it restored)
        self.calibrating = True
        if anchor is not None:
            self.add_frame(anchor)

    # -- building ----------------------------------------------------------------------------

    @property
    def anchor(self) -> str | None:
        return self._anchor

    @anchor.setter
    def anchor(self, frame: str) -> None:
        self._check_anchor(frame)
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
        if factor_id in self._folded:
            a, b = self._folded[factor_id][:2]
            return a, b, False
        raise InputError(f"unknown factor {factor_id!r}")

    @property
    def factor_ids(self) -> list[str]:
        """Every factor held: the solved ones in order of arrival, then the folded ones."""
        return [*self._factors, *self._folded]

    def representative(self, factor_id: str) -> str | None:
        """The factor a folded factor is folded into (rule 5); None for a solved one.
        InputError if unknown."""
        if factor_id in self._folded:
            return self._folded[factor_id][2]
        if factor_id not in self._factors:
            raise InputError(f"unknown factor {factor_id!r}")
        return None

    @property
    def frozen_count(self) -> int:
        """How many nodes are frozen (rule 6)."""
        return len(self._frozen)

    def _check_anchor(self, frame: str) -> None:
        if self._frozen and frame != self._frozen_anchor:
            raise InputError(f"{len(self._frozen)} nodes are frozen in the frame of "
                             f"{self._frozen_anchor!r}: the anchor cannot be {frame!r}")

    @property
    def folded_count(self) -> int:
        """How many factors are folded (held but not solved, rule 5)."""
        return len(self._folded)

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
        C = _check_covariance(covariance_66, f"factor {factor_id}: covariance_66")
        old = self._factors.get(factor_id)
        if old is None and factor_id in self._folded:
            old = self._unfold(factor_id)
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
        self._insert(_Factor(factor_id, self._names[self._frames[frame_a]],
                             self._names[self._frames[frame_b]], T, C, bool(known_inlier),
                             group))
        self._revision += 1
        return True

    def _insert(self, f: _Factor) -> None:
        """A factor into the graph: folded into the factor it agrees with (rule 5), or solved."""
        found = self._representative_for(f) if not f.known_inlier else None
        if found is not None:
            rep, carried = found
            fused = _fuse([self._measurement(self._factors[rep]), carried])  # before any change
            self._folded[f.factor_id] = (f.frame_a, f.frame_b, rep,
                                         _pack(f.T_a_b, f.covariance_66), f.group)
            self._deps.setdefault(rep, []).append(f.factor_id)
            self._fused[rep] = fused
            return
        self._factors[f.factor_id] = f
        if self._at_kept:
            self._index_at(f)

    def _index_at(self, f: _Factor) -> None:
        at = self._known_at if f.known_inlier else self._closures_at
        at[f.frame_a].append(f.factor_id)
        at[f.frame_b].append(f.factor_id)

    def _unfold(self, factor_id: str) -> _Factor:
        """A folded factor as it was added."""
        a, b, _, packed, group = self._folded[factor_id]
        return _Factor(factor_id, a, b, *_unpack(packed), False, group)

    def _measurement(self, g: _Factor) -> tuple[gtsam.Pose3, np.ndarray]:
        """What the solve uses of a solved factor: its own measurement, or fused with those
        folded into it (rule 5)."""
        return self._fused.get(g.factor_id, (g.T_a_b, g.covariance_66))

    def _refuse(self, rep: str) -> None:
        """The representative's fused measurement made again from its folded ones (after one
        left), each carried to its ends again along the odometry (which has not changed: a
        removed known inlier takes every folded factor out first, remove_factor)."""
        g = self._factors[rep]
        deps = self._deps.get(rep)
        if not deps:
            self._deps.pop(rep, None)
            self._fused.pop(rep, None)
            return
        items = [(g.T_a_b, g.covariance_66)]
        for d in deps:
            f = self._unfold(d)
            near_a = self._near(f.frame_a, self.config.fold_hops)
            near_b = self._near(f.frame_b, self.config.fold_hops)
            _, n, o = min((near_a[n][0] + near_b[o][0], n, o)
                          for n, o in ((g.frame_a, g.frame_b), (g.frame_b, g.frame_a))
                          if n in near_a and o in near_b)
            items.append(self._carry(f, g, near_a[n], near_b[o], n)[:2])
        self._fused[rep] = _fuse(items)

    def _take_folded(self, ids: list[str]) -> list[_Factor]:
        """These folded factors out of their representatives (whose fused measurements are
        made again), as they were added."""
        out, reps = [], set()
        for d in ids:
            out.append(self._unfold(d))
            rep = self._folded.pop(d)[2]
            self._deps[rep].remove(d)
            reps.add(rep)
        for rep in reps:
            self._refuse(rep)
        return out

    def _near(self, node: str, hops: int) -> dict[str, tuple[int, gtsam.Pose3, np.ndarray]]:
        """The nodes at most `hops` known-inlier factors from `node`: node -> (hops, pose in
        `node`'s frame, its 6x6 covariance composed along the path, first order)."""
        out = {node: (0, gtsam.Pose3(), np.zeros((6, 6)))}
        todo = [node]
        for h in range(1, hops + 1):
            nxt = []
            for n in todo:
                _, T_n, S_n = out[n]
                for fid in self._known_at.get(n, ()):
                    k = self._factors[fid]
                    if k.T_a_b is None:  # sealed (rule 6): not carried along
                        continue
                    m, T_step, C_step = ((k.frame_b, k.T_a_b, k.covariance_66) if k.frame_a == n
                                         else (k.frame_a, *_inverse(k.T_a_b, k.covariance_66)))
                    if m not in out:
                        out[m] = (h, *_compose(T_n, S_n, T_step, C_step))
                        nxt.append(m)
            todo = nxt
        return out

    def _representative_for(self, f: _Factor) -> tuple[str, tuple[gtsam.Pose3,
                                                                   np.ndarray]] | None:
        """The solved factor g that `f` folds into (rule 5), with f's measurement carried to g's
        ends (T, covariance, in g's direction): of the factors with their ends near f's, the
        nearest; `f` folds if the odometry between is known well enough (fold_drift) and it
        agrees with g's measurement (fused, if g holds folded ones)."""
        hops = self.config.fold_hops
        if hops <= 0 or f.frame_a not in self._frames or f.frame_b not in self._frames:
            return None
        if not self._at_kept:  # the first fold asked for: index the factors at their nodes
            for g in self._factors.values():
                self._index_at(g)
            self._at_kept = True
        near_a = self._near(f.frame_a, hops)
        near_b = self._near(f.frame_b, hops)
        best: tuple[int, str, str, str] | None = None  # (hops, factor, its end near a, near b)
        for n, (h_n, _, _) in near_a.items():
            for gid in self._closures_at.get(n, ()):
                if gid in self._sealed:  # not solved again (rule 6): nothing to fold into
                    continue
                g = self._factors[gid]
                o = g.frame_b if g.frame_a == n else g.frame_a
                if o in near_b and (best is None or h_n + near_b[o][0] < best[0]):
                    best = (h_n + near_b[o][0], gid, n, o)
        if best is None:
            return None
        _, gid, n, o = best
        g = self._factors[gid]
        T, S, drift = self._carry(f, g, near_a[n], near_b[o], n)
        if drift > self.config.fold_drift:
            return None
        T_g, C_g = self._measurement(g)
        e = np.asarray(gtsam.Pose3.Logmap(T_g.between(T)), dtype=np.float64)
        d2 = float(e @ np.linalg.solve(C_g + S, e))
        if d2 >= float(chi2.ppf(self.config.inlier_probability, 6)):
            return None
        return gid, (T, S)

    @staticmethod
    def _carry(f: _Factor, g: _Factor, at_a: tuple[int, gtsam.Pose3, np.ndarray],
               at_b: tuple[int, gtsam.Pose3, np.ndarray],
               n: str) -> tuple[gtsam.Pose3, np.ndarray, float]:
        """f's measurement carried to g's ends n (near f's a) and o (near f's b), in g's
        direction: (T, covariance, drift). at_a / at_b: n's and o's pose and covariance in
        f.a's / f.b's frame (_near). drift: the largest eigenvalue of what the odometry adds to
        the covariance, whitened by f's own (first order, S = S_own + odometry): large, and f
        says something about the odometry between its ends and g's that folding would lose."""
        _, T_an, S_an = at_a
        _, T_bo, S_bo = at_b
        zero = np.zeros((6, 6))
        T_na, S_na = _inverse(T_an, S_an)
        T, S = _compose(*_compose(T_na, S_na, f.T_a_b, f.covariance_66), T_bo, S_bo)  # n->a->b->o
        _, S_own = _compose(*_compose(T_na, zero, f.T_a_b, f.covariance_66), T_bo, zero)
        drift = float(eigh(S - S_own, S_own, eigvals_only=True).max())
        if g.frame_a != n:
            T, S = _inverse(T, S)  # g's direction
        return T, 0.5 * (S + S.T), drift

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
        folded into it go back to the graph (rule 5: folded again, or solved)."""
        if factor_id in self._folded:
            self._take_folded([factor_id])
            self._revision += 1
            self._cold_next = True  # its representative's fused measurement moved
            return True
        f = self._factors.pop(factor_id, None)
        if f is None:
            return False
        at = self._known_at if f.known_inlier else self._closures_at
        for node in (f.frame_a, f.frame_b) if self._at_kept else ():
            at[node].remove(factor_id)
            if not at[node]:
                del at[node]
        self._fused.pop(factor_id, None)
        self._sealed.pop(factor_id, None)
        deps = self._deps.pop(factor_id, [])
        back = [self._unfold(d) for d in deps]
        for d in deps:
            del self._folded[d]
        if f.known_inlier:  # folded factors may have been carried along it: judged again
            back += self._take_folded(list(self._folded))
        for unfolded in back:
            self._insert(unfolded)
        self._revision += 1
        self._cold_next = True  # the last solution may hold what this factor pulled
        return True

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
        """Solve the component of `anchor` (default: the graph's anchor); see the module rules.

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
            start = max(len(self._frozen) + step, self._frames[anchor] + 1)
            for limit in range(start, len(self._frames), step):
                self._remember(None, self._solve(anchor, False, limit=limit))
        return self.optimize(marginals=False)

    def _anchor_of(self, anchor: str | None) -> str:
        anchor = anchor if anchor is not None else self._anchor
        if anchor is None:
            raise InputError("the pose graph is empty: no anchor frame")
        if anchor not in self._frames:
            raise InputError(f"unknown anchor frame {anchor!r}")
        self._check_anchor(anchor)
        return anchor

    def _solve(self, anchor: str, marginals: bool, limit: int | None = None) -> GraphSolution:
        """One solve; with calibration on, solved again (warm) while a scale moved by more
        than `calibration.resolve_change`, at most `calibration.resolves` times."""
        sol = self._solve_once(anchor, marginals, limit)
        for _ in range(self.config.calibration.resolves if self._recalibrated else 0):
            self._remember(None, sol)
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
        frozen, sealed = self._frozen, self._sealed
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

        graph = gtsam.NonlinearFactorGraph()
        prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, cfg.anchor_sigma)
        seeds = {n: frozen[n] for n in boundary}
        if anchor not in frozen or not boundary:
            seeds[anchor] = gtsam.Pose3()
        for n, T in seeds.items():
            graph.add(gtsam.PriorFactorPose3(self.key(n), T, prior_noise))
        m = graph.size()  # factor i is graph index m + i
        for f in facs:
            graph.add(self._between(f))
        initial = self._initial_values(anchor, seeds, live, facs)

        # Rule 2: GNC with the TLS loss.
        gnc_ran = len(known) < len(facs)
        least_squares: gtsam.Values | None = None  # converged over every factor, if solved
        gnc_skipped = False
        if gnc_ran and cfg.least_squares_gate:
            least_squares = _levenberg_marquardt(graph, initial, "least-squares")
            barc = 0.5 * float(chi2.ppf(cfg.inlier_probability, 6))  # GTSAM's cost threshold
            gnc_skipped = all(graph.at(m + i).error(least_squares) < barc
                              for i in range(len(facs)) if i not in known)
        if gnc_skipped:
            assert least_squares is not None
            estimate = least_squares
            w = np.ones(len(facs))
        elif gnc_ran:
            params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
            params.setLossType(gtsam.GncLossType.TLS)
            params.setKnownInliers([*range(m), *(m + i for i in sorted(known))])
            try:
                gnc = gtsam.GncLMOptimizer(graph, initial, params)
                gnc.setInlierCostThresholdsAtProbability(cfg.inlier_probability)
                estimate = gnc.optimize()
            except RuntimeError as exc:
                raise SolverError(f"GNC pose-graph optimisation failed: {exc}") from exc
            w = np.asarray(gnc.getWeights(), dtype=np.float64).ravel()[m:]
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
            for _ in range(2 if f.factor_id in self._deps else 1)
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
            estimate = _levenberg_marquardt(final, estimate, "pose-graph")
        self._recalibrated = False
        if cfg.calibration.enabled and self.calibrating:
            self._calibrate(final, estimate, [None] * m + [
                facs[i].group for i in range(len(facs)) if i not in rejected])

        def with_folded(fid: str) -> list[str]:  # a factor, then those folded into it
            return [fid, *self._deps.get(fid, ())]

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
            folded={d: fid for fid in every_v for d in self._deps.get(fid, ())},
            marginals_error=marg_err,
            frozen_nodes=len(comp) - len(live),
        )
        # rule 6 freezes only nodes placed beyond doubt: joined to the anchor twice over by
        # closures GNC kept (as rule 3 confirms), and not in a chain an ambiguous closure pulls
        if cfg.max_live_nodes > 0:
            placed = twice[group[local[anchor]]]
            pulled = {group[local[n]] for i in ambiguous
                      for n in (facs[i].frame_a, facs[i].frame_b)}
            self._freeze(anchor, [n for n in live if twice[group[local[n]]] == placed
                                  and group[local[n]] not in pulled], poses, facs, held, live)
        return sol

    def _freeze(self, anchor: str, placed: list[str], poses: dict[str, gtsam.Pose3],
                facs: list[_Factor], held: dict[str, tuple[float, str, float]],
                live: list[str]) -> None:
        """Rule 6: a live node placed beyond doubt (`placed`) freezes at its solved pose once
        max_live_nodes nodes joined the anchor's component in later solves than it did (so a
        session that joins late, on one closure nothing can check yet, stays live until more
        closures judge it). Seals the factors between two frozen nodes that are settled: known
        inliers and closures GNC kept (ambiguous, outlying and unchecked ones stay in the solve
        and are judged again)."""
        cap = self.config.max_live_nodes
        new = [n for n in live if n not in self._joined]
        # nodes ever joined: live ones (in _joined) and frozen ones (they left _joined)
        total = len(self._joined) + len(self._frozen) + len(new)
        for n in new:
            self._joined[n] = total  # (those that join in one solve: alike)
        frozen = [n for n in placed if total - self._joined[n] >= cap]
        for n in frozen:
            self._frozen[n] = poses[n]
            del self._joined[n]  # (only live nodes need it)
        if frozen:
            self._frozen_anchor = anchor
            log.debug("pose graph: %d nodes frozen, %d live", len(self._frozen),
                      len(live) - len(frozen))
        for f in facs:  # (also one added between two frozen nodes: solved, then sealed)
            if (f.frame_a in self._frozen and f.frame_b in self._frozen
                    and (f.known_inlier or held[f.factor_id][1] == "")):
                self._sealed[f.factor_id] = held[f.factor_id][0]
                if f.factor_id not in self._deps:  # never solved again: its ends are enough
                    self._factors[f.factor_id] = _Factor(f.factor_id, f.frame_a, f.frame_b,
                                                         None, None, f.known_inlier, f.group)

    def _between(self, f: _Factor) -> gtsam.BetweenFactorPose3:
        T, C = self._measurement(f)
        s = self._scales.get(f.group) if f.group is not None else None
        if s is not None:
            C = scale_covariance(C, s)
        noise = gtsam.noiseModel.Gaussian.Covariance(np.array(C), False)
        return gtsam.BetweenFactorPose3(self.key(f.frame_a), self.key(f.frame_b), T, noise)

    def _initial_values(self, anchor: str, seeds: dict[str, gtsam.Pose3], live: list[str],
                        facs: list[_Factor]) -> gtsam.Values:
        """The seeds (the anchor, the frozen nodes the factors touch) at their poses, every live
        node chained from them along a spanning tree of the factors.

        Frame pairs are ranked: known inliers first, then pairs with more parallel factors, then
        the smaller covariance; within a pair the medoid measurement is used, so a single gross
        factor beside correct parallel ones does not spoil the starting point.

        Warm start: a node the last solution (same anchor) placed starts there; only new nodes
        are chained from their tree parent. It keeps a long mission's solve short (a synthetic
        chain of 850 keyframes with 2,000 loop closures: GNC 34.6 s from the chained start,
        0.44 s from the converged poses; `mergesvc bench cost` measures it in the service).
        It is not neutral: GTSAM's GNC sets its schedule (mu) from the residuals at the start
        and starts each weighted solve there, so verdicts on a borderline factor may depend on
        the graph's history. tests/test_graph.py checks warm against cold at every step of
        graphs with a wrong closure, a late chain and a retraction. After a factor is removed
        the next solve starts cold: the last poses may hold what that factor pulled.
        """
        prev: dict[str, gtsam.Pose3] = {}
        last = self._solved[1] if self._solved is not None else None
        if (self.config.warm_start and last is not None and last.anchor == anchor
                and not self._cold_next):
            prev = last.T_anchor_frame
        by_pair: dict[tuple[str, str], list[tuple[_Factor, gtsam.Pose3]]] = defaultdict(list)
        for f in facs:
            a, b = sorted((f.frame_a, f.frame_b))
            T = f.T_a_b if (a, b) == (f.frame_a, f.frame_b) else f.T_a_b.inverse()
            by_pair[(a, b)].append((f, T))
        ranked = []
        for pair, items in by_pair.items():
            dist = [
                sum(np.linalg.norm(gtsam.Pose3.Logmap(T.between(U))) for _, U in items)
                for _, T in items
            ]
            k = int(np.argmin(dist))
            f, T = items[k]
            known = any(g.known_inlier for g, _ in items)
            ranked.append(((not known, -len(items), float(np.trace(f.covariance_66))), pair, T))
        ranked.sort(key=lambda r: r[0])
        adj: dict[str, list[tuple[str, gtsam.Pose3]]] = defaultdict(list)
        nodes = [*seeds, *(n for n in live if n not in seeds)]
        uf = UnionFind(len(nodes))
        index = {f: i for i, f in enumerate(nodes)}
        for i in range(1, len(seeds)):  # the seeds are placed: one tree joins them all
            uf.union(0, i)
        for _, (a, b), T in ranked:  # Kruskal: best pairs first
            if uf.union(index[a], index[b]):
                adj[a].append((b, T))
                adj[b].append((a, T.inverse()))
        poses = dict(seeds)
        todo = list(seeds)
        while todo:
            a = todo.pop()
            for b, T_a_b in adj[a]:
                if b not in poses:
                    poses[b] = prev[b] if b in prev else poses[a].compose(T_a_b)
                    todo.append(b)
        values = gtsam.Values()
        for frame in nodes:
            values.insert(self.key(frame), poses[frame])
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


def _levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                         what: str) -> gtsam.Values:
    try:
        return gtsam.LevenbergMarquardtOptimizer(
            graph, initial, gtsam.LevenbergMarquardtParams()
        ).optimize()
    except RuntimeError as exc:
        raise SolverError(f"{what} optimisation failed: {exc}") from exc


__all__ = ["GraphSolution", "PoseGraph"]
