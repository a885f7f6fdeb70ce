"""The service's sessions: per robot session its keyframes, odometry edges and objects
(`SessionState`, rebuilt from the stored submaps on a restart), and `Sessions`, all of them:
each session's map placed for matching (`SessionMap`, cached until the session or the graph
solution changes), the other sessions a submap is matched against (one index over the fleet's
objects per embedding model: models are never matched with each other) and its own session's
objects last seen a few submaps before it (a loop the vehicle closed), and the odometry
chains between keyframes (pose and covariance) that factors and their checks need.

A session's map places every object with the current pose of its keyframe in the session
frame: keyframe 0 is the identity; keyframes the last solution holds take their solved pose
relative to keyframe 0; the others are composed along odometry edges from the nearest placed
keyframe. Keyframes no odometry joins to keyframe 0 (a lost submap broke the chain) are left
out, with their objects, until odometry or factors join them.
"""

from __future__ import annotations

import functools
import logging
from collections import defaultdict, deque
from collections.abc import ItemsView, Iterator, Mapping, ValuesView
from dataclasses import dataclass, field

import gtsam
import numpy as np

from mergesvc.core.calibration import scale_covariance
from mergesvc.core.factors import OdometryEdge, odometry_edge
from mergesvc.core.frames import FrameId, KeyframeId
from mergesvc.core.graph import GraphSolution
from mergesvc.core.model import ObjectArrays, ObjectMap, Submap
from mergesvc.core.poses import compose_with_covariance, inverse_with_covariance
from mergesvc.core.retrieval import FleetIndex
from mergesvc.fleet.held import HeldObject, PackedVector

# session maps kept for matching: only those built since the last graph solution can be used
# again, and each holds its objects' arrays (docs/benchmarks: how many pay)
SESSION_MAPS_CACHED = 8
log = logging.getLogger(__name__)


@dataclass
class SessionState:
    """One robot session: its keyframes, the odometry edges between them, its objects."""

    frame: FrameId
    keyframes: set[int] = field(default_factory=lambda: {0})
    edges: dict[tuple[int, int], OdometryEdge] = field(default_factory=dict)
    objects: dict[str, HeldObject] = field(default_factory=dict)  # compact: fleet/held.py
    up: dict[int, np.ndarray] = field(default_factory=dict)  # declared up per keyframe frame
    dim: int | None = None  # its embedding model's dimension (the first submap's)
    version: int = 0  # bumped by every submap
    # the last declared up and odometry covariance: a vehicle sends the same ones again and
    # again, held once (a long mission's keyframes each held their own copy)
    _last_up: np.ndarray | None = field(default=None, repr=False)
    _last_cov: np.ndarray | None = field(default=None, repr=False)
    # keyframe -> its odometry neighbours (the keyframes of its edges, either way)
    _adjacent: dict[int, list[int]] = field(
        default_factory=lambda: defaultdict(list), repr=False
    )
    # keyframe -> its pose in keyframe 0's frame along the odometry (edges never change)
    _origin: dict[int, gtsam.Pose3] = field(default_factory=lambda: {0: gtsam.Pose3()},
                                            repr=False)
    _parent: dict[int, int] = field(default_factory=dict, repr=False)  # union-find of edges

    @property
    def name(self) -> str:
        return str(self.frame)

    def node(self, k: int) -> str:
        """The pose-graph node of keyframe k: "{robot}/{session}#{k}"."""
        return str(KeyframeId(self.frame, k))

    def add(self, sub: Submap) -> OdometryEdge | None:
        """Take a submap in (idempotent); returns its odometry edge when it is new."""
        k = 0 if sub.keyframe is None else sub.keyframe
        seq = sub.seq if sub.seq is not None else -1
        if self.dim is None:
            self.dim = sub.dim
        self.keyframes.add(k)
        if sub.up is not None:
            up = np.asarray(sub.up, dtype=np.float64)
            if self._last_up is None or not np.array_equal(up, self._last_up):
                up.setflags(write=False)  # shared by the keyframes that declare it
                self._last_up = up
            self.up[k] = self._last_up
        for o in sub.objects:  # the latest submap holding an object gives its estimate
            held = self.objects.get(o.id)
            if held is None or held.seq <= seq:
                self.objects[o.id] = HeldObject.of(seq, k, o)
        self.version += 1
        edge = odometry_edge(sub)
        if edge is None:
            return None
        pair = (edge.from_.k, edge.to.k)
        old = self.edges.get(pair)
        if old is not None:
            if not old.T_from_to.equals(edge.T_from_to, 1e-9):
                log.warning("%s: odometry %d -> %d sent again with another value: kept the "
                            "first", self.name, *pair)
            return None
        if self._last_cov is None or not np.array_equal(edge.covariance, self._last_cov):
            self._last_cov = edge.covariance  # (read-only: odometry_edge)
        edge = OdometryEdge(KeyframeId(self.frame, edge.from_.k), KeyframeId(self.frame, edge.to.k),
                            edge.T_from_to, self._last_cov)  # this session's names, held once
        self.edges[pair] = edge
        self.keyframes.add(edge.from_.k)
        self._adjacent[pair[0]].append(pair[1])
        self._adjacent[pair[1]].append(pair[0])
        a, b = self._root(pair[0]), self._root(pair[1])
        if a != b:
            self._parent[a] = b
        return edge

    def joined(self, k: int) -> bool:
        """Whether odometry edges join keyframe k to keyframe 0."""
        return self._root(k) == self._root(0)

    def _root(self, k: int) -> int:
        parent = self._parent
        while parent.get(k, k) != k:
            parent[k] = parent.get(parent[k], parent[k])  # path halving
            k = parent[k]
        return k

    def origin_pose(self, k: int) -> gtsam.Pose3 | None:
        """Keyframe k's pose in keyframe 0's frame, composed along the odometry; None while no
        chain of edges joins them. Each keyframe is composed once (cached, with every keyframe
        the search passed on its way to one already known)."""
        hit = self._origin.get(k)
        if hit is not None or not self.joined(k):
            return hit
        rel = {k: gtsam.Pose3()}  # poses in k's frame, breadth first from k
        todo = deque([k])
        while todo:
            a = todo.popleft()
            for b in self._adjacent.get(a, ()):
                if b in rel:
                    continue
                e = self.edges.get((a, b))
                T = rel[a].compose(e.T_from_to if e is not None
                                   else self.edges[(b, a)].T_from_to.inverse())
                if b in self._origin:  # known: place k, then every keyframe passed
                    T_0_k = self._origin[b].compose(T.inverse())
                    for v, T_k_v in rel.items():
                        self._origin[v] = T_0_k.compose(T_k_v)
                    return T_0_k
                rel[b] = T
                todo.append(b)
        return None  # (not reached: joined means a path)

    def placements(self, source: int, targets: set[int], scale: np.ndarray | None = None
                   ) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
        """Pose and covariance of each target keyframe in `source`'s frame, composed along
        odometry edges from it (fewest edges first), each edge's covariance scaled per axis by
        `scale` (sigma, GTSAM order); targets not joined to it are absent."""
        done: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # edges share covariance objects

        def scaled(C: np.ndarray) -> np.ndarray:
            if scale is None:
                return C
            hit = done.get(id(C))
            if hit is None:  # `done` holds C: its id is not reused meanwhile
                hit = done[id(C)] = (C, scale_covariance(C, scale))
            return hit[1]

        out = {source: (gtsam.Pose3(), np.zeros((6, 6)))}
        todo, left = deque([source]), set(targets) - {source}
        while todo and left:
            k = todo.popleft()
            T_k, S_k = out[k]
            for j in self._adjacent.get(k, ()):
                if j in out:
                    continue
                edge = self.edges.get((k, j))
                if edge is not None:
                    step = (edge.T_from_to, scaled(edge.covariance))
                else:
                    e = self.edges[(j, k)]
                    step = inverse_with_covariance(e.T_from_to, scaled(e.covariance))
                out[j] = compose_with_covariance(T_k, S_k, *step)
                left.discard(j)
                todo.append(j)
        return {k: v for k, v in out.items() if k in targets}

    def propagate(self, seeds: Mapping[int, gtsam.Pose3]) -> dict[int, gtsam.Pose3]:
        """Poses of the keyframes reachable from `seeds` (keyframe -> pose) along odometry
        edges, each composed from the nearest seed (fewest edges); seeds keep their pose."""
        poses = dict(seeds)
        todo = deque(sorted(seeds))
        while todo:
            k = todo.popleft()
            for j in self._adjacent.get(k, ()):
                if j not in poses:
                    edge = self.edges.get((k, j))
                    poses[j] = poses[k].compose(edge.T_from_to if edge is not None
                                                else self.edges[(j, k)].T_from_to.inverse())
                    todo.append(j)
        return poses


@dataclass(frozen=True)
class SessionMap:
    """A session's objects placed in its frame for matching: the held objects and where they
    are placed (positions in the session frame), each object's keyframe and the keyframe poses
    (in the session frame) used to place them. `arrays` is what `match` computes on (made once,
    when first matched); `map` the same objects as an ObjectMap (built when asked)."""

    frame: FrameId
    objects: tuple[HeldObject, ...]
    positions: tuple[tuple[float, float, float], ...]
    up: tuple[float, ...] | None
    keyframe_of: dict[str, int]
    poses: dict[int, gtsam.Pose3]

    @property
    def dim(self) -> int:
        return self.objects[0].dim

    @functools.cached_property
    def arrays(self) -> ObjectArrays:
        """The objects as ObjectArrays: the values ObjectMap.arrays() gives for `map`."""
        objs = self.objects
        var = np.empty((len(objs), self.dim))
        for k, h in enumerate(objs):
            v = h.variance
            var[k] = v.unpack() if isinstance(v, PackedVector) else v  # a number broadcasts
        return ObjectArrays(
            ids=[h.id for h in objs],
            position_xyz_m=np.array(self.positions, dtype=np.float64),
            embeddings_nd=np.array([h.embedding.unpack() for h in objs], dtype=np.float64),
            variances_nd=var,
            n_obs=np.array([h.n_obs for h in objs], dtype=np.int64),
            up_xyz=None if self.up is None else np.asarray(self.up, dtype=np.float64),
        )

    def seen_by(self, seq: int, min_objects: int, exclude: frozenset[str] = frozenset()
                ) -> SessionMap | None:
        """The objects last held from submap `seq` or an earlier one and not in `exclude`,
        placed as here (None with fewer than min_objects): the old side of a loop, without
        the objects the vehicle's latest submaps still track (its own detections, not a
        revisit) nor the ids the submap holds (an object its tracker kept the id of is its own
        association again, and a submap planned twice finds the same map)."""
        keep = [k for k, h in enumerate(self.objects) if h.seq <= seq and h.id not in exclude]
        if len(keep) < min_objects:
            return None
        if len(keep) == len(self.objects):
            return self
        objs = tuple(self.objects[k] for k in keep)
        out = SessionMap(self.frame, objs, tuple(self.positions[k] for k in keep), self.up,
                         {h.id: self.keyframe_of[h.id] for h in objs}, self.poses)
        out.__dict__["arrays"] = self.arrays.subset(np.asarray(keep))  # rows of this map's
        return out

    @property
    def map(self) -> ObjectMap:
        return ObjectMap(robot_id=self.frame.robot, session_id=self.frame.session,
                         objects=[h.node_at(p) for h, p in zip(self.objects, self.positions,
                                                               strict=True)],
                         up=self.up)



def session_up(st: SessionState, poses: Mapping[int, gtsam.Pose3]) -> tuple[float, ...] | None:
    """The session frame's up, from the latest keyframe that declared one (its up rotated by
    that keyframe's pose in the session frame); None when no placed keyframe declared it."""
    for k in sorted(st.up, reverse=True):
        T = poses.get(k)
        if T is not None:
            u = np.asarray(T.rotation().matrix()) @ st.up[k]
            return tuple(float(x) for x in u / np.linalg.norm(u))
    return None


class Sessions:
    """Every session the service holds, by name "robot/session" (module docstring)."""

    def __init__(self, min_map_objects: int) -> None:
        self.min_map_objects = min_map_objects
        self.states: dict[str, SessionState] = {}
        self._indexes: dict[int, FleetIndex] = {}  # embedding dim -> its sessions' objects
        self._indexed: dict[str, int] = {}  # session -> its version in its index
        # session -> ((session version, solution count), its map): rebuilt when either changes
        self._maps: dict[str, tuple[tuple[int, int], SessionMap | None]] = {}
        self.solution: GraphSolution | None = None
        self.solutions = 0  # solutions taken so far (keys the session maps' cache)

    def __contains__(self, name: str) -> bool:
        return name in self.states

    def __getitem__(self, name: str) -> SessionState:
        return self.states[name]

    def get(self, name: str) -> SessionState | None:
        return self.states.get(name)

    def items(self) -> ItemsView[str, SessionState]:
        return self.states.items()

    def values(self) -> ValuesView[SessionState]:
        return self.states.values()

    def __len__(self) -> int:
        return len(self.states)

    def __iter__(self) -> Iterator[str]:
        return iter(self.states)

    def index_bytes(self) -> int:
        """Bytes the candidate indexes hold (every model's)."""
        return sum(i.nbytes() for i in self._indexes.values())

    def state(self, frame: FrameId) -> tuple[SessionState, bool]:
        """The session's state, made if new (True)."""
        name = str(frame)
        st = self.states.get(name)
        if st is not None:
            return st, False
        st = self.states[name] = SessionState(frame)
        return st, True

    def solved(self, solution: GraphSolution) -> None:
        """A new graph solution: every cached map is stale."""
        self.solution = solution
        self.solutions += 1
        self._maps.clear()

    def candidate_frames(self, me: str, sub: Submap, max_frames: int,
                         max_per_robot: int, loop_gap: int = 0) -> list[tuple[str, SessionMap]]:
        """The other sessions a submap of session `me` is matched against: those of its
        embedding model whose objects look most like the submap's (core/retrieval.py), at
        most max_frames, at most max_per_robot of one robot; then, with loop_gap > 0, its own
        session's objects last seen loop_gap or more submaps before it (`SessionMap.seen_by`;
        not for a submap without a sequence number or a keyframe)."""
        index = self._indexes.setdefault(sub.dim, FleetIndex())
        for name, st in self.states.items():  # sessions changed since they were indexed
            if st.dim == sub.dim and self._indexed.get(name) != st.version:
                emb = [h.embedding.unpack() for h in st.objects.values()]
                index.update(name, np.array(emb, dtype=np.float64) if emb
                             else np.zeros((0, sub.dim)))
                self._indexed[name] = st.version
        emb = np.asarray([o.embedding for o in sub.objects], dtype=np.float64)
        per_robot: dict[str, int] = defaultdict(int)
        out: list[tuple[str, SessionMap]] = []
        for fs in index.rank(emb, exclude=me):
            if len(out) >= max_frames:
                break
            robot = self.states[fs.frame].frame.robot
            if per_robot[robot] >= max_per_robot:
                continue
            sm = self.session_map(fs.frame)
            if sm is not None and sm.dim == sub.dim:
                out.append((fs.frame, sm))
                per_robot[robot] += 1
        if loop_gap > 0 and sub.seq is not None and sub.keyframe is not None \
                and me in self.states:  # (a loop ties two keyframes of the session)
            own = self.session_map(me)
            old = None if own is None or own.dim != sub.dim else own.seen_by(
                sub.seq - loop_gap, self.min_map_objects,
                frozenset(o.id for o in sub.objects))
            if old is not None:
                out.append((me, old))
        return out

    def session_map(self, name: str) -> SessionMap | None:
        """A session's objects placed in its frame (None with fewer than min_map_objects
        placed); cached until the session or the graph solution changes (the
        SESSION_MAPS_CACHED last used are kept)."""
        st = self.states[name]
        key = (st.version, self.solutions)
        cached = self._maps.pop(name, None)
        if cached is not None and cached[0] == key:
            self._maps[name] = cached  # the most recently used last
            return cached[1]
        poses = self.session_poses(st)
        placed, positions, keyframe_of = [], [], {}
        for oid, held in st.objects.items():
            T = poses.get(held.keyframe)
            if T is None:
                continue  # a keyframe the odometry does not join to keyframe 0 (yet)
            placed.append(held)
            if held.keyframe == 0 and T.equals(gtsam.Pose3(), 0.0):
                positions.append(held.position)
            else:
                p = T.transformFrom(np.asarray(held.position, dtype=np.float64))
                positions.append(tuple(map(float, p)))
            keyframe_of[oid] = held.keyframe
        sm = None
        if len(placed) >= self.min_map_objects:
            sm = SessionMap(st.frame, tuple(placed), tuple(positions), session_up(st, poses),
                            keyframe_of, poses)
        self._maps[name] = (key, sm)
        while len(self._maps) > SESSION_MAPS_CACHED:
            del self._maps[next(iter(self._maps))]
        return sm

    def session_poses(self, st: SessionState) -> dict[int, gtsam.Pose3]:
        """Pose of each placeable keyframe in the session frame (module docstring)."""
        sol = self.solution
        seeds = {0: gtsam.Pose3()}
        if sol is not None and (origin := sol.T_anchor_frame.get(st.node(0))) is not None:
            inv = origin.inverse()
            seeds = {k: inv.compose(T) for k in st.keyframes
                     if (T := sol.T_anchor_frame.get(st.node(k))) is not None}
            seeds[0] = gtsam.Pose3()
        return st.propagate(seeds)

    def anchor_poses(self, st: SessionState, anchor: str | None,
                     solution: GraphSolution | None) -> dict[int, gtsam.Pose3]:
        """Pose of each keyframe of a session in the anchor frame: the solved ones, and those
        joined to them by odometry (composed from the nearest); {} outside the anchor's
        component. Before any solution, only the anchor session, by odometry."""
        if solution is None:
            return st.propagate({0: gtsam.Pose3()}) if st.name == anchor else {}
        seeds = {k: T for k in st.keyframes
                 if (T := solution.T_anchor_frame.get(st.node(k))) is not None}
        return st.propagate(seeds) if seeds else {}

    def chains(self, frame: str, k: int, targets: set[int], scale: np.ndarray | None
               ) -> dict[int, tuple[gtsam.Pose3, np.ndarray]]:
        """Odometry from keyframe k of a session to each target, with covariances scaled by
        its robot's calibration (fleet/closures.py)."""
        st = self.states.get(frame)
        return {} if st is None else st.placements(k, targets, scale)


__all__ = ["SESSION_MAPS_CACHED", "SessionMap", "SessionState", "Sessions", "session_up"]
