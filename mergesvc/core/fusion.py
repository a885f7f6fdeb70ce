"""Object fusion: the objects of frames aligned by the pose graph (graph.py), joined along the
accepted correspondences and fused (the tracker's semantic Kalman fusion) into global objects.

The "frames" are the pose graph's nodes: session frames, or keyframes (the merge service: each
object of a session in the frame of the keyframe whose submap last held it), with `frame_of`
naming the session each node belongs to."""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import gtsam
import numpy as np

from mergesvc.core.connectivity import UnionFind
from mergesvc.core.frames import frame_name
from mergesvc.core.model import MAX_ID_LENGTH, Factor, ObjectArrays, ObjectMap, ObjectNode
from mergesvc.core.poses import as_pose3
from mergesvc.core.tracking import fuse_gaussians
from mergesvc.errors import InputError

log = logging.getLogger(__name__)


class ObjectLink(NamedTuple):
    """An accepted correspondence: object_a of frame_a is object_b of frame_b."""

    frame_a: str
    object_a: str
    frame_b: str
    object_b: str


def links_from_factor(factor: Factor) -> list[ObjectLink]:
    """The object correspondences a wire Factor carries, as ObjectLinks."""
    fa = frame_name(factor.robot_a, factor.session_a)
    fb = frame_name(factor.robot_b, factor.session_b)
    return [ObjectLink(fa, c.object_a, fb, c.object_b) for c in factor.correspondences]


@dataclass(frozen=True)
class FusedObjects:
    """Global objects in the anchor frame.

    objects: one ObjectNode per global object; members: global id -> [(frame, object id)] in
    input order; member_of: (frame, object id) -> global id; conflicts: global ids that hold two
    objects of one frame (the local map kept them apart, the correspondences joined them).
    """

    objects: list[ObjectNode]
    members: dict[str, list[tuple[str, str]]]
    member_of: dict[tuple[str, str], str] = field(repr=False)
    conflicts: list[str]

    def to_object_map(self, robot_id: str = "global", session_id: str = "merged") -> ObjectMap:
        return ObjectMap(robot_id=robot_id, session_id=session_id, objects=self.objects)


def fuse_objects(
    frame_objects: Mapping[str, ObjectArrays | ObjectMap | Sequence[ObjectNode]],
    T_anchor_frame: Mapping[str, gtsam.Pose3 | np.ndarray],
    links: Iterable[ObjectLink | tuple[str, str, str, str]],
    *,
    frame_of: Mapping[str, str] | None = None,
) -> FusedObjects:
    """Fuse the objects of aligned frames into global objects.

    frame_objects: frame -> its objects (positions in that frame): ObjectArrays, an ObjectMap /
    Submap or a list of ObjectNode (the last two carry labels); T_anchor_frame: frame poses,
    gtsam.Pose3 or (4, 4) (GraphSolution.T_anchor_frame). Frames without a pose are skipped,
    and so are links touching them. Objects joined by links (transitively: union-find) become
    one global object:
      position  = sum_i n_i (T_i p_i) / sum_i n_i  (n_obs-weighted mean in the anchor frame:
                  every observation is taken to carry the same position information, since
                  ObjectNode has no position covariance);
      embedding = product of the members' diagonal Gaussians (fuse_gaussians, the semantic
                  Kalman update; order-independent): var = 1 / sum 1/var_i,
                  mean = var * sum mean_i / var_i;
      n_obs     = sum n_i; label = the most common member label (input order breaks ties).
    The global id is "{frame}/{object id}" of the first member (frames in mapping order,
    objects in array order), so it persists while that member stays first; ids longer than
    MAX_ID_LENGTH fall back to "g{k}".

    frame_of: the session frame of each key of frame_objects when the keys are nodes of finer
    grain (keyframes "{frame}#{k}"): the global id then uses the session frame ("{frame}/{id}",
    stable while the object moves from one keyframe's submap to a later one's) and a conflict
    is two objects of one session frame. Links name nodes (the node holding the object).
    Default: every key is its own frame.
    """
    def session(node: str) -> str:
        return node if frame_of is None else frame_of.get(node, node)

    arrays: dict[str, ObjectArrays] = {}
    frame_labels: dict[str, list[str | None]] = {}
    for f, objs in frame_objects.items():
        if f not in T_anchor_frame:
            log.debug("fuse_objects: frame %s has no pose, skipped", f)
            continue
        if isinstance(objs, ObjectMap):
            arrays[f] = objs.arrays()
            frame_labels[f] = [o.label for o in objs.objects]
        elif isinstance(objs, ObjectArrays):
            arrays[f] = objs
            frame_labels[f] = [None] * objs.n
        elif isinstance(objs, Sequence) and objs and all(isinstance(o, ObjectNode) for o in objs):
            arrays[f] = ObjectArrays.from_objects(list(objs))
            frame_labels[f] = [o.label for o in objs]
        else:
            raise InputError(f"frame {f!r}: expected ObjectArrays, an ObjectMap or ObjectNodes")
    poses = {f: as_pose3(T_anchor_frame[f], f"pose of frame {f!r}") for f in arrays}
    frames = list(arrays)
    refs: list[tuple[str, str]] = []
    index: dict[tuple[str, str], int] = {}
    dims = {arrays[f].dim for f in frames}
    if len(dims) > 1:
        raise InputError(f"frames have different embedding dimensions {sorted(dims)}")
    for f in frames:
        for oid in arrays[f].ids:
            index[(f, oid)] = len(refs)
            refs.append((f, oid))

    uf = UnionFind(len(refs))
    for link in links:
        fa, oa, fb, ob = link
        if fa not in T_anchor_frame or fb not in T_anchor_frame:
            continue
        for fr, oid in ((fa, oa), (fb, ob)):
            if fr not in frame_objects:
                raise InputError(f"link {tuple(link)}: unknown frame {fr!r}")
            if (fr, oid) not in index:
                raise InputError(f"link {tuple(link)}: frame {fr!r} has no object {oid!r}")
        uf.union(index[(fa, oa)], index[(fb, ob)])

    # Member arrays in the anchor frame.
    pos: list[np.ndarray] = []
    emb: list[np.ndarray] = []
    var: list[np.ndarray] = []
    nobs: list[int] = []
    labels: list[str | None] = []
    for f in frames:
        arr = arrays[f]
        T = poses[f]
        pos.extend(arr.position_xyz_m @ T.rotation().matrix().T + T.translation())
        emb.extend(arr.embeddings_nd)
        var.extend(arr.variances_nd)
        nobs.extend(int(n) for n in arr.n_obs)
        labels.extend(frame_labels[f])

    groups: dict[int, list[int]] = defaultdict(list)
    for i in range(len(refs)):
        groups[uf.find(i)].append(i)

    objects: list[ObjectNode] = []
    members: dict[str, list[tuple[str, str]]] = {}
    member_of: dict[tuple[str, str], str] = {}
    conflicts: list[str] = []
    used: set[str] = set()
    for k, idx in enumerate(sorted(groups.values(), key=lambda g: g[0])):
        first = refs[idx[0]]
        gid = f"{session(first[0])}/{first[1]}"
        if len(gid) > MAX_ID_LENGTH or gid in used:
            gid = f"g{k}"
        used.add(gid)
        n = np.array([nobs[i] for i in idx], dtype=np.float64)
        p = (n[:, None] * np.array([pos[i] for i in idx])).sum(axis=0) / n.sum()
        mu, v = emb[idx[0]], var[idx[0]]
        for i in idx[1:]:
            mu, v = fuse_gaussians(mu, v, emb[i], var[i])
        member_refs = [refs[i] for i in idx]
        if len({session(fr) for fr, _ in member_refs}) < len(member_refs):
            conflicts.append(gid)
        objects.append(
            ObjectNode(
                id=gid,
                position=(float(p[0]), float(p[1]), float(p[2])),
                embedding=[float(x) for x in mu],
                variance=float(v[0]) if np.ptp(v) == 0 else [float(x) for x in v],
                n_obs=int(n.sum()),
                label=_majority([labels[i] for i in idx]),
            )
        )
        members[gid] = member_refs
        for r in member_refs:
            member_of[r] = gid
    if conflicts:
        # chained correspondences (a-b in one factor, b-c in another) can put two objects of one
        # session in one global object: kept, and listed in `conflicts`; nothing is wrong with
        # the factors, so this is information, not a warning
        log.info("fused map: %d global objects each hold two objects of one session (joined "
                 "through chained correspondences; listed as conflicts)", len(conflicts))
    return FusedObjects(objects=objects, members=members, member_of=member_of, conflicts=conflicts)


def _majority(labels: list[str | None]) -> str | None:
    counts: dict[str, int] = {}
    for lab in labels:
        if lab is not None:
            counts[lab] = counts.get(lab, 0) + 1
    if not counts:
        return None
    best = max(counts.values())
    return next(lab for lab in counts if counts[lab] == best)


__all__ = ["FusedObjects", "ObjectLink", "fuse_objects", "links_from_factor"]
