"""Worlds of the generalization benchmark (bench/generalize.py), which do not share the
generator's assumptions (axis conventions, embedding dimension, map size, look-alikes,
duplicates, range noise, declared vertical).

Worlds come from real data where it exists (`../shared/data`, real_data.py): the KITTI-00 ground
truth drive (camera axes, y down) with the ORB-SLAM2 estimate of the same drive as the map's
drifting frame, and class centroids from 12 real DINO ViT-S centroids; and from the project's own
generators (scenario.py, runs.py). Every world is built in a gravity-aligned frame (z up,
vehicles x forward, y left) and then written (`express`), as `match` files parsed with
`parse_model`, in the frame conventions of a cell (conventions.py): camera (x right, y down,
z forward), ENU (z up), NED (z down), a random rotation of the whole world, or the map in one
convention and the submap in another. A submap is in its vehicle's frame at the cut; a map in its
session's frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mergesvc.core.model import ObjectArrays, ObjectMap, Submap, parse_model
from mergesvc.core.verify import align
from mergesvc.sim.appearance import Appearance, class_centroids, view_quality
from mergesvc.sim.conventions import E_Z, _file_dict, rotate_points, rotate_truth, up_in
from mergesvc.sim.real_data import camera_to_gravity
from mergesvc.sim.runs import underwater_run
from mergesvc.sim.scenario import Family, Scenario, make_scenario

# ============================================================================================
# Worlds: built gravity-aligned, expressed in a cell's conventions afterwards
# ============================================================================================


@dataclass(frozen=True)
class NoiseModel:
    """Position noise of one measurement: sigma(r) = sigma0 + k1 r + k2 r^2 along the ray,
    sigma_cross across it; a fraction of outliers with the range scaled by U(0.6, 1.4)."""

    sigma0_m: float
    k1: float
    k2: float
    sigma_cross_m: float
    outlier_rate: float

    def measure(self, rel_xyz_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) true sensor-relative vectors -> noisy ones."""
        rel = np.atleast_2d(rel_xyz_m)
        r = np.linalg.norm(rel, axis=1, keepdims=True)
        ray = rel / np.maximum(r, 1e-9)
        sigma = self.sigma0_m + self.k1 * r + self.k2 * r**2
        out = rel + ray * rng.normal(size=r.shape) * sigma
        out += rng.normal(size=rel.shape) * self.sigma_cross_m
        bad = rng.random(len(rel)) < self.outlier_rate
        out[bad] = rel[bad] * rng.uniform(0.6, 1.4, size=(int(bad.sum()), 1))
        return out

    def scaled(self, factor: float, outlier_rate: float) -> NoiseModel:
        return NoiseModel(self.sigma0_m * factor, self.k1 * factor, self.k2 * factor,
                          self.sigma_cross_m * factor, outlier_rate)


DRIVE_NOISE = NoiseModel(0.1, 0.0, 0.0018, 0.1, 0.02)  # stereo: ~2.3 m at 35 m
POOL_NOISE = NoiseModel(0.08, 0.07, 0.0, 0.05, 0.03)  # sonar: ~0.4 m at 4.5 m


@dataclass(frozen=True)
class RawCase:
    """One submap of a world, gravity-aligned: body frame x forward, y left, z up (up to the
    vehicle's tilt). T_map_submap = (R_map_submap, t_map_submap); up_sub_xyz: the true vertical
    in the submap frame; map_index: which map of the world it is matched against."""

    sub: ObjectArrays
    truth: dict[str, str | None]
    equivalent: dict[str, tuple[str, ...]]
    R_map_submap: np.ndarray
    t_map_submap: np.ndarray
    map_index: int = 0
    up_sub_xyz: np.ndarray | None = None  # None: R_map_submap^T e_z (the map's vertical)


@dataclass(frozen=True)
class World:
    """Maps (gravity-aligned, z up) and the submap cases cut against them."""

    family: str
    maps: list[ObjectArrays]
    cases: list[RawCase]
    paper_radius_m: float
    robot_map: str = "car1"
    robot_sub: str = "car2"
    notes: tuple[str, ...] = ()


def fit_rigid_kabsch(src_xyz: np.ndarray, dst_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares R, t with dst ~ R src + t; (n, 3) each, n >= 3 not collinear
    (`verify.align`, gtsam's Umeyama)."""
    T = align(src_xyz, dst_xyz)
    if T is None:
        raise ValueError("a rigid fit needs at least 3 point pairs")
    return T.rotation().matrix(), np.asarray(T.translation())


def _local_truth(
    true_map_xyz: np.ndarray, est_map_xyz: np.ndarray, centre_xyz: np.ndarray, radius_m: float,
    T_W_B: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """T_map_submap where the map drifts: the rigid fit of the true positions of map objects
    near the submap to their map positions (what the map's frame is, there), after T_W_B."""
    d = np.linalg.norm(true_map_xyz - centre_xyz, axis=1)
    near = np.flatnonzero(d <= radius_m)
    if len(near) < 6:
        near = np.argsort(d)[:6]
    R_fix, t_fix = fit_rigid_kabsch(true_map_xyz[near], est_map_xyz[near])
    return R_fix @ T_W_B[:3, :3], R_fix @ T_W_B[:3, 3] + t_fix


def _add_duplicates(
    n_objects: int, est_xyz: np.ndarray, fraction: float, rng: np.random.Generator,
    offset_sigma_m: float = 0.7,
) -> tuple[list[int], np.ndarray]:
    """Failed re-association: a copy of a fraction of the objects, ~1 m away, fused from other
    views. Returns (source index of each copy, copy positions (m, 3))."""
    n_dup = round(fraction * n_objects)
    src = [int(i) for i in rng.choice(n_objects, size=n_dup, replace=False)] if n_dup else []
    xyz = est_xyz[src] + rng.normal(size=(n_dup, 3)) * offset_sigma_m if n_dup else np.zeros(
        (0, 3))
    return src, xyz


def _with_duplicates(
    arrs: ObjectArrays, ids: list[str], map_xyz: np.ndarray, truth_emb: np.ndarray,
    fraction: float, app: Appearance, rng: np.random.Generator, offset_sigma_m: float = 0.7,
) -> tuple[ObjectArrays, dict[int, list[str]]]:
    """The map with duplicates appended (`_add_duplicates`, 1-3 views each), and the map ids of
    each physical object (its own first, then its copies)."""
    n_obj = len(ids)
    src, dup_xyz = _add_duplicates(n_obj, map_xyz, fraction, rng, offset_sigma_m)
    same: dict[int, list[str]] = {i: [ids[i]] for i in range(n_obj)}
    if src:
        d_ids = [f"m{n_obj + j}" for j in range(len(src))]
        d_obs = rng.integers(1, 4, size=len(src))
        d_arr = _map_arrays(d_ids, dup_xyz, truth_emb[src], d_obs,
                            [rng.uniform(0.2, 1.0, size=o) for o in d_obs], app, rng)
        arrs = _concat(arrs, d_arr)
        for j, i in enumerate(src):
            same[i].append(d_ids[j])
    return arrs, same


def _map_arrays(
    ids: list[str], xyz: np.ndarray, truth_emb: np.ndarray, n_obs: np.ndarray,
    range_frac: list[np.ndarray], app: Appearance, rng: np.random.Generator,
) -> ObjectArrays:
    means, var = [], []
    for k in range(len(ids)):
        mu, v = app.fused(truth_emb[k], view_quality(range_frac[k], rng), rng)
        means.append(mu)
        var.append(v)
    d = app.dim
    return ObjectArrays(list(ids), np.asarray(xyz, dtype=np.float64), np.array(means),
                        np.repeat(np.array(var)[:, None], d, axis=1), np.asarray(n_obs))


@dataclass(frozen=True)
class WorldSpec:
    """The knobs of a world (one cell, one seed)."""

    family: str
    n_map: int
    dim: int = 384
    lookalike: str = "base"  # low | base | high
    duplicates: float = 0.0  # fraction of map objects present twice
    noise: str = "base"  # base | high
    n_cases: int = 8
    sub_size: int = 20  # 0: cycle 2-5 (pool)
    n_false: int = 2


LOOKALIKE = {  # (classes for a drive, classes for a pool, instance scale)
    "low": (28, 14, 0.9),
    "base": (16, 8, 0.45),
    "high": (4, 3, 0.22),
}


def _appearance(spec: WorldSpec, rng: np.random.Generator, dino: np.ndarray | None,
                pool: bool) -> Appearance:
    n_drive, n_pool, inst = LOOKALIKE[spec.lookalike]
    n_classes = n_pool if pool else n_drive
    view_noise = 1.8 if spec.noise == "base" else 2.4
    return Appearance(class_centroids(n_classes, spec.dim, rng, dino), inst, view_noise)


def _noise(base: NoiseModel, spec: WorldSpec) -> NoiseModel:
    return base if spec.noise == "base" else base.scaled(2.5, 0.1)


def kitti_world(
    spec: WorldSpec, seed: int, gt_poses: np.ndarray, est_poses: np.ndarray,
    dino: np.ndarray | None, split: int = 3200,
) -> World:
    """The real KITTI-00 drive: objects along the first `split` frames (2.5-12 m off the path,
    0-4 m above the road), the map built from those frames placed with the ORB-SLAM2 estimate
    (its real drift), submaps at loop-closure places after `split` in the true body frame.

    gt_poses / est_poses: (n, 4, 4) KITTI poses in camera axes (`load_kitti_poses_34`)."""
    rng = np.random.default_rng([seed, 9, 1])
    T_true = camera_to_gravity(gt_poses)
    T_est = camera_to_gravity(est_poses)
    xyz_path = T_true[:, :3, 3]
    n_obj = spec.n_map
    app = _appearance(spec, rng, dino, pool=False)
    noise = _noise(DRIVE_NOISE, spec)
    lateral_max = 12.0 if n_obj <= 1000 else 30.0
    # objects: anchored at frames of the first pass, beside the road
    at = rng.integers(20, split, size=n_obj)
    fwd = T_true[at, :3, 0]
    left = T_true[at, :3, 1]
    side = rng.choice([-1.0, 1.0], size=n_obj) * rng.uniform(2.5, lateral_max, size=n_obj)
    along = rng.uniform(-2.0, 2.0, size=n_obj)
    height = rng.uniform(0.0, 4.0, size=n_obj)
    true_xyz = (xyz_path[at] + side[:, None] * left + along[:, None] * fwd
                + (height - 1.65)[:, None] * E_Z)
    weights = rng.dirichlet(np.ones(len(app.centroids_cd)) * 2.0)
    classes = rng.choice(len(app.centroids_cd), size=n_obj, p=weights)
    truth_emb = app.instances(classes, rng)

    def observe(i: int, frames: np.ndarray, T_place: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean measured position of object i from `frames`, placed with poses T_place."""
        T = T_true[frames]
        rel = np.einsum("nji,nj->ni", T[:, :3, :3], true_xyz[i] - T[:, :3, 3])
        meas = noise.measure(rel, rng)
        P = T_place[frames]
        placed = np.einsum("nij,nj->ni", P[:, :3, :3], meas) + P[:, :3, 3]
        return placed.mean(axis=0), np.linalg.norm(rel, axis=1) / 35.0

    def visible(i: int, frames: np.ndarray) -> np.ndarray:
        T = T_true[frames]
        rel = np.einsum("nji,nj->ni", T[:, :3, :3], true_xyz[i] - T[:, :3, 3])
        r = np.linalg.norm(rel, axis=1)
        ok = (r >= 3.0) & (r <= 35.0) & (rel[:, 0] > 0) & (
            np.abs(rel[:, 1]) <= rel[:, 0] * np.tan(np.radians(45)))
        return frames[ok]

    # the map: 3-10 views per object from the frames approaching it, ORB-placed
    map_xyz, map_rf, map_obs = np.zeros((n_obj, 3)), [], np.zeros(n_obj, dtype=np.int64)
    for i in range(n_obj):
        frames = visible(i, np.arange(max(0, at[i] - 45), min(split, at[i] + 2)))
        if len(frames) == 0:
            frames = np.array([max(0, at[i] - 5)])
        k = min(len(frames), int(rng.integers(3, 11)))
        pick = np.sort(rng.choice(frames, size=k, replace=False))
        map_xyz[i], rf = observe(i, pick, T_est)
        map_rf.append(np.clip(rf, 0.0, 1.0))
        map_obs[i] = k
    ids = [f"m{k}" for k in range(n_obj)]
    arrs = _map_arrays(ids, map_xyz, truth_emb, map_obs, map_rf, app, rng)
    arrs, same = _with_duplicates(arrs, ids, map_xyz, truth_emb, spec.duplicates, app, rng)
    # loop-closure places: frames after split within 10 m of a frame of the first pass
    tree = cKDTree(xyz_path[:split])
    d_near, _ = tree.query(xyz_path[split:])
    places = split + np.flatnonzero(d_near <= 10.0)
    places = places[places < len(xyz_path) - 40]
    chosen = np.sort(rng.choice(places, size=min(spec.n_cases, len(places)), replace=False))
    obj_tree = cKDTree(true_xyz)
    cases = []
    for seq, k0 in enumerate(chosen):
        window = np.arange(k0, k0 + 40)
        around = obj_tree.query_ball_point(xyz_path[k0 + 20], 60.0)
        seen = {i: visible(i, window) for i in around}
        seen = {i: f for i, f in seen.items() if len(f)}
        body0 = np.linalg.inv(T_true[k0])
        dist0 = {i: np.linalg.norm(true_xyz[i] - xyz_path[k0]) for i in seen}
        pick = sorted(seen, key=lambda i: dist0[i])[: spec.sub_size]
        # positions in the body frame at k0 through the (short, near drift-free) relative poses
        T_rel = np.einsum("ij,njk->nik", body0, T_true)
        rows_xyz, rows_rf, rows_obs = [], [], []
        for i in pick:
            k = min(len(seen[i]), int(rng.integers(1, 4)))
            fr = np.sort(rng.choice(seen[i], size=k, replace=False))
            p, rf = observe(i, fr, T_rel)
            rows_xyz.append(p)
            rows_rf.append(np.clip(rf, 0.0, 1.0))
            rows_obs.append(k)
        sub_truth_emb = truth_emb[pick]
        # false detections: washed-out views of a random class, somewhere in view
        n_false = spec.n_false
        fake_xyz = np.column_stack([rng.uniform(5, 30, n_false), rng.uniform(-10, 10, n_false),
                                    rng.uniform(-1.6, 1.5, n_false)])
        fake_emb = app.instances(rng.integers(len(app.centroids_cd), size=n_false), rng)
        sub_ids_true = [ids[i] for i in pick] + [None] * n_false
        all_xyz = np.vstack([np.array(rows_xyz).reshape(-1, 3), fake_xyz])
        all_emb = np.vstack([sub_truth_emb.reshape(-1, app.dim), fake_emb])
        all_rf = rows_rf + [np.full(1, 1.0)] * n_false
        all_obs = np.array(rows_obs + [1] * n_false)
        sub_arr, truth, equiv = _submap_arrays(
            seq, all_xyz, all_emb, all_obs, all_rf, sub_ids_true,
            {ids[i]: tuple(same[i]) for i in pick}, app, rng)
        R, t = _local_truth(true_xyz, map_xyz, xyz_path[k0], 40.0, T_true[k0])
        # the vehicle's IMU vertical (true gravity), not the drifted map's
        cases.append(RawCase(sub_arr, truth, equiv, R, t, up_sub_xyz=T_true[k0, :3, :3].T @ E_Z))
    return World("kitti00", [arrs], cases, paper_radius_m=100.0)


def _concat(a: ObjectArrays, b: ObjectArrays) -> ObjectArrays:
    return ObjectArrays(a.ids + b.ids, np.vstack([a.position_xyz_m, b.position_xyz_m]),
                        np.vstack([a.embeddings_nd, b.embeddings_nd]),
                        np.vstack([a.variances_nd, b.variances_nd]),
                        np.concatenate([a.n_obs, b.n_obs]))


def _submap_arrays(
    seq: int, xyz: np.ndarray, truth_emb: np.ndarray, n_obs: np.ndarray,
    range_frac: list[np.ndarray], truth_of: list[str | None],
    same: dict[str, tuple[str, ...]], app: Appearance, rng: np.random.Generator,
) -> tuple[ObjectArrays, dict[str, str | None], dict[str, tuple[str, ...]]]:
    """Fuse the submap's views, shuffle its order, name it s{seq}_{j}; truth and equivalents."""
    order = rng.permutation(len(xyz))
    sids = [f"s{seq}_{j}" for j in range(len(xyz))]
    means, var = [], []
    for k in order:
        s = view_quality(range_frac[k], rng)
        if truth_of[k] is None:
            s = np.maximum(s, 0.3)  # a flash, a reflection: a poor view
        mu, v = app.fused(truth_emb[k], s, rng)
        means.append(mu)
        var.append(v)
    arr = ObjectArrays(sids, xyz[order], np.array(means),
                       np.repeat(np.array(var)[:, None], app.dim, axis=1), n_obs[order])
    truth = {sids[j]: truth_of[k] for j, k in enumerate(order)}
    equivalent = {sids[j]: same[truth_of[k]] for j, k in enumerate(order)
                  if truth_of[k] is not None}
    return arr, truth, equivalent


def pool_world(spec: WorldSpec, seed: int, dino: np.ndarray | None) -> World:
    """A harbour basin (30 x 15 m per 30 objects, 5 m deep): objects on the floor and buoys
    mid-water; the map from a drifting survey (heading error, 1 % scale, sonar range noise),
    submaps of 2-5 objects around a vehicle at 2 m depth with a random heading and a few
    degrees of pitch and roll."""
    rng = np.random.default_rng([seed, 9, 2])
    n_obj = spec.n_map
    scale = np.sqrt(n_obj / 30.0)
    basin = np.array([30.0, 15.0]) * scale
    app = _appearance(spec, rng, dino, pool=True)
    noise = _noise(POOL_NOISE, spec)
    xy = rng.uniform([1.5, 1.5], basin - 1.5, size=(n_obj, 2))
    buoy = rng.random(n_obj) < 0.2
    z = np.where(buoy, rng.uniform(-3.0, -1.5, n_obj), rng.uniform(-5.0, -4.5, n_obj))
    true_xyz = np.column_stack([xy, z])
    weights = rng.dirichlet(np.ones(len(app.centroids_cd)) * 2.0)
    classes = rng.choice(len(app.centroids_cd), size=n_obj, p=weights)
    truth_emb = app.instances(classes, rng)
    # the survey's drift: heading error and scale error about where it started
    yaw = np.radians(rng.normal(0.0, 2.0))
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    drift_scale = 1.0 + rng.normal(0.0, 0.01)

    def survey(p: np.ndarray) -> np.ndarray:
        return (p @ Rz.T) * np.array([drift_scale, drift_scale, 1.0])

    map_xyz, map_rf, map_obs = np.zeros((n_obj, 3)), [], rng.integers(3, 11, size=n_obj)
    for i in range(n_obj):
        k = int(map_obs[i])
        r = rng.uniform(0.8, 4.5, size=k)
        direction = rng.normal(size=(k, 3)) * [1, 1, 0.3]
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        rel = r[:, None] * direction
        map_xyz[i] = survey(true_xyz[i] - rel + noise.measure(rel, rng)).mean(axis=0)
        map_rf.append(np.clip(r / 3.0, 0.0, 1.0))  # murky water: poor views beyond 3 m
    ids = [f"m{k}" for k in range(n_obj)]
    arrs = _map_arrays(ids, map_xyz, truth_emb, map_obs, map_rf, app, rng)
    arrs, same = _with_duplicates(arrs, ids, map_xyz, truth_emb, spec.duplicates, app, rng,
                                  offset_sigma_m=0.5)
    cases = []
    for seq in range(spec.n_cases):
        size = spec.sub_size or 2 + seq % 4
        centre = true_xyz[rng.integers(n_obj), :2] + rng.normal(0, 1.5, size=2)
        heading = rng.uniform(-np.pi, np.pi)
        tilt = np.radians(rng.normal(0.0, 3.0, size=2))
        T_W_B = np.eye(4)
        T_W_B[:3, :3] = _rot_zyx(heading, tilt[0], tilt[1])
        T_W_B[:3, 3] = [centre[0], centre[1], -2.0]
        pick = list(np.argsort(np.linalg.norm(true_xyz[:, :2] - centre, axis=1))[:size])
        n_false = spec.n_false if size >= 4 else 0
        rows_xyz, rows_rf, rows_obs = [], [], []
        for i in pick:
            k = int(rng.integers(1, 4))
            rel = (true_xyz[i] - T_W_B[:3, 3]) @ T_W_B[:3, :3]  # R^T (p - t)
            meas = noise.measure(np.repeat(rel[None], k, axis=0), rng)
            rows_xyz.append(meas.mean(axis=0))
            rows_rf.append(np.full(k, min(np.linalg.norm(rel) / 3.0, 1.0)))
            rows_obs.append(k)
        fake_xyz = np.column_stack([rng.uniform(-3, 3, n_false), rng.uniform(-3, 3, n_false),
                                    rng.uniform(-3, 0, n_false)])
        fake_emb = app.instances(rng.integers(len(app.centroids_cd), size=n_false), rng)
        sub_arr, truth, equiv = _submap_arrays(
            seq, np.vstack([np.array(rows_xyz), fake_xyz]),
            np.vstack([truth_emb[pick], fake_emb]), np.array(rows_obs + [1] * n_false),
            rows_rf + [np.ones(1)] * n_false, [ids[i] for i in pick] + [None] * n_false,
            {ids[i]: tuple(same[i]) for i in pick}, app, rng)
        R, t = _local_truth(true_xyz, map_xyz, T_W_B[:3, 3], 8.0, T_W_B)
        cases.append(RawCase(sub_arr, truth, equiv, R, t, up_sub_xyz=T_W_B[:3, :3].T @ E_Z))
    return World("pool", [arrs], cases, paper_radius_m=2.0, robot_map="auv1", robot_sub="auv2")


def _rot_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def generator_world(spec: WorldSpec, seed: int) -> World:
    """The project's own generators, unchanged (z up): `gen-kitti` is `make_scenario(KITTI)`
    (one map per case), `gen-pool` windows of `underwater_run` (run 3, one map)."""
    if spec.family == "gen-kitti":
        maps, cases = [], []
        for j in range(spec.n_cases):
            sc = make_scenario(Family.KITTI, seed * 1000 + j, n_map=spec.n_map)
            maps.append(sc.map.arrays())
            cases.append(RawCase(sc.submap.arrays(), dict(sc.truth), dict(sc.equivalent),
                                 sc.R_map_submap, sc.t_map_submap, map_index=j))
        return World("gen-kitti", maps, cases, 100.0)
    run = underwater_run(3, seed)
    scs = []
    for size in (2, 3, 4, 5):
        scs += run.windows(size, count=max(1, spec.n_cases // 4))
    cases = [RawCase(sc.submap.arrays(), dict(sc.truth), dict(sc.equivalent), sc.R_map_submap,
                     sc.t_map_submap) for sc in scs[: spec.n_cases]]
    return World("gen-pool", [run.map.arrays()], cases, 2.0, "auv1", "auv1")


def express(
    world: World, C_map: np.ndarray, C_sub: np.ndarray, declare_up: bool
) -> list[Scenario]:
    """The world's cases as `match` files in the given conventions, parsed by `parse_model`:
    positions p -> C p, `up` added when declared, truth by `rotate_truth`."""
    maps: list[ObjectMap] = []
    for m in world.maps:
        d = _file_dict(m, world.robot_map, "s0", rotate_points(C_map, m.position_xyz_m),
                       up_in(C_map) if declare_up else None)
        maps.append(parse_model(ObjectMap, json.dumps(d), "map"))
    out = []
    for seq, c in enumerate(world.cases):
        up_sub = c.R_map_submap.T @ E_Z if c.up_sub_xyz is None else c.up_sub_xyz
        d = _file_dict(c.sub, world.robot_sub, "s1", rotate_points(C_sub, c.sub.position_xyz_m),
                       up_in(C_sub, up_sub) if declare_up else None, seq=seq)
        sub = parse_model(Submap, json.dumps(d), "submap")
        R, t = rotate_truth(c.R_map_submap, c.t_map_submap, C_map, C_sub)
        out.append(Scenario(maps[c.map_index], sub, dict(c.truth), R, t, world.paper_radius_m,
                            dict(c.equivalent)))
    return out


__all__ = [
    "DRIVE_NOISE",
    "LOOKALIKE",
    "POOL_NOISE",
    "NoiseModel",
    "RawCase",
    "World",
    "WorldSpec",
    "express",
    "fit_rigid_kabsch",
    "generator_world",
    "kitti_world",
    "pool_world",
]
