"""The merge service's state as files other tools read: the global pose graph in g2o and every
session's keyframe trajectory in TUM, from odometry alone and as merged.

`export_store` copies the service's SQLite store (an online backup of a read-only connection: a
running service may keep writing, and the file is never changed), rebuilds the service from the
copy as a restart does (`MergeService.restore`; submaps still pending are not in it) and writes
into `out_dir`: graph.g2o, graph_nodes.json, factors.json, map.json, export.json (the manifest)
and trajectories/{robot}_{session}_{odometry,merged}.tum. The anchor's component is in the
anchor frame, any other component in the frame of its first node (export.json names each
node's frame). The files, vertex ids, edge order, frames and TUM stamps: docs/export.md.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sqlite3
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.factors import factor_nodes, is_loop
from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor, FactorStatus, Submap
from mergesvc.core.poses import pose3_from_model
from mergesvc.errors import InputError, MergeError, StoreError, one_line
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.store import META_FLEET, StoreReader
from mergesvc.wire import Projection, decode_message
from mergesvc.wire.formats import write_g2o, write_tum

GRAPH_FILE = "graph.g2o"
NODES_FILE = "graph_nodes.json"
MANIFEST_FILE = "export.json"
FACTORS_FILE = "factors.json"
MAP_FILE = "map.json"
TRAJECTORY_DIR = "trajectories"
# the submaps restore() takes in (the others are pending or failed)
_PROCESSED = ("processed", "no_match")


@dataclass(frozen=True)
class ExportResult:
    """What export_store wrote. trajectories: "robot/session" -> {"odometry": path, "merged":
    path} (merged only for sessions in the anchor's component); stamps: "robot/session" ->
    "submap" or "keyframe" (see the module docstring)."""

    out_dir: Path
    anchor: str | None
    graph: Path
    nodes: Path
    manifest: Path
    vertices: int
    edges: int
    trajectories: dict[str, dict[str, Path]] = field(default_factory=dict)
    stamps: dict[str, str] = field(default_factory=dict)
    factors: Path | None = None
    global_map: Path | None = None

    @property
    def files(self) -> list[Path]:
        """Every file written: the graph, its node names, each trajectory, the factors, the
        global map (when there is one), the manifest."""
        return [self.graph, self.nodes,
                *(p for kinds in self.trajectories.values() for p in kinds.values()),
                *(p for p in (self.factors, self.global_map) if p is not None), self.manifest]


def snapshot_store(store_path: str | Path, copy_path: str | Path) -> Path:
    """A consistent copy of a store (SQLite online backup through a read-only connection: the
    source is never written, a service may be running on it). On read-only media, where SQLite
    cannot make a WAL file's index beside it, the file and its WAL are copied first and read
    there. InputError: no such file; StoreError: not an SQLite file, or unreadable."""
    src_path = Path(store_path)
    if not src_path.is_file():
        raise InputError(f"no store file {src_path}: give the file `mergesvc serve --store` "
                         f"wrote")
    dst_path = Path(copy_path)
    try:
        try:
            _backup(f"{src_path.resolve().as_uri()}?mode=ro", dst_path)
        except sqlite3.OperationalError:
            if os.access(src_path.parent, os.W_OK):
                raise
            with tempfile.TemporaryDirectory(dir=dst_path.parent) as tmp:
                for suffix in ("", "-wal"):
                    if Path(f"{src_path}{suffix}").is_file():
                        shutil.copyfile(f"{src_path}{suffix}", Path(tmp) / f"s.db{suffix}")
                _backup((Path(tmp) / "s.db").as_uri(), dst_path)
    except (sqlite3.Error, OSError) as exc:
        raise StoreError(f"cannot read store {src_path}: {one_line(exc)}") from exc
    return dst_path


def _backup(src_uri: str, dst_path: Path) -> None:
    src = sqlite3.connect(src_uri, uri=True)
    try:
        dst = sqlite3.connect(dst_path)
        try:
            src.backup(dst)
        finally:
            dst.close()
    finally:
        src.close()


def _write_json(path: Path, data: Any) -> Path:
    try:
        path.write_text(json.dumps(data, indent=1) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc
    return path


def _file_part(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", name)


def _stamped_submaps(svc: MergeService, projections: Sequence[Projection]) -> dict[str, dict[int,
                                                                                         float]]:
    """"robot/session" -> keyframe -> the `stamp` of the processed submap cut at that keyframe
    (the lowest seq if several; submaps without keyframe or stamp give none)."""
    out: dict[str, dict[int, tuple[int, float]]] = {}
    for row in svc.store.submaps():
        if row.status not in _PROCESSED:
            continue
        _, sub = decode_message(row.payload, list(projections))
        if not isinstance(sub, Submap) or sub.keyframe is None or sub.stamp is None:
            continue
        seen = out.setdefault(str(FrameId(sub.robot_id, sub.session_id)), {})
        seq = sub.seq if sub.seq is not None else -1
        if sub.keyframe not in seen or seq < seen[sub.keyframe][0]:
            seen[sub.keyframe] = (seq, float(sub.stamp))
    return {name: {k: s for k, (_, s) in ks.items()} for name, ks in out.items()}


def _session_stamps(keyframes: set[int], submap_stamps: dict[int, float]
                    ) -> tuple[dict[int, float], str]:
    """Every keyframe's TUM stamp and how keyframe 0's was found: "submap" (a submap cut at
    keyframe 0), "extrapolated" (from the first two later keyframes, linear in the keyframe
    index) or "keyframe" (every stamp is the keyframe index). See the module docstring."""
    index_stamps = {k: float(k) for k in keyframes}
    later = sorted(k for k in keyframes if k != 0)
    if not later or not all(k in submap_stamps for k in later):
        return index_stamps, "keyframe"
    stamps = {k: submap_stamps[k] for k in later}
    if 0 in submap_stamps:
        return {0: submap_stamps[0], **stamps}, "submap"
    if len(later) < 2:
        return index_stamps, "keyframe"
    (k1, s1), (k2, s2) = (later[0], stamps[later[0]]), (later[1], stamps[later[1]])
    s0 = s1 - k1 * (s2 - s1) / (k2 - k1)
    if not s2 > s1:  # stamps that do not grow with the keyframes: nothing to extrapolate
        return index_stamps, "keyframe"
    return {0: s0, **stamps}, "extrapolated"


def _graph_edges(svc: MergeService, ids: dict[str, int]) -> tuple[list[tuple[int, int, np.ndarray,
                                                                              np.ndarray]],
                                                                 list[dict[str, Any]]]:
    """Every factor of the service's graph, in its order, with its measurement and covariance
    from the service's own state: its sessions' odometry edges and its factors in force."""
    graph = svc.graph
    odometry = {e.edge_id: e for st in svc.sessions.values() for e in st.edges.values()}
    edges, listed = [], []
    for fid in graph.factor_ids:
        a, b, known = graph.factor_nodes(fid)
        if fid in svc.factors:
            f = svc.factors[fid]
            if tuple(str(x) for x in factor_nodes(f)) != (a, b):
                raise MergeError(f"factor {fid}: the graph ties {a} -> {b}, the factor "
                                 f"{' -> '.join(str(x) for x in factor_nodes(f))}")
            T, C = pose3_from_model(f.T_a_b), np.asarray(f.covariance)
            kind = "loop" if is_loop(f) else "inter_robot"
        elif fid in odometry:
            e = odometry[fid]
            T, C, kind = e.T_from_to, np.asarray(e.covariance), "odometry"
        elif fid in svc.merger.bound_edges:
            T, C = svc.merger.bound_edges[fid]
            kind = "odometry_bound"
        else:
            raise MergeError(f"factor {fid} of the pose graph is neither an odometry edge nor "
                             "a factor in force")
        edges.append((ids[a], ids[b], np.asarray(T.matrix()), C))
        listed.append({"factor_id": fid, "kind": kind, "i": ids[a], "j": ids[b],
                       "known_inlier": bool(known)})
    return edges, listed


def _node_poses(svc: MergeService) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """(4, 4) pose of every graph node and the node whose frame it is in (the anchor for the
    anchor's component, else the component's first node): see the module docstring."""
    graph = svc.graph
    poses: dict[str, np.ndarray] = {}
    frame_of: dict[str, str] = {}
    anchor = graph.anchor
    for name, by_k in svc.keyframe_poses().items():  # what the status query says
        st = svc.sessions[name]
        for k, T in by_k.items():
            poses[st.node(k)] = np.asarray(T, dtype=np.float64)
            frame_of[st.node(k)] = str(anchor)
    for comp in graph.components():
        todo = [n for n in comp if n not in poses]
        if not todo:
            continue
        root = anchor if anchor in comp else comp[0]
        sol = graph.optimize(root, marginals=False)
        for n in todo:
            poses[n] = np.asarray(sol.T_anchor_frame[n].matrix())
            frame_of[n] = str(root)
    return poses, frame_of


def export_store(
    store_path: str | Path,
    out_dir: str | Path,
    *,
    config: ServiceConfig | None = None,
    projections: Sequence[Projection] = (),
) -> ExportResult:
    """Write the g2o graph and the TUM trajectories of the service state a store holds into
    `out_dir` (see the module docstring). `config`: the service's settings (its `graph`
    section solves; its `store` is ignored, `store_path` is read); `projections`: the fleet
    projections compact submaps need (as `serve --projection`).

    InputError: no such store, or a store without any processed submap; StoreError: not a
    mergesvc store; SolverError: the pose graph cannot be solved."""
    out = Path(out_dir)
    cfg = config or ServiceConfig()
    with tempfile.TemporaryDirectory(prefix="mergesvc-export-") as tmp:
        copy = snapshot_store(store_path, Path(tmp) / "store.db")
        with StoreReader(copy) as reader:  # the store's own fleet, whatever the settings say
            fleet = reader.meta(META_FLEET) or cfg.fleet
        svc = MergeService(cfg.model_copy(update={"store": str(copy), "fleet": fleet}), None,
                           list(projections))
        try:
            svc.restore()
            return _write(svc, out, Path(store_path), list(projections))
        finally:
            svc.close()


def _write(svc: MergeService, out: Path, store_path: Path,
           projections: list[Projection]) -> ExportResult:
    graph = svc.graph
    if not graph.nodes:
        raise InputError(f"store {store_path} holds no processed submap: nothing to export")
    ids = {n: i for i, n in enumerate(graph.nodes)}
    poses, frame_of = _node_poses(svc)
    edges, listed = _graph_edges(svc, ids)
    stamped = _stamped_submaps(svc, projections)
    anchor = graph.anchor
    anchor_session = next((name for name, st in svc.sessions.items() if st.node(0) == anchor),
                          None)
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / TRAJECTORY_DIR).mkdir(exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write to {out}: {exc.strerror or exc}") from exc

    g2o = write_g2o(out / GRAPH_FILE, {ids[n]: poses[n] for n in graph.nodes}, edges)
    node_file = _write_json(out / NODES_FILE, {str(i): n for n, i in ids.items()})

    trajectories: dict[str, dict[str, Path]] = {}
    stamp_kind: dict[str, str] = {}
    stamp_0: dict[str, str] = {}
    node_stamp: dict[str, float | None] = {}
    used: set[str] = set()
    for name, st in svc.sessions.items():
        stamps, how = _session_stamps(st.keyframes, stamped.get(name, {}))
        stamp_kind[name] = "keyframe" if how == "keyframe" else "submap"
        stamp_0[name] = how
        for k in st.keyframes:
            node_stamp[st.node(k)] = stamps[k]
        base = f"{_file_part(st.frame.robot)}_{_file_part(st.frame.session)}"
        stem, n = base, 1
        while stem in used:  # two ids that differ only in characters a file name drops
            n += 1
            stem = f"{base}_{n}"
        used.add(stem)
        odometry = {k: np.asarray(T.matrix()) for k, T in
                    st.propagate({0: gtsam.Pose3()}).items()}
        merged = {k: poses[st.node(k)] for k in st.keyframes
                  if frame_of.get(st.node(k)) == anchor}
        files: dict[str, Path] = {}
        for label, traj in (("odometry", odometry), ("merged", merged)):
            ks = [k for k in sorted(traj) if node_stamp[st.node(k)] is not None]
            if not ks:
                continue
            files[label] = write_tum(
                out / TRAJECTORY_DIR / f"{stem}_{label}.tum",
                np.array([node_stamp[st.node(k)] for k in ks], dtype=np.float64),
                np.stack([traj[k] for k in ks]),
            )
        trajectories[name] = files

    factors = []
    for row in svc.store.factors():
        f = Factor.model_validate_json(row.payload)
        factors.append(f.model_copy(update={"status": FactorStatus(row.status)}).model_dump(
            mode="json"))
    factors_file = _write_json(out / FACTORS_FILE, factors)
    global_map, _ = svc.global_map()
    map_file = None
    if global_map is not None:
        map_file = _write_json(out / MAP_FILE, global_map.model_dump(mode="json",
                                                                      exclude_none=True))
    pending = len(svc.store.unprocessed_submaps())
    manifest = _write_json(out / MANIFEST_FILE, {
        "store": str(store_path),
        "anchor": anchor,
        "anchor_session": anchor_session,
        "nodes": [{"id": ids[n], "node": n, "frame": frame_of[n], "stamp": node_stamp.get(n)}
                  for n in graph.nodes],
        "edges": listed,
        "stamps": stamp_kind,
        "stamp_0": stamp_0,
        "trajectories": {s: {k: str(p) for k, p in f.items()} for s, f in trajectories.items()},
        "factors": str(factors_file),
        "map": str(map_file) if map_file is not None else None,
        "pending_submaps": pending,
    })
    return ExportResult(out_dir=out, anchor=anchor, graph=g2o, nodes=node_file,
                        manifest=manifest, vertices=len(ids), edges=len(edges),
                        trajectories=trajectories, stamps=stamp_kind, factors=factors_file,
                        global_map=map_file)


__all__ = [
    "FACTORS_FILE",
    "GRAPH_FILE",
    "MANIFEST_FILE",
    "MAP_FILE",
    "NODES_FILE",
    "TRAJECTORY_DIR",
    "ExportResult",
    "export_store",
    "snapshot_store",
]
