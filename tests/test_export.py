"""`mergesvc export` / fleet.export.export_store (issue 11): a service's store as the global pose
graph in g2o and every session's keyframe trajectory in TUM (odometry alone, and merged).

The store is built in-process through the service (`MergeService.ingest`, no Zenoh) from the
keyframe submaps of tests/test_keyframes.py (a seeded fleet world with known truth); the files
are read back with gtsam.readG2o and wire.formats.read_tum and checked against the service
itself: a restarted service's status (the export rebuilds the service as a restart does), its
factors, and the odometry the submaps carry."""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from test_keyframes import interleaved, mission, pose_error, run_service
from typer.testing import CliRunner

from mergesvc.cli import app
from mergesvc.core.factors import factor_nodes
from mergesvc.core.frames import FrameId
from mergesvc.core.poses import pose3_from_model
from mergesvc.errors import InputError, StoreError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.export import ExportResult, export_store
from mergesvc.fleet.service import MergeService
from mergesvc.wire.formats import read_tum


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def odometry_chain(subs) -> dict[int, np.ndarray]:
    """Keyframe -> (4, 4) pose in the session frame, composed from the submaps' odometry."""
    T = {0: np.eye(4)}
    for sub in subs:
        odo = sub.odometry
        T[sub.keyframe] = T[odo.from_keyframe] @ pose3_from_model(odo.T_from_to).matrix()
    return T


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    _, robots = mission()
    store = tmp / "merge.db"
    svc = run_service(interleaved(robots), store=str(store))
    live = {"status": svc.status(), "factors": dict(svc.factors),
            "nodes": list(svc.graph.nodes), "factor_ids": list(svc.graph.factor_ids)}
    svc.close()
    again = MergeService(ServiceConfig(store=str(store)), None)  # a restart
    again.restore()
    restarted = again.status()
    again.close()
    before = _sha(store)
    res = export_store(store, tmp / "out")
    assert _sha(store) == before  # the store is read, never written
    return robots, live, restarted, res


def test_the_files_are_where_the_result_says(exported) -> None:
    res = exported[3]
    assert isinstance(res, ExportResult)
    assert res.graph.name == "graph.g2o" and res.nodes.name == "graph_nodes.json"
    assert all(p.is_file() for p in res.files)
    assert set(res.trajectories) == {"auv1/s0", "auv2/s0", "auv3/s0"}
    for name, files in res.trajectories.items():
        robot, session = name.split("/")
        assert files["odometry"].name == f"{robot}_{session}_odometry.tum"
        assert files["merged"].name == f"{robot}_{session}_merged.tum"
    assert res.stamps == dict.fromkeys(res.trajectories, "keyframe")  # no stamps in the submaps
    assert res.anchor == "auv1/s0#0"


def test_g2o_holds_every_node_and_factor_with_the_service_poses(exported) -> None:
    _, live, restarted, res = exported
    graph, initial = gtsam.readG2o(str(res.graph), True)
    nodes = {int(i): n for i, n in json.loads(res.nodes.read_text()).items()}
    assert sorted(nodes.values()) == sorted(live["nodes"])
    assert initial.size() == len(live["nodes"]) == res.vertices
    assert graph.size() == len(live["factor_ids"]) == res.edges
    # every node of the anchor's component: its pose in the status of the service restarted
    # from the same store (what the export rebuilds), and close to the live service's
    kf = restarted["keyframe_poses"]
    assert sum(len(v) for v in kf.values()) == len(nodes)  # everyone is aligned here
    for i, name in nodes.items():
        frame, k = name.rsplit("#", 1)
        T = initial.atPose3(i).matrix()
        np.testing.assert_allclose(T, kf[frame][k], atol=1e-6)
        rot, trans = pose_error(gtsam.Pose3(T),
                                gtsam.Pose3(np.asarray(live["status"]["keyframe_poses"][frame][k])))
        assert rot < 0.01 and trans < 1e-3, (name, rot, trans)


def test_g2o_edges_carry_the_factors_measurement_and_covariance(exported) -> None:
    _, live, _, res = exported
    graph, _ = gtsam.readG2o(str(res.graph), True)
    ids = {n: int(i) for i, n in json.loads(res.nodes.read_text()).items()}
    manifest = json.loads(res.manifest.read_text())
    edges = {e["factor_id"]: n for n, e in enumerate(manifest["edges"])}
    assert set(edges) == set(live["factor_ids"])
    kinds = {e["kind"] for e in manifest["edges"]}
    assert kinds - {"loop"} == {"odometry", "inter_robot"}
    for e in manifest["edges"]:  # a loop ties two keyframes of one session
        if e["kind"] == "loop":
            assert live["factors"][e["factor_id"]]["robot_a"] == \
                live["factors"][e["factor_id"]]["robot_b"]
    assert len(live["factors"]) > 0
    for fid, f in live["factors"].items():
        factor = graph.at(edges[fid])
        assert isinstance(factor, gtsam.BetweenFactorPose3)
        a, b = factor_nodes(f)
        assert list(factor.keys()) == [ids[str(a)], ids[str(b)]]
        np.testing.assert_allclose(factor.measured().matrix(),
                                   pose3_from_model(f.T_a_b).matrix(), atol=1e-12)
        np.testing.assert_allclose(factor.noiseModel().covariance(), np.asarray(f.covariance),
                                   rtol=1e-9, atol=1e-15)


def test_odometry_edges_are_the_submaps_odometry(exported) -> None:
    robots, _, _, res = exported
    graph, _ = gtsam.readG2o(str(res.graph), True)
    ids = {n: int(i) for i, n in json.loads(res.nodes.read_text()).items()}
    edges = {e["factor_id"]: n for n, e in enumerate(json.loads(res.manifest.read_text())["edges"])}
    sub = robots["auv2"].submaps[3]
    odo = sub.odometry
    factor = graph.at(edges[f"odom:auv2/s0#{odo.from_keyframe}-{sub.keyframe}"])
    assert list(factor.keys()) == [ids[f"auv2/s0#{odo.from_keyframe}"],
                                   ids[f"auv2/s0#{sub.keyframe}"]]
    np.testing.assert_allclose(factor.measured().matrix(),
                               pose3_from_model(odo.T_from_to).matrix(), atol=1e-12)
    np.testing.assert_allclose(factor.noiseModel().covariance(), np.asarray(odo.covariance),
                               rtol=1e-9, atol=1e-15)


def test_merged_tum_is_the_status_keyframe_poses(exported) -> None:
    _, _, restarted, res = exported
    for name, by_k in restarted["keyframe_poses"].items():
        stamps, poses = read_tum(res.trajectories[name]["merged"])
        ks = sorted(int(k) for k in by_k)
        np.testing.assert_array_equal(stamps, ks)  # stamps: keyframe indices
        np.testing.assert_allclose(poses, [by_k[str(k)] for k in ks], atol=1e-6)


def test_odometry_tum_composes_the_submaps_odometry(exported) -> None:
    robots, _, _, res = exported
    for robot, r in robots.items():
        chain = odometry_chain(r.submaps)
        stamps, poses = read_tum(res.trajectories[str(FrameId(robot, "s0"))]["odometry"])
        ks = sorted(chain)
        np.testing.assert_array_equal(stamps, ks)
        np.testing.assert_allclose(poses, [chain[k] for k in ks], atol=1e-9)
        # and the vehicle's own odometry poses (the truth of what it sent)
        for k, T in zip(ks, poses):
            np.testing.assert_allclose(T, np.linalg.inv(r.T_est[0]) @ r.T_est[k], atol=1e-6)


def test_submap_stamps_are_the_tum_stamps_and_a_lone_session_is_solved(tmp_path) -> None:
    """Stamped submaps (what mergesvc agent sends): their stamps in both files, and keyframe 0
    (no submap is cut there) with its stamp extrapolated back along the first two keyframes.
    One session, no factor: the service never solved, the export solves it (its merged
    trajectory is its odometry, in its own anchor frame)."""
    _, robots = mission()
    subs = [s.model_copy(update={"stamp": 100.0 + s.keyframe / 2})
            for s in robots["auv1"].submaps[:4]]
    store = tmp_path / "one.db"
    run_service(subs, store=str(store)).close()
    res = export_store(store, tmp_path / "out")
    assert res.stamps == {"auv1/s0": "submap"}
    assert json.loads(res.manifest.read_text())["stamp_0"] == {"auv1/s0": "extrapolated"}
    chain = odometry_chain(subs)
    for kind in ("odometry", "merged"):
        stamps, poses = read_tum(res.trajectories["auv1/s0"][kind])
        np.testing.assert_allclose(stamps, [100.0] + [s.stamp for s in subs])
        np.testing.assert_allclose(poses, [chain[0]] + [chain[s.keyframe] for s in subs],
                                   atol=1e-6)
    _, initial = gtsam.readG2o(str(res.graph), True)
    assert initial.size() == 5


def test_a_session_outside_the_anchors_component_gets_no_merged_file(tmp_path) -> None:
    """Two sessions no factor joins: the second's nodes are in g2o in its own frame (its
    keyframe 0), export.json says so, and it has no merged trajectory."""
    _, robots = mission()
    subs = robots["auv1"].submaps[:2] + [
        s.model_copy(update={"session_id": "s9"}) for s in robots["auv1"].submaps[:2]
    ]
    store = tmp_path / "two.db"
    svc = run_service(subs, store=str(store), min_map_objects=1000)  # nothing matches
    assert not svc.factors
    svc.close()
    res = export_store(store, tmp_path / "out")
    assert set(res.trajectories["auv1/s0"]) == {"odometry", "merged"}
    assert set(res.trajectories["auv1/s9"]) == {"odometry"}
    frames = {n["node"]: n["frame"] for n in json.loads(res.manifest.read_text())["nodes"]}
    assert {n: f for n, f in frames.items() if n.startswith("auv1/s9")} == dict.fromkeys(
        [f"auv1/s9#{k}" for k in (0, *(s.keyframe for s in subs[2:]))], "auv1/s9#0")
    graph, initial = gtsam.readG2o(str(res.graph), True)
    assert initial.size() == len(frames) and graph.size() == 4


def test_export_errors(tmp_path) -> None:
    with pytest.raises(InputError, match="no store file"):
        export_store(tmp_path / "nope.db", tmp_path / "out")
    (tmp_path / "junk.db").write_bytes(b"not a database at all" * 100)
    with pytest.raises(StoreError):
        export_store(tmp_path / "junk.db", tmp_path / "out")
    MergeService(ServiceConfig(store=str(tmp_path / "empty.db")), None).close()
    with pytest.raises(InputError, match="nothing to export"):
        export_store(tmp_path / "empty.db", tmp_path / "out")


def test_export_command_prints_one_line_per_file(exported, tmp_path) -> None:
    _, _, _, res = exported
    store = res.out_dir.parent / "merge.db"
    out = tmp_path / "cli"
    r = CliRunner().invoke(app, ["export", "--store", str(store), "--out", str(out)])
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert [Path(x).relative_to(out) for x in lines] == [p.relative_to(res.out_dir)
                                                         for p in res.files]
    assert (out / "graph.g2o").read_text() == res.graph.read_text()
    # the store from the settings when --store is not given, the graph settings honoured
    s = tmp_path / "s.json"
    s.write_text(json.dumps({"service": {"store": str(store)}}))
    r = CliRunner().invoke(app, ["export", "--out", str(tmp_path / "cli2"), "--settings", str(s)])
    assert r.exit_code == 0, r.output
    assert len(r.output.splitlines()) == len(lines)
    r = CliRunner().invoke(app, ["export", "--store", str(tmp_path / "nope.db"), "--out",
                                 str(out)])
    assert r.exit_code == 2 and "no store file" in r.output


def test_a_store_is_exported_as_its_own_fleet_whatever_the_settings_say(exported,
                                                                          tmp_path) -> None:
    _, _, _, res = exported
    store = tmp_path / "claimed.db"
    shutil.copyfile(res.out_dir.parent / "merge.db", store)
    with contextlib.closing(sqlite3.connect(store)) as c, c:
        c.execute("INSERT INTO meta (key, value) VALUES ('fleet', 'reef')")
    other = export_store(store, tmp_path / "out", config=ServiceConfig(fleet="another"))
    assert other.graph.read_text() == res.graph.read_text()


def test_a_store_on_read_only_media_is_exported(exported, tmp_path) -> None:
    """Read-only media (a read-only bind mount in a mount namespace of its own): SQLite cannot
    make a WAL file's index beside the store; the export reads a copy instead."""
    _, _, _, res = exported
    src, ro, live = tmp_path / "media", tmp_path / "ro", tmp_path / "live"
    for d in (src, ro, live, src / "wal"):
        d.mkdir()
    shutil.copyfile(res.out_dir.parent / "merge.db", src / "merge.db")  # closed cleanly
    # as a crash leaves a store: rows in its WAL not yet in the file (autocheckpoint off)
    shutil.copyfile(res.out_dir.parent / "merge.db", live / "merge.db")
    with contextlib.closing(sqlite3.connect(live / "merge.db")) as c:
        c.execute("PRAGMA wal_autocheckpoint=0")
        with c:
            c.execute("INSERT INTO meta (key, value) VALUES ('probe', 'in the wal')")
        for name in ("merge.db", "merge.db-wal"):
            shutil.copyfile(live / name, src / "wal" / name)
    snapshot = tmp_path / "snapshot.py"
    snapshot.write_text(
        "import sqlite3, sys\nfrom mergesvc.fleet.export import snapshot_store\n"
        "c = sqlite3.connect(snapshot_store(sys.argv[1], sys.argv[2]))\n"
        "print(c.execute(\"SELECT value FROM meta WHERE key = 'probe'\").fetchone()[0])\n")
    script = (f"mount --bind {src} {ro} && mount -o remount,bind,ro {ro} && "
              f"! touch {ro}/probe 2>/dev/null && {sys.executable} -m mergesvc.cli export "
              f"--store {ro}/merge.db --out {tmp_path / 'out'} >/dev/null && exec "
              f"{sys.executable} {snapshot} {ro}/wal/merge.db {tmp_path}/copy.db")
    probe = subprocess.run(["unshare", "-m", "sh", "-c", "mount --bind / /mnt"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"no mount namespace here to make read-only media: {probe.stderr.strip()}")
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True,
                       timeout=120, cwd=Path(__file__).parents[1])
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out" / "graph.g2o").read_text() == res.graph.read_text()
    assert r.stdout.strip() == "in the wal"  # the WAL's rows were read with the file


def test_evo_ape_on_the_export_is_the_service_side_ate(tmp_path) -> None:
    """evo (its Python API, as `evo_ape tum truth.tum export.tum --align`: SE(3) Umeyama, no
    scale, translation part) on the exported TUM files gives the ATE core/trajectory.py
    computes from the service's own poses on the same keyframes, keyframe 0 included. The
    submaps are stamped as mergesvc agent stamps them (the frame's time; none is cut at
    keyframe 0): the export once left keyframe 0 out, and evo disagreed with the demo."""
    from evo.core import sync
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape
    from evo.tools import file_interface

    from mergesvc.core.trajectory import ate_rmse
    from mergesvc.wire.formats import write_tum

    t0, dt = 1000.0, 0.5  # frame k at t0 + k dt
    _, robots = mission()
    subs = [s.model_copy(update={"stamp": t0 + dt * s.keyframe}) for s in interleaved(robots)]
    store = tmp_path / "stamped.db"
    svc = run_service(subs, store=str(store))
    poses = svc.status()["keyframe_poses"]
    svc.close()
    res = export_store(store, tmp_path / "out")
    checked = 0
    for robot, rb in robots.items():
        name = str(FrameId(robot, "s0"))
        truth = tmp_path / f"{robot}_truth.tum"  # every frame
        write_tum(truth, t0 + dt * np.arange(len(rb.T_true)), np.stack(rb.T_true))
        ours = {"odometry": odometry_chain(rb.submaps),
                "merged": {int(k): np.asarray(T) for k, T in poses.get(name, {}).items()}}
        for kind, path in res.trajectories[name].items():
            stamps, _ = read_tum(path)
            ks = [round((s - t0) / dt) for s in stamps]
            assert ks[0] == 0 and ks == sorted(ours[kind]), (name, kind)  # every keyframe
            np.testing.assert_allclose(stamps, t0 + dt * np.array(ks), atol=1e-9)
            ref, est = sync.associate_trajectories(
                file_interface.read_tum_trajectory_file(str(truth)),
                file_interface.read_tum_trajectory_file(str(path)))
            assert est.num_poses == len(ks)
            got = ape(ref, est, PoseRelation.translation_part, align=True,
                      correct_scale=False).stats["rmse"]
            want = ate_rmse(np.stack([ours[kind][k] for k in ks]),
                            np.stack([rb.T_true[k] for k in ks]))
            assert got == pytest.approx(want, rel=1e-6, abs=1e-6), (name, kind)
            checked += 1
    assert checked >= 4  # odometry of every robot, merged of the anchor's component


def test_keyframe_0_stamp_rules() -> None:
    from mergesvc.fleet.export import _session_stamps

    assert _session_stamps({0, 4, 8}, {4: 12.0, 8: 14.0}) == ({0: 10.0, 4: 12.0, 8: 14.0},
                                                             "extrapolated")
    assert _session_stamps({0, 4, 8}, {0: 9.5, 4: 12.0, 8: 14.0})[1] == "submap"
    assert _session_stamps({0, 4}, {4: 12.0}) == ({0: 0.0, 4: 4.0}, "keyframe")  # too few
    assert _session_stamps({0, 4, 8}, {4: 12.0})[1] == "keyframe"  # a keyframe without one
    assert _session_stamps({0, 4, 8}, {4: 12.0, 8: 12.0})[1] == "keyframe"  # not growing
