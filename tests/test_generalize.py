"""The generalization benchmark: frame conventions transform worlds and their truth
consistently, the cosine + Hungarian baseline, the real-data worlds, and the quick matrix."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mergesvc.bench.generalize import (
    METHODS,
    NGM_METHODS,
    UNRELATED_CASES,
    UNRELATED_SEED,
    Cell,
    GeneralizePlan,
    cell_scenarios,
    cosine_hungarian,
    cosine_hungarian_outcome,
    lacking_pairs,
    quick_plan,
    run_generalize,
    unrelated_pairs,
)
from mergesvc.core.model import ObjectArrays
from mergesvc.sim import Family, Scenario, make_scenario
from mergesvc.sim.appearance import Appearance, class_centroids
from mergesvc.sim.conventions import (
    C_CAMERA,
    C_NED,
    convention_rotation,
    rotate_points,
    rotate_world,
    supports_up,
)
from mergesvc.sim.real_data import (
    DINO_CENTROIDS,
    KITTI_GT,
    KITTI_ORB,
    camera_to_gravity,
    data_available,
    load_dino_centroids,
    load_kitti_poses_34,
)
from mergesvc.sim.worlds import WorldSpec, express, fit_rigid_kabsch, kitti_world, pool_world

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
HAS_DINO = data_available(SHARED_DATA, DINO_CENTROIDS)
HAS_KITTI = data_available(SHARED_DATA, KITTI_GT, KITTI_ORB, DINO_CENTROIDS)
needs_dino = pytest.mark.skipif(not HAS_DINO, reason="../shared/data (DINO centroids) absent")
needs_kitti = pytest.mark.skipif(not HAS_KITTI, reason="../shared/data (KITTI-00) absent")

FRAMES = [("enu", "enu"), ("camera", "camera"), ("ned", "ned"), ("random", "random"),
          ("camera", "enu"), ("ned", "camera"), ("random", "ned")]


def _conventions(a: str, b: str, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    C_map = convention_rotation(a, rng)
    return C_map, C_map if a == b else convention_rotation(b, rng)


def _true_pairs(sc: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) submap positions and (k, 3) positions of their true map objects."""
    m, s = sc.map.arrays(), sc.submap.arrays()
    index = {oid: k for k, oid in enumerate(m.ids)}
    rows = [(j, index[sc.truth[sid]]) for j, sid in enumerate(s.ids) if sc.truth[sid]]
    return (s.position_xyz_m[[j for j, _ in rows]], m.position_xyz_m[[k for _, k in rows]])


def _residuals(sc: Scenario) -> np.ndarray:
    """|R p_sub + t - p_map| of every true pair under the scenario's truth (k,)."""
    p_sub, p_map = _true_pairs(sc)
    return np.linalg.norm(p_sub @ sc.R_map_submap.T + sc.t_map_submap - p_map, axis=1)


# ------------------------------------------------------------------ conventions


def test_convention_matrices_are_rotations_with_the_documented_axes() -> None:
    rng = np.random.default_rng(0)
    for name in ("enu", "ned", "camera", "random"):
        C = convention_rotation(name, rng)
        np.testing.assert_allclose(C @ C.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(C) == pytest.approx(1.0)
    up, forward, left = np.eye(3)[2], np.eye(3)[0], np.eye(3)[1]
    np.testing.assert_allclose(C_CAMERA @ up, [0, -1, 0])  # camera: y down
    np.testing.assert_allclose(C_CAMERA @ forward, [0, 0, 1])  # z forward
    np.testing.assert_allclose(C_CAMERA @ left, [-1, 0, 0])  # x right
    np.testing.assert_allclose(C_NED @ up, [0, 0, -1])  # z down
    with pytest.raises(ValueError):
        convention_rotation("random")
    with pytest.raises(ValueError):
        convention_rotation("nwu")


@pytest.mark.parametrize(("map_conv", "sub_conv"), FRAMES)
@pytest.mark.parametrize("family", [Family.UNDERWATER, Family.KITTI])
def test_rotate_world_transforms_positions_and_truth_consistently(
    map_conv: str, sub_conv: str, family: Family
) -> None:
    sc = make_scenario(family, seed=5, n_map=60 if family is Family.KITTI else 25)
    C_map, C_sub = _conventions(map_conv, sub_conv)
    rot = rotate_world(sc, C_map, C_sub)
    # positions are the originals, rotated
    np.testing.assert_allclose(rot.map.arrays().position_xyz_m,
                               rotate_points(C_map, sc.map.arrays().position_xyz_m), atol=1e-5)
    np.testing.assert_allclose(rot.submap.arrays().position_xyz_m,
                               rotate_points(C_sub, sc.submap.arrays().position_xyz_m),
                               atol=1e-5)
    # the truth still maps every submap object onto its map object, as well as before
    np.testing.assert_allclose(_residuals(rot), _residuals(sc), atol=1e-4)
    assert np.median(_residuals(rot)) < 3.0
    R = rot.R_map_submap
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    # map back: C_map^T (R' C_sub p + t') is the original map frame's answer
    p_sub, _ = _true_pairs(rot)
    back = (p_sub @ R.T + rot.t_map_submap) @ C_map
    orig_sub, _ = _true_pairs(sc)
    np.testing.assert_allclose(back, orig_sub @ sc.R_map_submap.T + sc.t_map_submap, atol=1e-4)
    assert rot.truth == sc.truth and rot.map.arrays().ids == sc.map.arrays().ids
    # conventions by name give the same world
    named = rotate_world(sc, map_conv, sub_conv, rng=np.random.default_rng(3))
    np.testing.assert_allclose(named.R_map_submap, rot.R_map_submap, atol=1e-12)


@pytest.mark.skipif(not supports_up(), reason="this build's file models have no `up` field")
@pytest.mark.parametrize(("map_conv", "sub_conv"), FRAMES)
def test_declared_up_is_the_frames_vertical(map_conv: str, sub_conv: str) -> None:
    sc = make_scenario(Family.UNDERWATER, seed=2, n_map=25)
    C_map, C_sub = _conventions(map_conv, sub_conv)
    rot = rotate_world(sc, C_map, C_sub, declare_up=True)
    up_map, up_sub = np.asarray(rot.map.up), np.asarray(rot.submap.up)
    np.testing.assert_allclose(up_map, C_map @ [0, 0, 1], atol=1e-8)
    # the truth takes the submap's vertical onto the map's
    np.testing.assert_allclose(rot.R_map_submap @ up_sub, up_map, atol=1e-6)
    assert "up" not in json.loads(rotate_world(sc, C_map, C_sub).map.model_dump_json(
        exclude_none=True))


def test_fit_rigid_kabsch_recovers_a_transform() -> None:
    rng = np.random.default_rng(1)
    R = convention_rotation("random", rng)
    src = rng.normal(size=(10, 3))
    R_est, t_est = fit_rigid_kabsch(src, src @ R.T + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, [1.0, 2.0, 3.0], atol=1e-9)


# ------------------------------------------------------------------ appearance


@pytest.mark.parametrize("dim", [128, 384, 768])
def test_class_centroids_keep_the_real_cosines_in_any_dimension(dim: int) -> None:
    rng = np.random.default_rng(7)
    real = load_dino_centroids(SHARED_DATA / DINO_CENTROIDS) if HAS_DINO else rng.normal(
        size=(12, 384)) + 2.0
    U = real / np.linalg.norm(real, axis=1, keepdims=True)
    C = class_centroids(12, dim, rng, real)
    assert C.shape == (12, dim)
    # the same set of pairwise cosines (the classes come out shuffled)
    cos_in = np.sort((U @ U.T)[np.triu_indices(12, 1)])
    cos_out = np.sort((C @ C.T)[np.triu_indices(12, 1)])
    np.testing.assert_allclose(cos_out, cos_in, atol=1e-9)
    more = class_centroids(20, dim, rng, real)
    assert more.shape == (20, dim)
    np.testing.assert_allclose(np.linalg.norm(more, axis=1), 1.0)


def test_fused_views_carry_the_tracked_variance_s_over_n() -> None:
    rng = np.random.default_rng(0)
    app = Appearance(class_centroids(4, 64, rng))
    x = app.instances(np.array([1]), rng)[0]
    _, var = app.fused(x, np.full(5, 0.2), rng)
    assert var == pytest.approx(0.2 / 5)
    # more, better views: closer to the truth
    cos = [float(mu @ x / np.linalg.norm(mu) / np.linalg.norm(x))
           for mu, _ in (app.fused(x, np.full(n, s), rng) for n, s in ((1, 0.5), (30, 0.05)))]
    assert cos[1] > cos[0]


# ------------------------------------------------------------------ the baseline


def _arrays(ids: list[str], emb: list[list[float]]) -> ObjectArrays:
    e = np.asarray(emb, dtype=np.float64)
    return ObjectArrays(ids, np.zeros((len(ids), 3)) + np.arange(len(ids))[:, None], e,
                        np.full(e.shape, 0.1), np.ones(len(ids), dtype=np.int64))


def test_cosine_hungarian_is_the_optimal_one_to_one_assignment() -> None:
    # map objects along the axes; greedy (sub0 first) would take m0 twice or leave sub1 with
    # its worst option; the optimum gives m0 to sub1 and m1 to sub0
    map_ = _arrays(["m0", "m1", "m2"], [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    sub = _arrays(["a", "b"], [[0.9, 0.8, 0.0], [0.85, 0.1, 0.0]])
    np.testing.assert_array_equal(cosine_hungarian(map_, sub), [1, 0])
    # the scale of an embedding does not matter (cosine)
    sub_scaled = _arrays(["a", "b"], [[9.0, 8.0, 0.0], [0.085, 0.01, 0.0]])
    np.testing.assert_array_equal(cosine_hungarian(map_, sub_scaled), [1, 0])
    out = cosine_hungarian_outcome(map_, sub)
    assert out.result.accepted and out.result.reason.value == "not_verified"
    got = {m.submap_object: (m.map_object, m.score) for m in out.result.matches}
    assert got["a"][0] == "m1" and got["b"][0] == "m0"
    assert got["b"][1] == pytest.approx(0.85 / np.hypot(0.85, 0.1), abs=1e-6)


def test_cosine_hungarian_leaves_extra_submap_objects_unmatched() -> None:
    map_ = _arrays(["m0", "m1"], [[1, 0], [0, 1]])
    sub = _arrays(["a", "b", "c"], [[1, 0.1], [0.1, 1], [0.7, 0.7]])
    a = cosine_hungarian(map_, sub)
    assert sorted(a.tolist()) == [-1, 0, 1]
    assert a[0] == 0 and a[1] == 1


# ------------------------------------------------------------------ real-data worlds


@needs_kitti
@pytest.mark.parametrize(("map_conv", "sub_conv"), FRAMES)
def test_kitti_world_truth_holds_in_every_convention(map_conv: str, sub_conv: str) -> None:
    gt = load_kitti_poses_34(SHARED_DATA / KITTI_GT)
    est = load_kitti_poses_34(SHARED_DATA / KITTI_ORB)
    dino = load_dino_centroids(SHARED_DATA / DINO_CENTROIDS)
    world = kitti_world(WorldSpec("kitti00", 150, dim=128, n_cases=2, sub_size=10), 0, gt,
                        est, dino)
    base = express(world, np.eye(3), np.eye(3), declare_up=False)
    rot = express(world, *_conventions(map_conv, sub_conv), declare_up=False)
    for sc0, sc in zip(base, rot, strict=True):
        res = _residuals(sc)
        np.testing.assert_allclose(res, _residuals(sc0), atol=1e-4)
        # stereo noise grows with range (up to ~2.5 m at 35 m) and the map drifts
        assert np.median(res) < 2.5
        assert sum(v is None for v in sc.truth.values()) == 2  # the false detections
    if supports_up():
        # declared verticals: the map's nominal one, the vehicle's true one; they agree through
        # the truth up to the map's drift and the road's grade (a few degrees)
        rot_up = express(world, *_conventions(map_conv, sub_conv), declare_up=True)
        for sc in rot_up:
            up_map, up_sub = np.asarray(sc.map.up), np.asarray(sc.submap.up)
            angle = np.degrees(np.arccos(np.clip(up_map @ sc.R_map_submap @ up_sub, -1, 1)))
            assert angle < 8.0
    # KITTI's own frame is the camera convention: the map expressed in camera axes is the
    # ORB-SLAM2 world frame, whose vertical is -y
    if map_conv == "camera":
        m = rot[0].map.arrays().position_xyz_m
        path = est[:3200, :3, 3]
        d = np.linalg.norm(m[:, None, [0, 2]] - path[None, ::20, [0, 2]], axis=2).min(axis=1)
        assert np.median(d) < 15.0  # objects beside the real (estimated) path


@needs_kitti
def test_camera_to_gravity_makes_kitti_level() -> None:
    T = camera_to_gravity(load_kitti_poses_34(SHARED_DATA / KITTI_GT))
    # the drive stays within a few metres of height over 3.7 km, and the body z stays up
    assert np.ptp(T[:, 2, 3]) < 30.0
    assert np.min(T[:, 2, 2]) > np.cos(np.radians(10))


@needs_dino
def test_pool_world_duplicates_count_as_correct() -> None:
    dino = load_dino_centroids(SHARED_DATA / DINO_CENTROIDS)
    world = pool_world(WorldSpec("pool", 30, duplicates=0.5, n_cases=6, sub_size=5,
                                 n_false=1), 1, dino)
    assert world.maps[0].n == 45
    scs = express(world, C_NED, C_NED, declare_up=False)
    twins = [(sid, eq) for sc in scs for sid, eq in sc.equivalent.items() if len(eq) > 1]
    assert twins
    sc = next(s for s in scs if twins[0][0] in s.equivalent)
    sid, eq = twins[0]
    assert all(sc.is_correct(sid, m) for m in eq)
    assert np.median(_residuals(scs[0])) < 1.5


# ------------------------------------------------------------------ the matrix


def _check_metrics(report: dict) -> None:
    for name, e in report["cells"].items():
        if e["skipped"]:
            continue
        for m in report["methods"]:
            o = e["methods"][m]["over_seeds"]
            if m.startswith("paper") and not o.get("cases"):
                continue
            assert o["cases"] > 0, (name, m)
            for k in ("node_accuracy", "paper_accuracy", "accepted_fraction"):
                assert 0.0 <= o[k]["median"] <= 1.0, (name, m, k)
            for k in ("precision", "recall"):
                v = o[k]["median"]
                assert np.isnan(v) or 0.0 <= v <= 1.0, (name, m, k)
            assert 0 <= o["accepted"] <= o["cases"]
            assert o["latency_p50_ms"]["median"] > 0
            assert o["latency_p99_ms"]["median"] >= o["latency_p50_ms"]["median"]
            assert sum(o["reasons"].values()) == o["cases"]
            for probe in ("unrelated", "lacking"):
                u = o.get(probe)
                if m.startswith("paper"):
                    assert u is None  # paper mode accepts nothing: not asked
                else:
                    assert u["cases"] == min(UNRELATED_CASES, e["cell"]["n_cases"]) * o["seeds"]
                    assert 0 <= u["accepted"] <= u["cases"] and u["matches"] >= u["accepted"]
        # the baseline matches every submap object and never verifies, on a place the map
        # lacks too
        cos = e["methods"]["cos-hungarian"]["over_seeds"]
        assert cos["accepted"] == cos["cases"]
        assert cos["unrelated"]["accepted"] == cos["unrelated"]["cases"]
        assert cos["lacking"]["accepted"] == cos["lacking"]["cases"]


def test_quick_matrix_returns_every_cell_with_sane_metrics() -> None:
    plan = GeneralizePlan.quick(seed=0, data_dir=SHARED_DATA)
    report = run_generalize(plan)
    assert list(report["cells"]) == [c.name for c in quick_plan()]
    assert tuple(report["methods"]) == METHODS + NGM_METHODS
    _check_metrics(report)
    for c in quick_plan():
        e = report["cells"][c.name]
        if (c.family == "pool" and not HAS_DINO) or (c.family == "kitti00" and not HAS_KITTI):
            assert e["skipped"].startswith("data absent")
        elif c.vertical and not supports_up():
            assert "up" in e["skipped"]
        else:
            assert e["skipped"] is None
    # the generator's own world never needs the shared data
    assert report["cells"]["gen-pool/camera"]["skipped"] is None
    # the cosine baseline answers even where verification rejects; on the clean pool it is
    # right for most objects
    if HAS_DINO:
        cos = report["cells"]["pool"]["methods"]["cos-hungarian"]["over_seeds"]
        assert cos["node_accuracy"]["median"] > 0.5
    json.dumps(report, default=float)  # JSON-ready
    assert "| cell |" in report["markdown"]


def test_submaps_of_another_world_are_counted_as_the_matcher_answers_them() -> None:
    """The unrelated probe: each of this seed's maps against a submap of the same cell's world
    for another seed (no object in common), counted per method as `match` answers them."""
    from mergesvc.bench.generalize import _Data
    from mergesvc.core.config import match_config
    from mergesvc.core.pipeline import match

    cell = Cell("gen-pool/camera", "gen-pool", frame="camera", n_map=0, n_cases=5, sub_size=0,
                paper_cases=0)
    seed = 3
    here, there = cell_scenarios(cell, seed), cell_scenarios(cell, seed + UNRELATED_SEED)
    pairs = unrelated_pairs(cell, seed, _Data(SHARED_DATA), here)
    assert len(pairs) == UNRELATED_CASES
    for j, (mp, sub) in enumerate(pairs):
        assert mp is here[j].map
        assert sub.model_dump_json() == there[j].submap.model_dump_json()
        # none of the submap's objects is in the map: the map objects the other world's truth
        # names are none of this map's
        theirs = there[j].map.arrays()
        truth = [theirs.ids.index(m) for m in there[j].truth.values() if m is not None]
        ours = {row.tobytes() for row in mp.arrays().embeddings_nd}
        assert truth and not ours & {theirs.embeddings_nd[k].tobytes() for k in truth}
    accepted = sum(match(mp, sub, match_config()).result.accepted for mp, sub in pairs)
    # the harder probe: each map without the submap's own objects (duplicates too), the rest
    # as it was
    lacking = lacking_pairs(here)
    assert len(lacking) == UNRELATED_CASES
    for sc, (mp, sub) in zip(here, lacking, strict=False):
        assert sub is sc.submap
        ids = {o.id for o in mp.objects}
        theirs = {t for t in sc.truth.values() if t} | {
            x for v in sc.equivalent.values() for x in v}
        assert theirs and not ids & theirs
        assert ids | theirs == {o.id for o in sc.map.objects}
    lacked = sum(match(mp, sub, match_config()).result.accepted for mp, sub in lacking)
    report = run_generalize(GeneralizePlan([cell], seed=seed, methods=("verified",)))
    o = report["cells"][cell.name]["methods"]["verified"]["over_seeds"]
    assert o["unrelated"]["cases"] == UNRELATED_CASES and o["unrelated"]["accepted"] == accepted
    assert o["lacking"]["cases"] == UNRELATED_CASES and o["lacking"]["accepted"] == lacked
    assert "| unrelated accepted | lacking accepted |" in report["markdown"]


def test_ngm_is_compared_with_the_default_solver_cell_by_cell() -> None:
    """NGM beside RRWM on the same cases: node accuracy, precision, p50 ratio, the verified
    target; the cell's rows and the comparison in the markdown."""
    cell = Cell("gen-pool/camera", "gen-pool", frame="camera", n_map=0, n_cases=3, sub_size=0,
                paper_cases=1)
    report = run_generalize(GeneralizePlan([cell], methods=("verified", "paper", *NGM_METHODS)))
    rows = report["ngm_vs_default"]["gen-pool/camera"]
    assert set(rows) == {"verified", "paper"}
    v = rows["verified"]
    o = report["cells"]["gen-pool/camera"]["methods"]
    assert v["node_accuracy"]["ngm"] == o["verified-ngm"]["over_seeds"]["node_accuracy"]["median"]
    assert v["node_accuracy_diff"] == pytest.approx(
        v["node_accuracy"]["ngm"] - v["node_accuracy"]["default"])
    assert v["p50_ratio"] > 0 and isinstance(v["meets_target"], bool)
    assert "meets_target" not in rows["paper"]
    assert o["paper-ngm"]["over_seeds"]["cases"] == 1  # paper methods: the paper cases only
    md = report["markdown"]
    assert "| gen-pool/camera | base | 45 | verified-ngm |" in md
    assert "### NGM against the default solver" in md and "of 1 cells" in md


def test_cells_needing_absent_data_are_skipped_cleanly(tmp_path: Path) -> None:
    cells = [replace(c, n_cases=2, paper_cases=1) for c in quick_plan()
             if c.family in ("pool", "gen-pool")][:2]
    cells.append(Cell("gen-pool/camera", "gen-pool", frame="camera", n_map=0, n_cases=2,
                      sub_size=0, paper_cases=0))
    report = run_generalize(GeneralizePlan(cells, seeds=2, data_dir=tmp_path,
                                           methods=("verified", "cos-hungarian")))
    assert report["cells"]["pool"]["skipped"].startswith("data absent")
    e = report["cells"]["gen-pool/camera"]
    assert e["skipped"] is None and e["methods"]["verified"]["over_seeds"]["seeds"] == 2
    assert "skipped (data absent" in report["markdown"]


def test_cli_bench_generalize_writes_json_and_markdown(tmp_path: Path) -> None:
    out = tmp_path / "gen.json"
    r = subprocess.run(
        [sys.executable, "-m", "mergesvc.cli", "bench", "generalize", "--quick", "--no-paper",
         "--cell", "gen-pool", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "gen-pool/camera" in r.stdout and "cos-hungarian" in r.stdout
    report = json.loads(out.read_text())
    assert list(report["cells"]) == ["gen-pool/camera"]
    assert out.with_suffix(".md").read_text().startswith("| cell |")
