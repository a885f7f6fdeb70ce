"""One submap in, its result and factors out, as one unit of work: no transport, no store.

`plan` matches the submap against the other sessions' maps, fits each accepted match as a
factor (locally: core/factors.py local_fit), takes the submap into its session and asks the
pairwise-consistency sets which factors the graph may trust (fleet/closures.py); it returns a
`UnitOfWork` and changes nothing but the session (idempotent: a submap planned again finds it
there). The caller commits the unit in one store transaction, then `apply`s it (the graph, the
factor tables, the consistency sets) and publishes; after a failed commit it calls `rollback`,
and the row stays pending. A replayed submap plans to the same factor ids.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.factors import (
    anchoring_keyframe,
    factor_from_match,
    local_fit,
    match_factor_id,
    yields_factor,
)
from mergesvc.core.frames import FrameId, KeyframeId
from mergesvc.core.graph import PoseGraph
from mergesvc.core.model import Factor, Submap
from mergesvc.core.pipeline import match
from mergesvc.core.poses import check_covariance
from mergesvc.errors import InputError, MergeError, SchemaError
from mergesvc.fleet.closures import ClosureSets
from mergesvc.fleet.config import CLOSURE_GROUP, ServiceConfig, bound_group, odometry_group
from mergesvc.fleet.held import FactorTable
from mergesvc.fleet.mixed import ProfileViews
from mergesvc.fleet.replies import NO_FRAMES, FrameTried, Outcome, SubmapResult
from mergesvc.fleet.sessions import SessionMap, Sessions, SessionState

log = logging.getLogger(__name__)


def check_odometry(sub: Submap) -> None:
    """SchemaError unless the submap's odometry covariance is one the pose graph takes (it
    symmetrises first: the wire model's check of the lower triangle is not enough)."""
    if sub.odometry is not None:
        try:
            check_covariance(np.asarray(sub.odometry.covariance), "odometry covariance")
        except InputError as exc:
            raise SchemaError(str(exc)) from None


@dataclass
class MatchPlan:
    """What one submap is matched against: the other sessions (name, map) and, for each, the
    (map, submap) arrays `match` takes (in a compact code when either side has one)."""

    others: list[tuple[str, SessionMap]]
    pairs: list[tuple[Any, Any]]


@dataclass
class UnitOfWork:
    """What processing one stored submap decided, before anything is committed."""

    row_id: int
    sub: Submap
    result: SubmapResult
    factors: list[Factor]  # every factor its matches gave (sent, held or replayed)
    sent: list[Factor] = field(default_factory=list)  # trusted now: stored accepted, sent
    withdrawn: list[Factor] = field(default_factory=list)  # dropped: retracted, held
    held: list[Factor] = field(default_factory=list)  # new and not trusted: stored held
    matches_tried: int = 0
    new_session: bool = False
    _undo: dict[Any, Any] = field(default_factory=dict, repr=False)  # consistency sets before

    @property
    def status(self) -> str:
        return "processed" if self.factors else "no_match"

    @property
    def detail(self) -> str:
        return f"{len(self.factors)} factors"


class Merger:
    """The state a submap is merged into, and the rules (module docstring)."""

    def __init__(self, config: ServiceConfig, graph: PoseGraph, sessions: Sessions,
                 views: ProfileViews) -> None:
        self.config = config
        self.graph = graph
        self.sessions = sessions
        self.views = views
        self.factors = FactorTable()  # in force: in the graph, sent (fleet/held.py)
        # keyframe-to-first edges of robots with a declared odometry bound: id -> (T, C)
        self.bound_edges: dict[str, tuple[gtsam.Pose3, np.ndarray]] = {}
        # session -> keyframe not joined to 0 yet -> its bound covariance's factor
        self._unbound: dict[str, dict[int, float]] = {}
        self.held: dict[str, Factor] = {}  # kept, not trusted (yet)
        self.closures = ClosureSets(config.consistency, self._chains)
        self.anchor: str | None = None  # the anchor session "robot/session"

    # -- planning ----------------------------------------------------------------------------

    def to_match(self, sub: Submap, payload: bytes) -> MatchPlan:
        """The sessions `sub` is matched against and the (map, submap) arrays of each; reads
        the sessions, changes nothing (the fleet index aside). SchemaError first when the
        graph would refuse the submap."""
        check_odometry(sub)  # (a row stored before the boundary checked it)
        me = str(FrameId(sub.robot_id, sub.session_id))
        code = self.views.note(me, payload)  # compact: how its embeddings were coded
        others = self.sessions.candidate_frames(me, sub, self.config.max_candidate_frames,
                                                self.config.max_frames_per_robot,
                                                self.config.loop_gap_submaps)
        return MatchPlan(others, [self.views.pair(other, sm.arrays, sub, code)
                                  for other, sm in others])

    def plan(self, row_id: int, sub: Submap, payload: bytes,
             lock: AbstractContextManager[Any] | None = None,
             matched: tuple[MatchPlan, list[Any]] | None = None) -> UnitOfWork:
        """Match, fit, take the submap into its session, weigh the new factors (module
        docstring); `lock` (the state lock) is held for the changes, not the matching.
        `matched`: the matching already done elsewhere (`to_match` and each pair's
        MatchResult: fleet/lane.py). Raises what matching raises; the session may then hold
        the submap (a later plan of the same row finds it there). A submap the graph would
        refuse raises SchemaError first, before any change."""
        if matched is None:
            todo = self.to_match(sub, payload)
            results = [match(m, s, self.config.match).result for m, s in todo.pairs]
        else:
            todo, results = matched
        factors: list[Factor] = []
        tried: list[FrameTried] = []
        others = todo.others
        me = str(FrameId(sub.robot_id, sub.session_id))
        for (other, sm), res in zip(others, results):
            if not yields_factor(res) or (  # (a loop onto the submap's own node: none)
                    other == me and anchoring_keyframe(res, sm.keyframe_of) == sub.keyframe):
                tried.append(FrameTried(frame=other, reason=res.reason,
                                        matches=len(res.matches)))
                continue
            factor = self._factor(res, sm, FrameId.parse(other), sub)
            tried.append(FrameTried(frame=other, reason=res.reason, matches=len(res.matches),
                                    factor_id=factor.factor_id))
            factors.append(factor)
        result = SubmapResult(
            robot=sub.robot_id, session=sub.session_id, seq=sub.seq,
            outcome=Outcome.PROCESSED if factors else Outcome.NO_MATCH,
            factors=[f.factor_id for f in factors], tried=tried,
            reason=None if factors else (tried[0].reason if tried else NO_FRAMES))
        uow = UnitOfWork(row_id, sub, result, factors, matches_tried=len(others))
        with lock if lock is not None else contextlib.nullcontext():
            uow.new_session = self._take(sub)
            try:
                self._weigh(uow)
            except BaseException:  # the consistency sets as they were: no phantom factor
                self.rollback(uow)
                raise
        return uow

    def _take(self, sub: Submap) -> bool:
        """The submap into its session's state (idempotent); True if the session is new."""
        st, new = self.sessions.state(FrameId(sub.robot_id, sub.session_id))
        st.add(sub)
        return new

    def _weigh(self, uow: UnitOfWork) -> None:
        """The new factors offered to the consistency sets: which to send, withdraw, hold.
        The sets' state before is kept in the unit (rollback)."""
        involved: dict[str, Factor] = {}
        for f in uow.factors:
            if f.factor_id in self.factors or f.factor_id in self.held:
                continue  # a replay
            key = self.closures.pair_key(f)
            if key not in uow._undo:
                uow._undo[key] = copy.deepcopy(self.closures.pair_state(key))
            v = self.closures.offer(f)
            involved[f.factor_id] = f
            for fid in (*v.trusted, *v.withdrawn):
                if fid not in involved:
                    involved[fid] = self._known(fid)
        for fid, f in involved.items():
            trusted = self.closures.is_trusted(fid)
            if trusted and fid not in self.factors:
                uow.sent.append(f)
            elif not trusted and fid in self.factors:
                uow.withdrawn.append(f)
            elif not trusted and fid not in self.held:
                uow.held.append(f)

    def _known(self, fid: str) -> Factor:
        f = self.held.get(fid)
        return f if f is not None else self.factors[fid]

    def factor(self, factor_id: str) -> Factor | None:
        """A factor as the service holds it: in force or held."""
        return self.factors[factor_id] if factor_id in self.factors else \
            self.held.get(factor_id)

    def rollback(self, uow: UnitOfWork) -> None:
        """The consistency sets as they were before `plan` (the commit failed)."""
        for key, state in uow._undo.items():
            self.closures.set_pair_state(key, state)

    # -- applying ----------------------------------------------------------------------------

    def apply(self, uow: UnitOfWork) -> bool:
        """A committed unit into the graph and the factor tables; True when the graph changed
        in a way a solve must see (a factor in or out, an odometry edge closing a loop)."""
        closes_loop = self._add_to_graph(uow.sub)
        for f in uow.held:
            self.held[f.factor_id] = f
        for f in uow.sent:
            self.held.pop(f.factor_id, None)
            self.factors[f.factor_id] = f
            self.graph.add_factor_model(f, keyframe_nodes=True, group=CLOSURE_GROUP)
        for f in uow.withdrawn:
            self.factors.pop(f.factor_id)
            self.graph.remove_factor(f.factor_id)
            self.held[f.factor_id] = f
        return bool(uow.sent or uow.withdrawn or closes_loop)

    def restore(self, sub: Submap) -> None:
        """A processed submap from the store (a restart): into its session and the graph."""
        self._take(sub)
        self._add_to_graph(sub)

    def restore_factor(self, factor: Factor, trusted: bool) -> None:
        """A stored factor with the verdict it had (a restart, in the order they were made).
        One the graph refuses (its nodes or covariance) is held, logged: the restart goes on."""
        self.closures.offer(factor, trusted=trusted)
        if trusted:
            try:
                self.graph.add_factor_model(factor, keyframe_nodes=True, group=CLOSURE_GROUP)
            except (MergeError, ValueError) as exc:
                log.error("stored factor %s refused by the graph, held: %s", factor.factor_id,
                          exc)
                self.held[factor.factor_id] = factor
                return
            self.factors[factor.factor_id] = factor
        else:
            self.held[factor.factor_id] = factor

    def retract(self, factor_id: str) -> Factor | None:
        """A factor GNC rejected: out of the graph and the tables, never trusted again."""
        f = self.factors.pop(factor_id) if factor_id in self.factors else None
        if f is not None:
            self.graph.remove_factor(factor_id)
            self.closures.forget(factor_id)
        return f

    def _add_to_graph(self, sub: Submap) -> bool:
        """The submap's keyframe node and odometry edge (a known inlier) into the graph, and
        its bound edges (`_add_bounds`); the first session is the anchor. True when the edge
        joined two nodes the graph had or a bound edge came in (either may close a loop: the
        graph must be solved again)."""
        st = self.sessions[str(FrameId(sub.robot_id, sub.session_id))]
        if self.anchor is None:
            self.set_anchor(st.name)
        self.graph.add_frame(st.node(0))
        closes_loop = False
        k = 0 if sub.keyframe is None else sub.keyframe
        odo, edge = sub.odometry, None
        if odo is not None and sub.keyframe is not None:
            edge = st.edges.get((odo.from_keyframe, k))
            if edge is not None:
                a, b = str(edge.from_), str(edge.to)
                closes_loop = self.graph.has_node(a) and self.graph.has_node(b)
                self.graph.add_factor(edge.edge_id, a, b, edge.T_from_to, edge.covariance,
                                      known_inlier=True, group=odometry_group(sub.robot_id))
        self.graph.add_frame(st.node(k))
        if sub.robot_id in self.config.odometry_bounds:
            ends = (k,) if edge is None else (odo.from_keyframe, k)
            step = None if edge is None else float(np.linalg.norm(edge.T_from_to.translation()))
            closes_loop = self._add_bounds(st, ends, step, sub.robot_id) or closes_loop
        return closes_loop

    def _add_bounds(self, st: SessionState, ends: tuple[int, ...], step_m: float | None,
                    robot: str) -> bool:
        """A robot with a declared odometry bound (ServiceConfig.odometry_bounds): each
        keyframe (`ends`: the new submap's, and its odometry edge's other end) tied to its
        session's keyframe 0 by the odometry between them, with the bound's covariance times
        the keyframes its errors stay alike over (`odometry_bound_span_m` over the edge's
        length `step_m`), a known inlier in the robot's bound group. A keyframe not yet joined
        to 0 waits, and is tied when an edge joins it. True when an edge was added (it closes
        a loop through keyframe 0: a solve must see it)."""
        span = self.config.odometry_bound_span_m
        share = max(1.0, span / step_m) if span > 0 and step_m else 1.0
        waiting = self._unbound.setdefault(st.name, {})
        for j in ends:  # (a submap applied again has its edges)
            if j != 0 and f"bound:{st.node(j)}" not in self.bound_edges:
                waiting.setdefault(j, share)
        if not any(st.joined(j) for j in ends):  # nothing joined to 0 changed
            return False
        B = np.diag(np.square(np.asarray(self.config.odometry_bounds[robot], np.float64)))
        added = False
        for j in sorted(j for j in waiting if st.joined(j)):
            T = st.origin_pose(j)
            if T is None:
                continue
            fid = f"bound:{st.node(j)}"
            C = B * waiting.pop(j)
            self.graph.add_factor(fid, st.node(0), st.node(j), T, C, known_inlier=True,
                                  group=bound_group(robot))
            self.bound_edges[fid] = (T, C)
            added = True
        return added

    def set_anchor(self, name: str) -> None:
        self.anchor = name
        self.graph.anchor = str(KeyframeId.origin(FrameId.parse(name)))

    # -- factors -----------------------------------------------------------------------------

    def _chains(self, frame: str, k: int, targets: set[int]
                ) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
        st = self.sessions.get(frame)
        scale = None if st is None else self.graph.noise_scales.get(
            odometry_group(st.frame.robot))
        return self.sessions.chains(frame, k, targets, scale)

    def _factor(self, res: Any, sm: SessionMap, other: FrameId, sub: Submap) -> Factor:
        """The factor of an accepted match of `sub` against session `other`'s map: pose level
        (keyframe Ka of other -> the submap's keyframe) unless both ends are keyframe 0 and the
        submap has no keyframe (an old client against frame-anchored objects: the frame-level
        factor, which ties the same two nodes)."""
        me = FrameId(sub.robot_id, sub.session_id)
        fid = match_factor_id(other, me, sub.seq if sub.seq is not None else 0)
        ka = anchoring_keyframe(res, sm.keyframe_of)
        if sub.keyframe is None and ka == 0:
            return factor_from_match(res, other, me, factor_id=fid,
                                     drift_sigma=self.config.drift_sigma)
        measured = self._local_fit(res, other, ka, sub) if self.config.local_fit else None
        if measured is not None:
            return factor_from_match(res, other, me, factor_id=fid,
                                     drift_sigma=self.config.local_drift_sigma,
                                     keyframe_a=ka, keyframe_b=sub.keyframe or 0,
                                     measured=measured)
        return factor_from_match(
            res, other, me, factor_id=fid, drift_sigma=self.config.drift_sigma,
            keyframe_a=ka, keyframe_b=sub.keyframe or 0, T_a_keyframe_a=sm.poses[ka],
        )

    def _local_fit(self, res: Any, other: FrameId, ka: int, sub: Submap
                   ) -> tuple[gtsam.Pose3, np.ndarray] | None:
        """T_{Ka,Kb} fitted on the matched objects with the other session's placed around Ka
        by its odometry (core/factors.py local_fit); None when that cannot be done (a matched
        object's keyframe not joined to Ka by odometry, too few pairs)."""
        st = self.sessions[str(other)]
        mine = {o.id: o for o in sub.objects}
        pairs = [(st.objects[m.map_object], mine[m.submap_object]) for m in res.matches
                 if m.map_object in st.objects and m.submap_object in mine]
        if not pairs:
            return None
        scale = self.graph.noise_scales.get(odometry_group(other.robot))
        placed = st.placements(ka, {h.keyframe for h, _ in pairs}, scale)
        v = self.config.match.verify
        up_map = st.up.get(ka) if v.gravity_aligned and sub.up is not None else None
        return local_fit(
            np.array([o.position for _, o in pairs], dtype=np.float64),
            np.array([h.position for h, _ in pairs], dtype=np.float64),
            [h.keyframe for h, _ in pairs], placed,
            up_sub=None if up_map is None else np.asarray(sub.up, dtype=np.float64),
            up_map=up_map,
            vertical_sigma_rad=np.radians(v.vertical_sigma_deg),
            sigma_floor_m=self.config.local_sigma_floor_m,
            range_weighted=self.config.local_range_weighted)


__all__ = ["MatchPlan", "Merger", "UnitOfWork", "check_odometry"]
