"""Folding, rule 5 of the pose graph (docs/pose_graph.md): a new closure that agrees with a
solved factor whose ends are near its own, where the odometry between is known well, is folded
into that factor (its representative): held and reported, but not solved. The representative is
solved with its own measurement fused with the folded ones', each carried to its ends along the
odometry (covariances propagated to first order).

Guarantees: a folded factor is held as it was added (replays and retractions see it unchanged)
and as it was carried when it folded, so a representative's fused measurement can be made again
whatever became of that odometry since (sealed by rule 6). A change that fails changes nothing.
Pure: no I/O.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Container, Mapping, Sequence

import gtsam
import numpy as np
from scipy.linalg import eigh

from mergesvc.core.chi2 import chi2_quantile
from mergesvc.core.config import GraphConfig
from mergesvc.core.graph_factor import GraphFactor, levenberg_marquardt
from mergesvc.core.poses import compose_with_covariance as _compose
from mergesvc.core.poses import inverse_with_covariance as _inverse
from mergesvc.errors import SolverError

_TRIU = np.triu_indices(6)
_PACKED = 28  # float64s of one packed measurement (_pack)

Measurement = tuple[gtsam.Pose3, np.ndarray]  # T, its (6, 6) covariance
_Near = dict[str, tuple[int, gtsam.Pose3, np.ndarray]]  # node -> (hops, pose, covariance)


def _pack(T: gtsam.Pose3, C: np.ndarray) -> np.ndarray:
    """A measurement in 28 float64s: translation, quaternion (w, x, y, z), the covariance's
    upper triangle."""
    q = T.rotation().toQuaternion()
    return np.concatenate([np.asarray(T.translation(), dtype=np.float64),
                           [q.w(), q.x(), q.y(), q.z()], C[_TRIU]])


def _unpack(v: np.ndarray) -> Measurement:
    T = gtsam.Pose3(gtsam.Rot3.Quaternion(*v[3:7]), v[:3].copy())
    C = np.zeros((6, 6))
    C[_TRIU] = v[7:]
    C = C + np.triu(C, 1).T
    C.setflags(write=False)
    return T, C


def _fuse(items: Sequence[Measurement]) -> Measurement:
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
    estimate = levenberg_marquardt(graph, initial, "fusion")
    try:
        cov = np.asarray(gtsam.Marginals(graph, estimate).marginalCovariance(key),
                         dtype=np.float64)
    except RuntimeError as exc:
        raise SolverError(f"fusion marginals failed: {exc}") from exc
    return estimate.atPose3(key), 0.5 * (cov + cov.T)


def _carry(f: GraphFactor, g: GraphFactor, at_a: tuple[int, gtsam.Pose3, np.ndarray],
           at_b: tuple[int, gtsam.Pose3, np.ndarray],
           n: str) -> tuple[gtsam.Pose3, np.ndarray, float]:
    """f's measurement carried to g's ends n (near f's a) and o (near f's b), in g's
    direction: (T, covariance, drift). at_a / at_b: n's and o's pose and covariance in
    f.a's / f.b's frame (Folding.near). drift: the largest eigenvalue of what the odometry adds
    to the covariance, whitened by f's own (first order, S = S_own + odometry): large, and f
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


class Folding:
    """The folded factors of one pose graph and the fused measurements of their
    representatives. `factors`: the graph's solved factors (read here, written by the graph
    only)."""

    def __init__(self, factors: Mapping[str, GraphFactor]) -> None:
        self._factors = factors
        # folded factor -> (node a, node b, its representative, its measurement as added and
        # as carried to the representative's ends (two _pack-ed, in one array), noise group):
        # a long mission holds thousands, so each is one small array, not Pose3s and matrices
        self.folded: dict[str, tuple[str, str, str, np.ndarray, str | None]] = {}
        self.deps: dict[str, list[str]] = {}  # representative -> its folded factors
        # representative -> its measurement fused with its folded ones'
        self.fused: dict[str, Measurement] = {}
        # node -> ids of the solved factors at it: known inliers, and the others (kept once
        # folding was asked for, built then from the factors)
        self._known_at: dict[str, list[str]] = defaultdict(list)
        self._closures_at: dict[str, list[str]] = defaultdict(list)
        self._at_kept = False

    def representative(self, factor_id: str) -> str | None:
        """The factor a folded factor is folded into; None if it is not folded."""
        entry = self.folded.get(factor_id)
        return entry[2] if entry is not None else None

    def measurement(self, g: GraphFactor) -> Measurement:
        """What the solve uses of a solved factor: its own measurement, or fused with those
        folded into it."""
        return self.fused.get(g.factor_id, (g.T_a_b, g.covariance_66))

    def unfold(self, factor_id: str) -> GraphFactor:
        """A folded factor as it was added."""
        a, b, _, packed, group = self.folded[factor_id]
        return GraphFactor(factor_id, a, b, *_unpack(packed[:_PACKED]), False, group)

    # -- folding a factor ----------------------------------------------------------------------

    def find(self, f: GraphFactor, config: GraphConfig,
             sealed: Container[str]) -> tuple[str, Measurement] | None:
        """The solved factor g that `f` folds into, with f's measurement carried to g's ends
        (T, covariance, in g's direction): of the factors with their ends near f's, the nearest;
        `f` folds if the odometry between is known well enough (fold_drift) and it agrees with
        g's measurement (fused, if g holds folded ones). None: `f` is solved. Never one of the
        `sealed` factors (not solved again: nothing to fold into)."""
        hops = config.fold_hops
        if hops <= 0 or f.known_inlier:
            return None
        if not self._at_kept:  # the first fold asked for: index the factors at their nodes
            for g in self._factors.values():
                self._at(g, list.append)
            self._at_kept = True
        near_a = self._near(f.frame_a, hops)
        near_b = self._near(f.frame_b, hops)
        best: tuple[int, str, str, str] | None = None  # (hops, factor, its end near a, near b)
        for n, (h_n, _, _) in near_a.items():
            for gid in self._closures_at.get(n, ()):
                if gid in sealed:
                    continue
                g = self._factors[gid]
                o = g.frame_b if g.frame_a == n else g.frame_a
                if o in near_b and (best is None or h_n + near_b[o][0] < best[0]):
                    best = (h_n + near_b[o][0], gid, n, o)
        if best is None:
            return None
        _, gid, n, o = best
        g = self._factors[gid]
        T, S, drift = _carry(f, g, near_a[n], near_b[o], n)
        if drift > config.fold_drift:
            return None
        T_g, C_g = self.measurement(g)
        e = np.asarray(gtsam.Pose3.Logmap(T_g.between(T)), dtype=np.float64)
        d2 = float(e @ np.linalg.solve(C_g + S, e))
        if d2 >= chi2_quantile(config.inlier_probability, 6):
            return None
        return gid, (T, S)

    def fold(self, f: GraphFactor, rep: str, carried: Measurement) -> None:
        """Fold `f` into `rep` (find's answer)."""
        fused = _fuse([self.measurement(self._factors[rep]), carried])  # before any change
        self.folded[f.factor_id] = (f.frame_a, f.frame_b, rep, np.concatenate(
            [_pack(f.T_a_b, f.covariance_66), _pack(*carried)]), f.group)
        self.deps.setdefault(rep, []).append(f.factor_id)
        self.fused[rep] = fused

    def _near(self, node: str, hops: int) -> _Near:
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

    # -- the solved factors at each node -------------------------------------------------------

    def solved(self, f: GraphFactor) -> None:
        """`f` is now a solved factor of the graph."""
        if self._at_kept:
            self._at(f, list.append)

    def _at(self, f: GraphFactor, change: Callable[[list[str], str], None]) -> None:
        at = self._known_at if f.known_inlier else self._closures_at
        for node in (f.frame_a, f.frame_b):
            change(at[node], f.factor_id)
            if not at[node]:
                del at[node]

    # -- removing ------------------------------------------------------------------------------

    def remove(self, factor_id: str) -> None:
        """Drop a folded factor; its representative's fused measurement is made again from its
        own and the other folded ones' as they were carried (first, so a failure changes
        nothing)."""
        rep = self.folded[factor_id][2]
        rest = [d for d in self.deps[rep] if d != factor_id]
        fused = self._fused_of(rep, rest) if rest else None
        del self.folded[factor_id]
        if fused is None:
            del self.deps[rep]
            self.fused.pop(rep, None)
        else:
            self.deps[rep] = rest
            self.fused[rep] = fused

    def _fused_of(self, rep: str, deps: list[str]) -> Measurement:
        g = self._factors[rep]
        return _fuse([(g.T_a_b, g.covariance_66),
                      *(_unpack(self.folded[d][3][_PACKED:]) for d in deps)])

    def release(self, f: GraphFactor) -> list[GraphFactor]:
        """The solved factor `f` leaves the graph (the caller drops it): the folded factors that
        go back to the graph, as they were added, to be folded again or solved. Those folded
        into `f`, and when `f` is a known inlier every folded factor (they may have been
        carried along it: judged again)."""
        if self._at_kept:
            self._at(f, list.remove)
        self.fused.pop(f.factor_id, None)
        ids = self.deps.pop(f.factor_id, [])
        if f.known_inlier:
            own = set(ids)
            ids += [d for d in self.folded if d not in own]
        back = [self.unfold(d) for d in ids]
        if f.known_inlier:  # every representative lost its folded factors
            self.folded.clear()
            self.deps.clear()
            self.fused.clear()
        for d in ids:
            self.folded.pop(d, None)
        return back

    def releases(self, f: GraphFactor) -> bool:
        """Whether removing `f` sends folded factors back to the graph (release)."""
        return f.factor_id in self.deps or (f.known_inlier and bool(self.folded))

    def checkpoint(self) -> Callable[[], None]:
        """A function that puts this state back as it is now (for a change that may fail half
        way: the graph's reinsertion of released factors)."""
        folded, fused, at_kept = dict(self.folded), dict(self.fused), self._at_kept
        deps = {r: list(v) for r, v in self.deps.items()}
        known_at = {n: list(v) for n, v in self._known_at.items()}
        closures_at = {n: list(v) for n, v in self._closures_at.items()}

        def undo() -> None:
            for now, was in ((self.folded, folded), (self.fused, fused), (self.deps, deps),
                             (self._known_at, known_at), (self._closures_at, closures_at)):
                now.clear()
                now.update(was)
            self._at_kept = at_kept

        return undo


__all__ = ["Folding", "Measurement"]
