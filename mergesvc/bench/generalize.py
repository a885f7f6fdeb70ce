"""Generalization benchmark (issue 9): a matrix of worlds that do not share the generator's
assumptions (axis conventions, embedding dimension, map size, look-alikes, duplicates, range
noise, declared vertical), with verified mode, paper mode and cosine + Hungarian side by side.

Worlds come from real data where it exists (`../shared/data`): the KITTI-00 ground truth drive
(camera axes, y down) with the ORB-SLAM2 estimate of the same drive as the map's drifting frame,
and class centroids from 12 real DINO ViT-S centroids; and from the project's own generators
(`mergesvc.sim.scenario`) re-expressed in other frames. Every world is built in a gravity-aligned
frame (z up, vehicles x forward, y left) and then written, as `match` files parsed with
`parse_model`, in the frame conventions of the cell: camera (x right, y down, z forward), ENU
(z up), NED (z down), a random rotation of the whole world, or the map in one convention and the
submap in another. A submap is in its vehicle's frame at the cut; a map in its session's frame.
"""

from __future__ import annotations

import json
import logging
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mergesvc.bench.suite import score_case
from mergesvc.core.config import MatchConfig
from mergesvc.core.model import (
    Match,
    MatchResult,
    ObjectArrays,
    ObjectMap,
    RejectReason,
    Submap,
    parse_model,
)
from mergesvc.core.pipeline import MatchOutcome, match
from mergesvc.core.verify import align
from mergesvc.sim import Family, Scenario, make_scenario, underwater_run

log = logging.getLogger(__name__)

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
KITTI_GT = "kitti00/KITTI_00_gt.txt"
KITTI_ORB = "kitti00/KITTI_00_ORB.txt"
DINO_CENTROIDS = "dino_underwater/object_encodings_2obj1loop.txt"

E_Z = np.array([0.0, 0.0, 1.0])

# ============================================================================================
# Frame conventions
# ============================================================================================
#
# A convention is a rotation C taking coordinates of a gravity-aligned frame (x forward, y left,
# z up: FLU for a vehicle body, ENU-like for a world) into the convention's axes: p_conv = C p.
# The same C serves a world frame and a vehicle's body frame (KITTI's world frame is its first
# camera frame, so it follows the camera convention too).

CONVENTIONS = ("enu", "ned", "camera", "random")

C_ENU = np.eye(3)
C_NED = np.diag([1.0, -1.0, -1.0])  # x forward / north, y right / east, z down
C_CAMERA = np.array(  # x right = -left, y down = -up, z forward
    [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3): a normalised Gaussian quaternion (w, x, y, z)."""
    w, x, y, z = rng.normal(size=4)
    return Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy: scalar last


def convention_rotation(name: str, rng: np.random.Generator | None = None) -> np.ndarray:
    """C (3, 3): gravity-aligned (x forward, y left, z up) coordinates -> convention `name`
    (`enu`, `ned`, `camera`, `random`; `random` draws from rng)."""
    if name == "enu":
        return C_ENU.copy()
    if name == "ned":
        return C_NED.copy()
    if name == "camera":
        return C_CAMERA.copy()
    if name == "random":
        if rng is None:
            raise ValueError("the random convention needs a numpy Generator")
        return random_rotation(rng)
    raise ValueError(f"unknown frame convention {name!r} (one of {', '.join(CONVENTIONS)})")


def up_in(C: np.ndarray, up_xyz: np.ndarray = E_Z) -> np.ndarray:
    """The vertical (3,) of a gravity-aligned frame, expressed in convention C."""
    return C @ up_xyz


def rotate_points(C: np.ndarray, position_xyz_m: np.ndarray) -> np.ndarray:
    """(n, 3) points p -> C p."""
    return np.asarray(position_xyz_m, dtype=np.float64) @ C.T


def rotate_truth(
    R_map_submap: np.ndarray, t_map_submap: np.ndarray, C_map: np.ndarray, C_sub: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """T_map_submap after the map frame is re-expressed by C_map and the submap's by C_sub:
    p_map' = C_map (R C_sub^T p_sub' + t), so R' = C_map R C_sub^T, t' = C_map t."""
    return C_map @ R_map_submap @ C_sub.T, C_map @ t_map_submap


def _file_dict(
    arr: ObjectArrays, robot_id: str, session_id: str, position_xyz_m: np.ndarray,
    up_xyz: np.ndarray | None, seq: int | None = None, digits: int = 6,
) -> dict[str, Any]:
    """A map / submap file (the `match` format) as a dict; isotropic variances as one number."""
    objects = []
    for k, oid in enumerate(arr.ids):
        v = arr.variances_nd[k]
        var: float | list[float] = (
            float(v[0]) if np.ptp(v) <= 1e-12 * v[0] else np.round(v, digits + 2).tolist()
        )
        objects.append({
            "id": oid,
            "position": [round(float(x), digits) for x in position_xyz_m[k]],
            "embedding": np.round(arr.embeddings_nd[k], digits).tolist(),
            "variance": var,
            "n_obs": int(arr.n_obs[k]),
        })
    out: dict[str, Any] = {"schema_version": 1, "robot_id": robot_id, "session_id": session_id,
                           "objects": objects}
    if seq is not None:
        out["seq"] = seq
    if up_xyz is not None:
        out["up"] = [round(float(x), 9) for x in up_xyz]
    return out


def supports_up() -> bool:
    """Whether the file models carry the optional `up` field yet."""
    return "up" in ObjectMap.model_fields


def rotate_world(
    sc: Scenario,
    C_map: np.ndarray | str,
    C_sub: np.ndarray | str | None = None,
    declare_up: bool = False,
    map_up_xyz: np.ndarray = E_Z,
    parsed_map: ObjectMap | None = None,
    rng: np.random.Generator | None = None,
) -> Scenario:
    """A gravity-aligned scenario (map z up) re-expressed: map positions by C_map, submap
    positions by C_sub (default: C_map, a rotation of the whole world), the truth transformed
    consistently (`rotate_truth`). C_map / C_sub: (3, 3) or a convention name (`enu`, `ned`,
    `camera`, `random`, drawn from rng; the same name twice: one rotation). declare_up adds
    the `up` field to both files (the submap's is its frame's true vertical,
    R_map_submap^T map_up). Files go through JSON and `parse_model`. parsed_map: an already
    rotated map to share (many submaps of one map).

    E.g. `rotate_world(make_scenario("kitti", 0), "camera", "enu", declare_up=True)`."""
    if isinstance(C_sub, str) and isinstance(C_map, str) and C_sub == C_map:
        C_sub = None  # one convention (one random rotation) for the whole world
    if isinstance(C_map, str):
        C_map = convention_rotation(C_map, rng)
    if C_sub is None:
        C_sub = C_map
    elif isinstance(C_sub, str):
        C_sub = convention_rotation(C_sub, rng)
    if declare_up and not supports_up():
        raise ValueError("this build's file models have no `up` field")
    sub_up = sc.R_map_submap.T @ map_up_xyz
    if parsed_map is None:
        m = sc.map.arrays()
        map_dict = _file_dict(m, sc.map.robot_id, sc.map.session_id,
                              rotate_points(C_map, m.position_xyz_m),
                              up_in(C_map, map_up_xyz) if declare_up else None)
        parsed_map = parse_model(ObjectMap, json.dumps(map_dict), "map")
    s = sc.submap.arrays()
    sub_dict = _file_dict(s, sc.submap.robot_id, sc.submap.session_id,
                          rotate_points(C_sub, s.position_xyz_m),
                          up_in(C_sub, sub_up) if declare_up else None, seq=sc.submap.seq)
    submap = parse_model(Submap, json.dumps(sub_dict), "submap")
    R, t = rotate_truth(sc.R_map_submap, sc.t_map_submap, C_map, C_sub)
    return Scenario(parsed_map, submap, dict(sc.truth), R, t, sc.paper_radius_m,
                    dict(sc.equivalent))


# ============================================================================================
# Real data
# ============================================================================================


def data_available(data_dir: Path | None = None, *names: str) -> bool:
    """Whether every named file exists under data_dir (default: ../shared/data)."""
    d = Path(data_dir or DEFAULT_DATA_DIR)
    return all((d / n).is_file() for n in names)


def load_kitti_poses_34(path: Path | str) -> np.ndarray:
    """KITTI poses (n, 4, 4): camera -> world, camera axes (x right, y down, z forward)."""
    P = np.loadtxt(path).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3, :] = P
    return T


def camera_to_gravity(T_cam: np.ndarray) -> np.ndarray:
    """KITTI poses (n, 4, 4) in camera axes -> world_T_body with world and body gravity-aligned
    (x forward, y left, z up): w = C^T k, c = C b, so T_W_B = C^T T C."""
    A = np.eye(4)
    A[:3, :3] = C_CAMERA
    return np.linalg.inv(A) @ T_cam @ A


def load_dino_centroids(path: Path | str) -> np.ndarray:
    """The real DINO centroids (12, 384), one python-list line each."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    return np.asarray(rows, dtype=np.float64)


# ============================================================================================
# Appearance: class centroids with DINO structure in any dimension, instances, fused views
# ============================================================================================


def class_centroids(
    n_classes: int, dim: int, rng: np.random.Generator, dino_kd: np.ndarray | None = None
) -> np.ndarray:
    """(n_classes, dim) unit class centroids. From real centroids (k, d0): their exact pairwise
    cosines carried into `dim` dimensions by a random orthonormal embedding of their span;
    classes beyond k are mixtures of two real ones plus a fresh direction. Without real data:
    a shared direction plus random prototypes (pairwise cosine ~0.3)."""
    if dino_kd is None:
        shared = rng.normal(size=dim)
        shared /= np.linalg.norm(shared)
        raw = 0.6 * shared + rng.normal(size=(n_classes, dim)) / np.sqrt(dim)
        return raw / np.linalg.norm(raw, axis=1, keepdims=True)
    U = dino_kd / np.linalg.norm(dino_kd, axis=1, keepdims=True)
    k = len(U)
    Q, _ = np.linalg.qr(U.T)  # (d0, k) orthonormal basis of their span
    A = U @ Q  # (k, k) coordinates: A A^T = U U^T, the real cosines
    E, _ = np.linalg.qr(rng.normal(size=(dim, k)))  # (dim, k) random orthonormal embedding
    base = A @ E.T  # (k, dim)
    if n_classes <= k:
        return base[rng.permutation(k)[:n_classes]]
    extra = []
    for _ in range(n_classes - k):
        i, j = rng.choice(k, size=2, replace=False)
        w = rng.uniform(0.2, 0.8)
        fresh = rng.normal(size=dim)
        fresh /= np.linalg.norm(fresh)
        v = w * base[i] + (1 - w) * base[j] + rng.uniform(0.5, 1.2) * fresh
        extra.append(v / np.linalg.norm(v))
    return np.vstack([base, np.array(extra)])


@dataclass(frozen=True)
class Appearance:
    """How objects look: class centroids, instance spread, view noise (per unit of s)."""

    centroids_cd: np.ndarray  # (c, dim) unit
    instance_scale: float = 0.6  # relative norm of an instance's offset from its class
    view_noise: float = 1.8  # noise norm of a view of quality s: view_noise * sqrt(s) * |x|

    @property
    def dim(self) -> int:
        return self.centroids_cd.shape[1]

    def instances(self, classes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(n, dim) true appearances, norms 4.1-7.7 like the real DINO centroids."""
        n, d = len(classes), self.dim
        x = self.centroids_cd[classes] + self.instance_scale * rng.normal(size=(n, d)) / np.sqrt(d)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        return x * rng.uniform(4.1, 7.7, size=(n, 1))

    def fused(
        self, truth_d: np.ndarray, s_views: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, float]:
        """Views of one object with qualities s_views (n,), fused by inverse-variance weights.
        Each view's noise has per-dimension variance view_noise^2 s |x|^2 / dim; the tracked
        variance is 1 / sum(1 / s) (s / n for n views of equal s). Returns (mean (dim,), var)."""
        d = self.dim
        norm = float(np.linalg.norm(truth_d))
        gain = rng.uniform(0.85, 1.15, size=(len(s_views), 1))
        sd = self.view_noise * np.sqrt(s_views)[:, None] * norm / np.sqrt(d)
        views = gain * truth_d + rng.normal(size=(len(s_views), d)) * sd
        w = 1.0 / s_views
        return (w[:, None] * views).sum(axis=0) / w.sum(), float(1.0 / w.sum())


def view_quality(range_frac: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Image uncertainty s (n,) in [0.04, 0.6]: worse far away, occasionally bad anyway."""
    r = np.asarray(range_frac, dtype=np.float64)
    return np.clip(0.04 + 0.3 * r + 0.25 * rng.beta(1.5, 6.0, size=r.shape), 0.04, 0.6)


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


# ============================================================================================
# Methods
# ============================================================================================


def cosine_hungarian(map_: ObjectArrays, sub: ObjectArrays) -> np.ndarray:
    """The plain baseline: cosine similarity of the embeddings (n_sub, n_map), Hungarian
    assignment maximising it; every submap object matched (while map objects last).
    Returns (n_sub,) map index per submap object, -1 where none is left."""
    S = sub.unit_embeddings_nd @ map_.unit_embeddings_nd.T
    rows, cols = linear_sum_assignment(S, maximize=True)
    out = np.full(sub.n, -1, dtype=np.int64)
    out[rows] = cols
    return out


def cosine_hungarian_outcome(
    map_: ObjectMap | ObjectArrays, sub: ObjectMap | ObjectArrays,
    clock: Callable[[], float] = time.perf_counter,
) -> MatchOutcome:
    """`cosine_hungarian` wrapped as a pipeline outcome (accepted, nothing verified)."""
    t0 = clock()
    m = map_ if isinstance(map_, ObjectArrays) else map_.arrays()
    s = sub if isinstance(sub, ObjectArrays) else sub.arrays()
    assignment = cosine_hungarian(m, s)
    S = s.unit_embeddings_nd @ m.unit_embeddings_nd.T
    matches = [Match(submap_object=s.ids[i], map_object=m.ids[int(a)],
                     score=round(float(S[i, a]), 6)) for i, a in enumerate(assignment) if a >= 0]
    result = MatchResult(accepted=bool(matches), reason=RejectReason.NOT_VERIFIED,
                         matches=matches, transform=None, covariance=None,
                         timings_ms={"total": round((clock() - t0) * 1e3, 3)})
    return MatchOutcome(result=result, assignment=assignment, proposed=assignment)


METHODS = ("verified", "paper", "cos-hungarian")


# ============================================================================================
# The matrix
# ============================================================================================


@dataclass(frozen=True)
class Cell:
    """One combination of the matrix. frame: `conv` or `map_conv>sub_conv`."""

    name: str
    family: str  # kitti00 | pool | gen-kitti | gen-pool
    frame: str = "enu"
    vertical: bool = False  # declare `up` in both files
    dim: int = 384
    n_map: int = 600
    lookalike: str = "base"
    duplicates: float = 0.0
    noise: str = "base"
    n_cases: int = 8
    sub_size: int = 20
    n_false: int = 2
    paper_cases: int = 2
    varies: str = "base"  # which factor this cell varies around its family's base

    def conventions(self) -> tuple[str, str]:
        a, _, b = self.frame.partition(">")
        return a, b or a

    def spec(self) -> WorldSpec:
        return WorldSpec(self.family, self.n_map, self.dim, self.lookalike, self.duplicates,
                         self.noise, self.n_cases, self.sub_size, self.n_false)

    def needs(self) -> tuple[str, ...]:
        return {"kitti00": (KITTI_GT, KITTI_ORB, DINO_CENTROIDS),
                "pool": (DINO_CENTROIDS,)}.get(self.family, ())


def full_plan() -> list[Cell]:
    """A base cell per world family, one-factor variations around it, a few combined hard
    cells. Bases use each world's native convention without a declared vertical (what outside
    data looks like); `+up` cells declare it."""
    kb = Cell("kitti00", "kitti00", frame="camera", n_map=600, n_cases=8, sub_size=20,
              n_false=2, paper_cases=2)
    pb = Cell("pool", "pool", frame="ned", n_map=30, n_cases=16, sub_size=0, n_false=1,
              paper_cases=16)
    gk = Cell("gen-kitti", "gen-kitti", frame="enu", n_map=605, n_cases=6, paper_cases=1)
    gp = Cell("gen-pool", "gen-pool", frame="enu", n_map=0, n_cases=12, sub_size=0,
              paper_cases=12)
    cells = [kb]
    for fr in ("enu", "ned", "random", "camera>enu"):
        cells.append(replace(kb, name=f"kitti00/{fr}", frame=fr, varies="frame", paper_cases=1))
    for fr in ("camera", "random", "camera>enu"):
        cells.append(replace(kb, name=f"kitti00/{fr}+up", frame=fr, vertical=True,
                             varies="frame+up", paper_cases=1))
    for d in (128, 768):
        cells.append(replace(kb, name=f"kitti00/d{d}", dim=d, varies="dim", paper_cases=1))
    for n in (2000, 5000):
        cells.append(replace(kb, name=f"kitti00/map{n}", n_map=n, varies="map size",
                             n_cases=6, paper_cases=0))
    cells += [
        replace(kb, name="kitti00/lookalike-high", lookalike="high", varies="look-alikes",
                paper_cases=1),
        replace(kb, name="kitti00/dup15%", duplicates=0.15, varies="duplicates", paper_cases=1),
        replace(kb, name="kitti00/noise-high", noise="high", varies="range noise",
                paper_cases=1),
        replace(kb, name="kitti00/sub8", sub_size=8, n_false=1, varies="submap size",
                paper_cases=1),
    ]
    cells.append(pb)
    for fr in ("enu", "camera", "random", "ned>enu", "ned>camera"):
        cells.append(replace(pb, name=f"pool/{fr}", frame=fr, varies="frame"))
    for fr in ("ned", "random", "ned>camera"):
        cells.append(replace(pb, name=f"pool/{fr}+up", frame=fr, vertical=True,
                             varies="frame+up"))
    for d in (128, 768):
        cells.append(replace(pb, name=f"pool/d{d}", dim=d, varies="dim"))
    cells += [
        replace(pb, name="pool/map300", n_map=300, varies="map size", paper_cases=8),
        replace(pb, name="pool/lookalike-high", lookalike="high", varies="look-alikes"),
        replace(pb, name="pool/lookalike-low", lookalike="low", varies="look-alikes"),
        replace(pb, name="pool/dup15%", duplicates=0.15, varies="duplicates"),
        replace(pb, name="pool/noise-high", noise="high", varies="range noise"),
    ]
    cells.append(gk)
    for fr in ("camera", "ned", "random", "enu>camera"):
        cells.append(replace(gk, name=f"gen-kitti/{fr}", frame=fr, varies="frame"))
    cells.append(replace(gk, name="gen-kitti/camera+up", frame="camera", vertical=True,
                         varies="frame+up"))
    cells.append(gp)
    for fr in ("camera", "ned", "random", "enu>ned"):
        cells.append(replace(gp, name=f"gen-pool/{fr}", frame=fr, varies="frame"))
    cells.append(replace(gp, name="gen-pool/enu>ned+up", frame="enu>ned", vertical=True,
                         varies="frame+up"))
    # combined hard cells
    cells += [
        replace(kb, name="hard/kitti00-random-d768-lookalike-dup", frame="random", dim=768,
                lookalike="high", duplicates=0.15, varies="combined", paper_cases=1),
        replace(kb, name="hard/kitti00-map5000-camera>ned-d128-noise", frame="camera>ned",
                n_map=5000, dim=128, noise="high", varies="combined", n_cases=6,
                paper_cases=0),
        replace(kb, name="hard/kitti00-map5000-camera>ned-d128-noise+up", frame="camera>ned",
                vertical=True, n_map=5000, dim=128, noise="high", varies="combined",
                n_cases=6, paper_cases=0),
        replace(pb, name="hard/pool-ned>camera-noise-dup-lookalike", frame="ned>camera",
                noise="high", duplicates=0.15, lookalike="high", varies="combined"),
        replace(pb, name="hard/pool-ned>camera-noise-dup-lookalike+up", frame="ned>camera",
                vertical=True, noise="high", duplicates=0.15, lookalike="high",
                varies="combined"),
    ]
    return cells


def quick_plan() -> list[Cell]:
    """A few small cells for CI (well under a minute): the pool in its native and two foreign
    frames, with and without `up`, a small KITTI-00 map, the project's pool generator rotated."""
    pb = Cell("pool", "pool", frame="ned", n_map=30, n_cases=6, sub_size=0, n_false=1,
              paper_cases=3)
    kb = Cell("kitti00/map200", "kitti00", frame="camera", n_map=200, n_cases=3, sub_size=12,
              n_false=2, paper_cases=1, varies="map size")
    return [
        pb,
        replace(pb, name="pool/ned>camera", frame="ned>camera", varies="frame"),
        replace(pb, name="pool/ned>camera+up", frame="ned>camera", vertical=True,
                varies="frame+up"),
        replace(pb, name="pool/random/d128", frame="random", dim=128, varies="frame+dim"),
        kb,
        replace(kb, name="kitti00/map200/enu+up", frame="enu", vertical=True,
                varies="frame+up"),
        Cell("gen-pool/camera", "gen-pool", frame="camera", n_map=0, n_cases=4, sub_size=0,
             paper_cases=2, varies="frame"),
    ]


@dataclass
class _Data:
    data_dir: Path
    gt: np.ndarray | None = None
    est: np.ndarray | None = None
    dino: np.ndarray | None = None

    def load(self, names: Iterable[str]) -> None:
        for n in names:
            if n == KITTI_GT and self.gt is None:
                self.gt = load_kitti_poses_34(self.data_dir / n)
            elif n == KITTI_ORB and self.est is None:
                self.est = load_kitti_poses_34(self.data_dir / n)
            elif n == DINO_CENTROIDS and self.dino is None:
                self.dino = load_dino_centroids(self.data_dir / n)


def build_world(cell: Cell, seed: int, data: _Data) -> World:
    """The cell's world (gravity-aligned), for one seed."""
    spec = cell.spec()
    data.load(cell.needs())
    if cell.family == "kitti00":
        assert data.gt is not None and data.est is not None
        return kitti_world(spec, seed, data.gt, data.est, data.dino)
    if cell.family == "pool":
        return pool_world(spec, seed, data.dino)
    return generator_world(spec, seed)


def cell_scenarios(cell: Cell, seed: int, data_dir: Path | None = None) -> list[Scenario]:
    """The cell's cases as parsed `match` files in its conventions, with their truth."""
    world = build_world(cell, seed, _Data(Path(data_dir or DEFAULT_DATA_DIR)))
    rng = np.random.default_rng([seed, 9, 3])
    a, b = cell.conventions()
    C_map = convention_rotation(a, rng)
    C_sub = C_map if b == a else convention_rotation(b, rng)
    return express(world, C_map, C_sub, cell.vertical)


# ------------------------------------------------------------------ scoring


def confusers(sc: Scenario) -> float:
    """Look-alike density seen by a case: per matchable submap object, how many map objects
    (not the same physical object) are closer by cosine than its true match; the mean."""
    m, s = sc.map.arrays(), sc.submap.arrays()
    index = {oid: k for k, oid in enumerate(m.ids)}
    counts = []
    for j, sid in enumerate(s.ids):
        true = sc.truth.get(sid)
        if true is None:
            continue
        same = {index[x] for x in sc.equivalent.get(sid, (true,))}
        cos = m.unit_embeddings_nd @ s.unit_embeddings_nd[j]
        best_true = max(cos[k] for k in same)
        closer = cos > best_true
        closer[list(same)] = False
        counts.append(int(closer.sum()))
    return float(np.mean(counts)) if counts else float("nan")


def score(sc: Scenario, outcome: MatchOutcome) -> dict[str, Any]:
    """score_case (bench.py) plus node accuracy over every submap object (a false detection is
    right when left unmatched), the reason and the exact stage's budget state."""
    base = score_case(sc, outcome)
    n = base["matchable"] + base["outliers"]
    right_matchable = base["accuracy"] * base["matchable"]
    exact = outcome.exact
    return {
        **base,
        "node_accuracy": (right_matchable + base["outliers_unmatched"]) / max(n, 1.0),
        "reason": outcome.result.reason.value,
        "latency_ms": float(outcome.result.timings_ms.get("total", float("nan"))),
        "exact_ms": float(outcome.result.timings_ms.get("exact", float("nan"))),
        "exact_budget_hit": bool(exact is not None and not exact.optimal),
        "search_incomplete": outcome.result.reason is RejectReason.SEARCH_INCOMPLETE,
    }


def _run_method(method: str, sc: Scenario, configs: dict[str, MatchConfig]) -> MatchOutcome:
    if method == "cos-hungarian":
        return cosine_hungarian_outcome(sc.map, sc.submap)
    return match(sc.map, sc.submap, configs[method])


def _percentile(values: list[float], q: float) -> float:
    """Percentile of the finite values (the exact stage runs only in verified mode)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if len(v) else float("nan")


def summarize(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One method on one cell and seed: rates over its cases."""
    if not rows:
        return {"cases": 0}
    acc_returned = sum(r["acc_returned"] for r in rows)
    matchable = sum(r["matchable"] for r in rows)
    lat = np.array([r["latency_ms"] for r in rows])
    rot = [r["rot_err_deg"] for r in rows if np.isfinite(r["rot_err_deg"])]
    reasons: dict[str, int] = {}
    for r in rows:
        reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "cases": len(rows),
        "node_accuracy": float(np.mean([r["node_accuracy"] for r in rows])),
        "paper_accuracy": float(np.mean([r["accuracy"] for r in rows])),
        "precision": sum(r["acc_right"] for r in rows) / acc_returned if acc_returned else
        float("nan"),
        "recall": sum(r["acc_right"] for r in rows) / matchable if matchable else float("nan"),
        "accepted": int(sum(r["accepted"] for r in rows)),
        "accepted_fraction": float(np.mean([r["accepted"] for r in rows])),
        "wrong_accepted": int(sum(r["acc_returned"] - r["acc_right"] for r in rows)),
        "latency_p50_ms": float(np.percentile(lat, 50)),
        "latency_p99_ms": float(np.percentile(lat, 99)),
        "exact_p50_ms": _percentile([r.get("exact_ms", np.nan) for r in rows], 50),
        "exact_p99_ms": _percentile([r.get("exact_ms", np.nan) for r in rows], 99),
        "exact_budget_hits": int(sum(r["exact_budget_hit"] for r in rows)),
        "search_incomplete": int(sum(r["search_incomplete"] for r in rows)),
        "rot_err_deg_median": float(np.median(rot)) if rot else float("nan"),
        "reasons": reasons,
    }


SPREAD_KEYS = ("node_accuracy", "paper_accuracy", "precision", "recall", "accepted_fraction",
               "latency_p50_ms", "latency_p99_ms", "exact_p50_ms", "exact_p99_ms",
               "exact_budget_hits", "rot_err_deg_median")


def _spread(values: list[float]) -> dict[str, float]:
    a = np.asarray([v for v in values if np.isfinite(v)], dtype=np.float64)
    if len(a) == 0:
        return {"median": float("nan"), "min": float("nan"), "max": float("nan")}
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max())}


def over_seeds(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Median and [min, max] over seeds of each rate; counts summed."""
    per_seed = [p for p in per_seed if p.get("cases")]
    if not per_seed:
        return {"cases": 0}
    reasons: dict[str, int] = {}
    for p in per_seed:
        for k, v in p["reasons"].items():
            reasons[k] = reasons.get(k, 0) + v
    out: dict[str, Any] = {k: _spread([p[k] for p in per_seed]) for k in SPREAD_KEYS}
    out.update(cases=sum(p["cases"] for p in per_seed),
               accepted=sum(p["accepted"] for p in per_seed),
               wrong_accepted=sum(p["wrong_accepted"] for p in per_seed),
               search_incomplete=sum(p["search_incomplete"] for p in per_seed),
               exact_budget_hits_total=sum(p["exact_budget_hits"] for p in per_seed),
               seeds=len(per_seed), reasons=reasons)
    return out


# ------------------------------------------------------------------ the run


@dataclass
class GeneralizePlan:
    """What `mergesvc bench generalize` runs."""

    cells: list[Cell]
    seed: int = 0
    seeds: int = 1
    methods: tuple[str, ...] = METHODS
    paper_max_map: int = 700  # paper mode's dense K: only maps up to this size
    data_dir: Path = field(default_factory=lambda: DEFAULT_DATA_DIR)

    @classmethod
    def quick(cls, seed: int = 0, seeds: int = 1, data_dir: Path | None = None
              ) -> GeneralizePlan:
        return cls(quick_plan(), seed, seeds, data_dir=Path(data_dir or DEFAULT_DATA_DIR))

    @classmethod
    def full(cls, seed: int = 0, seeds: int = 1, data_dir: Path | None = None
             ) -> GeneralizePlan:
        return cls(full_plan(), seed, seeds, data_dir=Path(data_dir or DEFAULT_DATA_DIR))

    def steps(self) -> int:
        """Number of (cell, seed, case) units, for a progress bar."""
        return sum(c.n_cases for c in self.cells) * self.seeds


def run_generalize(
    plan: GeneralizePlan,
    progress: Callable[[str, int], Any] | None = None,
) -> dict[str, Any]:
    """Run the matrix. progress(message, cases done) after each case. Returns a JSON-ready
    report: per cell its settings, skip note (missing data, no `up` field), and per method the
    rates over seeds (median, min, max) and per seed; plus every case's record."""
    t_start = time.perf_counter()
    configs = {"verified": MatchConfig(), "paper": MatchConfig(mode="paper")}
    data = _Data(Path(plan.data_dir))
    has_up = supports_up()
    report: dict[str, Any] = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()} {platform.python_version()}",
        "data_dir": str(plan.data_dir),
        "seed": plan.seed,
        "seeds": plan.seeds,
        "methods": list(plan.methods),
        "settings": {k: v.model_dump(mode="json") for k, v in configs.items()},
        "paper_max_map": plan.paper_max_map,
        "cells": {},
        "cases": [],
    }
    done = 0
    for cell in plan.cells:
        entry: dict[str, Any] = {"cell": asdict(cell), "skipped": None, "methods": {}}
        report["cells"][cell.name] = entry
        missing = [n for n in cell.needs() if not (Path(plan.data_dir) / n).is_file()]
        if missing:
            entry["skipped"] = f"data absent: {', '.join(missing)}"
        elif cell.vertical and not has_up:
            entry["skipped"] = "this build's files have no `up` field"
        if entry["skipped"]:
            log.info("%s skipped: %s", cell.name, entry["skipped"])
            done += cell.n_cases * plan.seeds
            if progress:
                progress(f"{cell.name}: skipped", done)
            continue
        per_seed: dict[str, list[dict[str, Any]]] = {m: [] for m in plan.methods}
        notes: list[str] = []
        confusion: list[float] = []
        n_map = 0
        for s in range(plan.seeds):
            seed = plan.seed + s
            world = build_world(cell, seed, data)
            rng = np.random.default_rng([seed, 9, 3])
            a, b = cell.conventions()
            C_map = convention_rotation(a, rng)
            C_sub = C_map if b == a else convention_rotation(b, rng)
            scenarios = express(world, C_map, C_sub, cell.vertical)
            rows: dict[str, list[dict[str, Any]]] = {m: [] for m in plan.methods}
            for k, sc in enumerate(scenarios):
                n_map = len(sc.map.objects)
                confusion.append(confusers(sc))
                for method in plan.methods:
                    if method == "paper" and (k >= cell.paper_cases
                                              or n_map > plan.paper_max_map):
                        continue
                    outcome = _run_method(method, sc, configs)
                    rec = score(sc, outcome)
                    rec.update(cell=cell.name, seed=seed, case=k, method=method,
                               n_sub=len(sc.submap.objects), n_map=n_map)
                    rows[method].append(rec)
                    report["cases"].append(rec)
                done += 1
                if progress:
                    progress(f"{cell.name} seed {seed} case {k}", done)
            for m in plan.methods:
                per_seed[m].append(summarize(rows[m]))
        if "paper" in plan.methods and (cell.paper_cases == 0 or n_map > plan.paper_max_map):
            notes.append(f"paper skipped (map {n_map} objects > {plan.paper_max_map} or capped)")
        entry["notes"] = notes
        entry["n_map"] = n_map
        entry["confusers_mean"] = float(np.nanmean(confusion)) if confusion else float("nan")
        for m in plan.methods:
            entry["methods"][m] = {"over_seeds": over_seeds(per_seed[m]),
                                   "per_seed": per_seed[m]}
    report["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    report["markdown"] = markdown(report)
    return report


def _fmt(s: dict[str, float] | None, digits: int = 2, seeds: int = 1) -> str:
    if not s or not np.isfinite(s.get("median", float("nan"))):
        return "-"
    med = f"{s['median']:.{digits}f}"
    if seeds > 1 and s["max"] > s["min"]:
        return f"{med} [{s['min']:.{digits}f}-{s['max']:.{digits}f}]"
    return med


def markdown(report: dict[str, Any]) -> str:
    """The report as a markdown table: one row per cell and method."""
    seeds = int(report.get("seeds", 1))
    lines = [
        "| cell | varies | map | method | node acc | precision | recall | accepted "
        "| p50 ms | p99 ms | exact p50/p99 ms | budget hits | look-alikes | reasons |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    skipped = []
    for name, e in report["cells"].items():
        if e["skipped"]:
            skipped.append(f"- {name}: skipped ({e['skipped']})")
            continue
        for m, r in e["methods"].items():
            o = r["over_seeds"]
            if not o.get("cases"):
                continue
            reasons = ", ".join(f"{k} {v}" for k, v in sorted(o["reasons"].items(),
                                                              key=lambda kv: -kv[1]))
            hits = o.get("exact_budget_hits_total", "-") if m == "verified" else "-"
            exact = (f"{_fmt(o.get('exact_p50_ms'), 1, 1)} / {_fmt(o.get('exact_p99_ms'), 1, 1)}"
                     if m == "verified" else "-")
            lines.append(
                f"| {name} | {e['cell']['varies']} | {e['n_map']} | {m} "
                f"| {_fmt(o['node_accuracy'], 2, seeds)} | {_fmt(o['precision'], 2, seeds)} "
                f"| {_fmt(o['recall'], 2, seeds)} | {o['accepted']}/{o['cases']} "
                f"| {_fmt(o['latency_p50_ms'], 1, seeds)} | {_fmt(o['latency_p99_ms'], 1, seeds)} "
                f"| {exact} | {hits} | {e['confusers_mean']:.1f} | {reasons} |"
            )
        for note in e.get("notes", []):
            skipped.append(f"- {name}: {note}")
    text = "\n".join(lines)
    if skipped:
        text += "\n\n" + "\n".join(skipped)
    text += (
        "\n\nnode acc: right submap objects / all submap objects (a false detection or an "
        "object not in the map is right when left unmatched), on every returned answer; "
        "precision / recall: matches of accepted answers only; budget hits: cases whose exact "
        "stage stopped at its budget unproven (search_incomplete among the reasons when that "
        "rejected an answer); look-alikes: mean map "
        "objects closer by cosine than the true match, per matchable submap object."
    )
    return text


__all__ = [
    "CONVENTIONS",
    "C_CAMERA",
    "C_ENU",
    "C_NED",
    "Appearance",
    "Cell",
    "GeneralizePlan",
    "NoiseModel",
    "World",
    "WorldSpec",
    "camera_to_gravity",
    "cell_scenarios",
    "class_centroids",
    "convention_rotation",
    "cosine_hungarian",
    "cosine_hungarian_outcome",
    "data_available",
    "express",
    "fit_rigid_kabsch",
    "full_plan",
    "generator_world",
    "kitti_world",
    "load_dino_centroids",
    "load_kitti_poses_34",
    "markdown",
    "pool_world",
    "quick_plan",
    "random_rotation",
    "rotate_points",
    "rotate_truth",
    "rotate_world",
    "run_generalize",
    "score",
    "supports_up",
    "up_in",
]
