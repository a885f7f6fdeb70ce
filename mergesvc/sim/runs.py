"""Vehicle runs through a world: a path, odometry drift, each frame's detections through the
tracker (core.tracking), the map from the first part of a run and submaps cut from the revisit,
with ground truth followed through every detection. The paper tables' pool runs
(`underwater_run`) and KITTI-like drive (`drive_run`), and single observations for training an
uncertainty head (`image_s_dataset`).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mergesvc.core.model import ObjectMap, ObjectNode, Submap
from mergesvc.core.tracking import Detection, Frame, ObjectTracker, Track, TrackingConfig
from mergesvc.sim.scenario import (
    KITTI_CLASSES,
    UNDERWATER_CLASSES,
    EmbeddingModel,
    Family,
    Scenario,
)

_E_Z = np.array([0.0, 0.0, 1.0])  # up in the gravity-aligned worlds

log = logging.getLogger(__name__)


# ============================================================================================
# Runs: a vehicle moving through a world, detections, odometry drift, tracking (tracking.py)
# ============================================================================================
#
# make_scenario (scenario.py) draws a map and a submap directly (fast; unit tests, scale
# sweeps). The runs below are what the benchmark's paper tables use: a vehicle flies (or drives)
# a path, its odometry drifts, each frame's detections (with per-image uncertainty s, position
# noise, range outliers and false positives) go through the tracker of tracking.py (association
# gates + semantic Kalman) in the vehicle's own estimated frame. The first part of the run
# becomes the map, submaps are cut from the revisit, and ground truth follows every detection
# through.


# What a vehicle reports as each image's uncertainty s, from the observed embeddings (n, d) -> (n,):
# by default the simulator's true s; a learned head (uncertainty.py) or a constant instead.
ImageUncertainty = Callable[[np.ndarray], np.ndarray]


def world_embedding_model(family: Family, seed: int) -> EmbeddingModel:
    """The appearance model of one world (a pool, a city, seen through one backbone): shared by
    every run of that seed, so what is learned on one run's data holds for the others."""
    names = UNDERWATER_CLASSES if family is Family.UNDERWATER else KITTI_CLASSES
    code = 0 if family is Family.UNDERWATER else 1
    return EmbeddingModel.create(len(names), np.random.default_rng([seed, 99, code]))


def image_s_dataset(
    n: int, seed: int = 0, family: Family | str = Family.UNDERWATER
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Single observations as the runs make them, for training an uncertainty head.

    Returns embeddings (n, d), task loss (n,) = |y - x| / |x| (how far the view is from the
    object's true appearance), and the true image uncertainty s (n,). Draws s like the runs do
    (range, light); the objects are new instances of the world's classes (same appearance
    model as the runs of that seed: `world_embedding_model`).
    """
    family = Family(family)
    rng = np.random.default_rng([seed, 11])
    names = UNDERWATER_CLASSES if family is Family.UNDERWATER else KITTI_CLASSES
    model = world_embedding_model(family, seed)
    truth = model.instances(rng.integers(len(names), size=n), rng)
    frac = rng.uniform(0.0, 1.0, n)
    light = rng.uniform(0.0, 1.0, n) ** 3
    s = np.clip(0.05 + 0.25 * frac**2 + 0.25 * light + rng.normal(0, 0.02, n), 0.05, 0.5)
    y = model.observe(truth, s, rng)
    loss = np.linalg.norm(y - truth, axis=1) / np.linalg.norm(truth, axis=1)
    return y, loss, s


SURVEY_SAMPLES = 4000  # views in the survey a fleet's projection is fitted on (the demo's)


def survey_embeddings(
    seed: int, family: Family | str = Family.UNDERWATER, samples: int = SURVEY_SAMPLES
) -> np.ndarray:
    """(samples, d) single views of new instances of the world's classes, drawn apart from
    any mission of `seed` (image_s_dataset of seed + 1000): the survey data a fleet fits its
    shared projection on (the demo, `mergesvc projection make --survey`)."""
    return image_s_dataset(samples, seed + 1000, family)[0]


@dataclass(frozen=True)
class RunConfig:
    """How one run is simulated; `underwater_run` / `drive_run` fill in per-family defaults."""

    speed_mps: float
    frame_dt_s: float
    range_m: tuple[float, float]  # detections between these ranges
    fov_deg: float  # full horizontal field of view
    p_detect: float  # per frame, for an object in view
    pos_sigma_m: tuple[float, float]  # position noise: at the near and at the far range
    outlier_rate: float  # fraction of detections with a wrong range (sonar multipath)
    false_per_frame: float  # mean false detections per frame (lighting, reflections)
    odo_scale_sigma: float  # relative error of each odometry step's length
    yaw_rw_rad: float  # heading random walk per frame
    yaw_bias_rad: float  # heading bias per frame (gyro bias)
    tracking: TrackingConfig
    min_obs: int = 2  # tracks seen fewer times are not sent (a single flash is not an object)


@dataclass(frozen=True)
class Run:
    """A simulated run: truth, the vehicle's estimate, and its map and revisit tracks.

    poses_true / poses_est: (n, 4, 4) world_T_body per frame (est starts at the true start);
    split: first frame of the revisit; tracks_map / tracks_revisit: tracks in the est frame.
    """

    family: Family
    name: str
    seed: int
    stamps_s: np.ndarray
    poses_true: np.ndarray
    poses_est: np.ndarray
    split: int
    object_xyz_m: np.ndarray  # (n_obj, 3) true centres
    object_ids: list[str]
    object_classes: list[str]
    tracks_map: tuple[Track, ...]
    tracks_revisit: tuple[Track, ...]
    paper_radius_m: float
    robot_id: str = "auv1"

    @functools.cached_property
    def map(self) -> ObjectMap:
        """The map the vehicle built in the first part of the run (its estimated frame)."""
        nodes = [_track_node(t) for t in self.tracks_map]
        return ObjectMap(robot_id=self.robot_id, session_id="s0", objects=nodes)

    @functools.cached_property
    def _map_by_truth(self) -> dict[str, list[Track]]:
        out: dict[str, list[Track]] = {}
        for t in self.tracks_map:
            if t.truth_id is not None:
                out.setdefault(t.truth_id, []).append(t)
        return out

    def drift_m(self, k: int) -> float:
        """Position error of the estimate at frame k (metres)."""
        return float(np.linalg.norm(self.poses_est[k, :3, 3] - self.poses_true[k, :3, 3]))

    def submap(self, tracks: list[Track], seq: int) -> Scenario:
        """A submap of the given revisit tracks, in the body frame at the first sighting."""
        t0 = min(t.first_seen_s for t in tracks)
        k0 = int(np.searchsorted(self.stamps_s, t0))
        est_inv = np.linalg.inv(self.poses_est[k0])
        nodes, truth, equivalent = [], {}, {}
        for j, t in enumerate(sorted(tracks, key=lambda t: t.first_seen_s)):
            sid = f"s{seq}_{j}"
            p = est_inv[:3, :3] @ t.position_xyz_m + est_inv[:3, 3]
            nodes.append(_track_node(t, sid, p))
            same = sorted(
                self._map_by_truth.get(t.truth_id or "", []), key=lambda m: -m.n_obs
            )
            truth[sid] = same[0].track_id if same else None
            equivalent[sid] = tuple(m.track_id for m in same)
        T = self.poses_true[k0]  # submap frame = the true body frame at t0; map ~ world
        return Scenario(
            map=self.map,
            submap=Submap(
                robot_id=self.robot_id, session_id="s1", seq=seq, stamp=float(t0), objects=nodes
            ),
            truth=truth,
            R_map_submap=T[:3, :3].copy(),
            t_map_submap=T[:3, 3].copy(),
            paper_radius_m=self.paper_radius_m,
            equivalent=equivalent,
        )

    def windows(self, size: int, count: int | None = None) -> list[Scenario]:
        """Submaps of `size` consecutive revisit tracks (by first sighting), where the drift is
        largest first (the paper's choice: the second half, where drift is worst)."""
        tracks = sorted(self.tracks_revisit, key=lambda t: t.first_seen_s)
        groups = [tracks[i : i + size] for i in range(0, len(tracks) - size + 1, size)]
        k = [int(np.searchsorted(self.stamps_s, g[0].first_seen_s)) for g in groups]
        order = np.argsort([-self.drift_m(min(x, len(self.stamps_s) - 1)) for x in k],
                           kind="stable")
        chosen = [groups[i] for i in order[: count or len(groups)]]
        return [self.submap(g, seq) for seq, g in enumerate(chosen)]

    def places(self, n_places: int = 4, size: int = 20, min_gap_s: float = 60.0) -> list[Scenario]:
        """Submaps of `size` revisit tracks at `n_places` loop-closure places: where the revisit
        passes close to where the map part of the run went (the paper's Table II)."""
        map_xy = self.poses_true[: self.split, :2, 3]
        cands = []
        for k in range(self.split, len(self.stamps_s)):
            d = np.linalg.norm(map_xy - self.poses_true[k, :2, 3], axis=1)
            j = int(np.argmin(d))
            if d[j] < 15.0 and self.stamps_s[k] - self.stamps_s[j] > min_gap_s:
                cands.append(k)
        if not cands:
            return []
        picks = np.unique(np.linspace(0, len(cands) - 1, n_places + 2)[1:-1].round().astype(int))
        out = []
        for seq, c in enumerate(picks):
            t_place = self.stamps_s[cands[c]]
            near = sorted(self.tracks_revisit, key=lambda t: abs(t.first_seen_s - t_place))
            out.append(self.submap(near[:size], seq))
        return out


def _track_node(t: Track, oid: str | None = None, position: np.ndarray | None = None
                ) -> ObjectNode:
    p = t.position_xyz_m if position is None else position
    return ObjectNode(
        id=oid or t.track_id,
        position=(float(p[0]), float(p[1]), float(p[2])),
        embedding=t.mean_d.tolist(),
        variance=t.variance_d.tolist(),
        n_obs=t.n_obs,
    )


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    c, s_ = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, z]
    return T


def _sample_path(waypoints_xy: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every step_m along a polyline and the heading there. (n, 2), (n,)."""
    seg = np.diff(waypoints_xy, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    s_cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    s = np.arange(0.0, s_cum[-1], step_m)
    k = np.clip(np.searchsorted(s_cum, s, side="right") - 1, 0, len(seg) - 1)
    f = (s - s_cum[k]) / np.maximum(seg_len[k], 1e-9)
    xy = waypoints_xy[k] + f[:, None] * seg[k]
    yaw = np.arctan2(seg[k, 1], seg[k, 0])
    return xy, yaw


def _odometry(
    xy: np.ndarray, yaw: np.ndarray, cfg: RunConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Dead reckoning from noisy steps: (n, 2) est positions, (n,) est headings."""
    n = len(xy)
    step = np.diff(xy, axis=0)
    dyaw = np.angle(np.exp(1j * np.diff(yaw)))
    est_xy, est_yaw = np.zeros((n, 2)), np.zeros(n)
    est_xy[0], est_yaw[0] = xy[0], yaw[0]
    for k in range(1, n):
        # the step in the body frame at k-1, measured with scale noise; heading from a gyro
        # with a bias and a random walk
        c, s_ = np.cos(yaw[k - 1]), np.sin(yaw[k - 1])
        body = np.array([c * step[k - 1, 0] + s_ * step[k - 1, 1],
                         -s_ * step[k - 1, 0] + c * step[k - 1, 1]])
        body *= 1.0 + rng.normal(0.0, cfg.odo_scale_sigma)
        est_yaw[k] = est_yaw[k - 1] + dyaw[k - 1] + cfg.yaw_bias_rad + rng.normal(
            0.0, cfg.yaw_rw_rad)
        c, s_ = np.cos(est_yaw[k - 1]), np.sin(est_yaw[k - 1])
        est_xy[k] = est_xy[k - 1] + [c * body[0] - s_ * body[1], s_ * body[0] + c * body[1]]
    return est_xy, est_yaw


def _frames(
    family: Family,
    poses_true: np.ndarray,
    poses_est: np.ndarray,
    stamps: np.ndarray,
    objects_xyz: np.ndarray,
    truth_emb: np.ndarray,
    ids: list[str],
    n_classes: int,
    cfg: RunConfig,
    rng: np.random.Generator,
    model: EmbeddingModel,
    image_s: ImageUncertainty | None = None,
) -> Iterator[Frame]:
    """Per frame: which objects the sensor sees, their measured positions (noise growing with
    range, multipath outliers), each image's uncertainty s and embedding, false detections;
    placed with the estimated pose poses_est[k] (the vehicle's only knowledge of where it is)."""
    half_fov = np.radians(cfg.fov_deg) / 2.0
    r_lo, r_hi = cfg.range_m
    for k in range(len(stamps)):
        Tt, Te = poses_true[k], poses_est[k]
        rel = (objects_xyz - Tt[:3, 3]) @ Tt[:3, :3]  # body-frame positions, (n_obj, 3)
        rng_m = np.linalg.norm(rel, axis=1)
        bearing = np.arctan2(rel[:, 1], rel[:, 0])
        seen = (rng_m >= r_lo) & (rng_m <= r_hi) & (np.abs(bearing) <= half_fov)
        seen &= rng.random(len(rel)) < cfg.p_detect
        idx = np.flatnonzero(seen)
        frac = (rng_m[idx] - r_lo) / max(r_hi - r_lo, 1e-9)
        # image uncertainty: far, oblique and badly lit views are worse
        light = rng.uniform(0.0, 1.0, size=len(idx)) ** 3
        s_img = np.clip(0.05 + 0.25 * frac**2 + 0.25 * light + rng.normal(0, 0.02, len(idx)),
                        0.05, 0.5)
        sigma = cfg.pos_sigma_m[0] + (cfg.pos_sigma_m[1] - cfg.pos_sigma_m[0]) * frac
        meas = rel[idx] + rng.normal(size=(len(idx), 3)) * sigma[:, None]
        out = rng.random(len(idx)) < cfg.outlier_rate
        meas[out] *= rng.uniform(0.6, 1.4, size=(int(out.sum()), 1))
        d = truth_emb.shape[1]
        emb = model.observe(truth_emb[idx], s_img, rng) if len(idx) else np.zeros((0, d))
        truths: list[str | None] = [ids[i] for i in idx]
        n_false = rng.poisson(cfg.false_per_frame)
        if n_false:
            # a flash, a reflection: somewhere in view, looking like a washed-out random class
            r = rng.uniform(r_lo, r_hi, n_false)
            b = rng.uniform(-half_fov, half_fov, n_false)
            fz = rng.uniform(-1.0, 1.0, n_false) if family is Family.UNDERWATER else rng.uniform(
                0.0, 2.0, n_false) - Tt[2, 3]
            fake = np.column_stack([r * np.cos(b), r * np.sin(b), fz])
            s_fake = rng.uniform(0.3, 0.5, n_false)
            fake_emb = model.observe(
                model.instances(rng.integers(n_classes, size=n_false), rng), s_fake, rng)
            meas = np.vstack([meas, fake])
            emb = np.vstack([emb, fake_emb])
            s_img = np.concatenate([s_img, s_fake])
            sigma = np.concatenate([sigma, np.full(n_false, cfg.pos_sigma_m[1])])
            truths += [None] * n_false
        if image_s is not None and len(emb):
            # the vehicle does not know the true s: it reports what its estimator says
            s_img = np.asarray(image_s(emb), dtype=np.float64)
        dets = []
        for j in range(len(meas)):
            p_est = Te[:3, :3] @ meas[j] + Te[:3, 3]
            cov = Te[:3, :3] @ np.diag(np.full(3, sigma[j] ** 2)) @ Te[:3, :3].T
            dets.append(Detection(emb[j], float(s_img[j]), p_est, cov, float(stamps[k]),
                                  truths[j]))
        # the vehicle's AHRS: gravity in its body frame (the world here is z up)
        yield Frame(k, float(stamps[k]), Te, Tt, dets, up_body=Tt[:3, :3].T @ _E_Z)


def _simulate(
    family: Family,
    name: str,
    seed: int,
    xy: np.ndarray,
    yaw: np.ndarray,
    z_m: np.ndarray,
    split: int,
    objects_xyz: np.ndarray,
    classes: np.ndarray,
    class_names: list[str],
    cfg: RunConfig,
    rng: np.random.Generator,
    model: EmbeddingModel,
    robot_id: str,
    paper_radius_m: float,
    image_s: ImageUncertainty | None = None,
) -> Run:
    n = len(xy)
    stamps = np.arange(n) * cfg.frame_dt_s
    est_xy, est_yaw = _odometry(xy, yaw, cfg, rng)
    poses_true = np.stack([_pose(*xy[k], z_m[k], yaw[k]) for k in range(n)])
    poses_est = np.stack([_pose(*est_xy[k], z_m[k], est_yaw[k]) for k in range(n)])
    truth_emb = model.instances(classes, rng)
    ids = [f"{class_names[c]}_{k}" for k, c in enumerate(classes)]
    trackers = (ObjectTracker(cfg.tracking), ObjectTracker(cfg.tracking))
    for fr in _frames(family, poses_true, poses_est, stamps, objects_xyz, truth_emb, ids,
                      len(class_names), cfg, rng, model, image_s):
        trackers[0 if fr.k < split else 1].observe_frame(fr.detections)
    keep = [tuple(t for t in tr.tracks if t.n_obs >= cfg.min_obs) for tr in trackers]
    return Run(
        family, name, seed, stamps, poses_true, poses_est, split, objects_xyz, ids,
        [class_names[c] for c in classes], keep[0], keep[1], paper_radius_m, robot_id,
    )


def _pool_objects(
    n: int, pool_xy_m: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Classes (n,) and centres (n, 3) of pool objects: on the floor (3.5-4 m deep), buoys
    mid-water, 1.5-2 m from the walls; class frequencies skewed per pool."""
    classes = rng.choice(len(UNDERWATER_CLASSES), size=n,
                         p=rng.dirichlet(np.ones(len(UNDERWATER_CLASSES)) * 3.0))
    xy = rng.uniform([2.0, 1.5], pool_xy_m - [2.0, 1.5], size=(n, 2))
    z = np.where(classes == UNDERWATER_CLASSES.index("buoy"), rng.uniform(-2.5, -1.5, n),
                 rng.uniform(-4.0, -3.5, n))
    return classes, np.column_stack([xy, z])


def underwater_run(run: int = 1, seed: int = 0, image_s: ImageUncertainty | None = None) -> Run:
    """The paper's pool runs 1-3: 2 or 4 laps of a lawnmower or loop pattern over 8-30 objects.

    Run 1: 4 laps of a loop over ~12 objects; run 2: 2 laps of a lawnmower over ~20 objects;
    run 3: 4 laps of a loop over ~30 objects (denser, more look-alikes). DVL/IMU dead
    reckoning drifts; sonar ranging noise 0.1-0.5 m with occasional multipath outliers.
    """
    if run not in (1, 2, 3):
        raise ValueError(f"underwater run must be 1, 2 or 3, got {run}")
    rng = np.random.default_rng([seed, run])
    n_obj = {1: 12, 2: 20, 3: 30}[run] + int(rng.integers(-3, 4))
    pool = np.array([25.0, 12.0])
    classes, objects = _pool_objects(n_obj, pool, rng)
    if run == 2:  # lawnmower: lanes 3 m apart, back and forth, 2 laps
        lanes = np.arange(1.5, pool[1] - 1.0, 3.0)
        pts = []
        for i, y in enumerate(lanes):
            xs = (1.0, pool[0] - 1.0) if i % 2 == 0 else (pool[0] - 1.0, 1.0)
            pts += [(xs[0], y), (xs[1], y)]
        lap = np.array(pts)
        laps = 2
    else:  # a loop inset 1.5 m from the walls, 4 laps
        lap = np.array([[1.5, 1.5], [pool[0] - 1.5, 1.5], [pool[0] - 1.5, pool[1] - 1.5],
                        [1.5, pool[1] - 1.5], [1.5, 1.5]])
        laps = 4
    way = np.vstack([lap] * laps if run != 2 else [lap, lap[::-1]])
    cfg = RunConfig(
        speed_mps=0.4, frame_dt_s=1.0, range_m=(0.5, 4.5), fov_deg=100.0, p_detect=0.7,
        pos_sigma_m=(0.1, 0.5), outlier_rate=0.05, false_per_frame=0.08,
        odo_scale_sigma=0.02, yaw_rw_rad=np.radians(0.2), yaw_bias_rad=np.radians(0.01),
        tracking=TrackingConfig(cos_min=0.6, window_s=60.0),
    )
    path_xy, yaw = _sample_path(way, cfg.speed_mps * cfg.frame_dt_s)
    z_path = np.full(len(path_xy), -2.0)
    model = world_embedding_model(Family.UNDERWATER, seed)
    return _simulate(
        Family.UNDERWATER, f"underwater run {run}", seed, path_xy, yaw, z_path,
        len(path_xy) // 2, objects, classes, UNDERWATER_CLASSES, cfg, rng, model,
        "auv1", 2.0, image_s,
    )


def load_kitti_poses(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """KITTI odometry poses (12 numbers a line, camera: x right, y down, z forward) ->
    ground-plane path (n, 2) and heading (n,), in a frame with z up."""
    P = np.loadtxt(path).reshape(-1, 3, 4)
    xy = np.column_stack([P[:, 2, 3], -P[:, 0, 3]])
    fwd = P[:, :, 2]  # the camera's z axis in the world
    return xy, np.arctan2(-fwd[:, 0], fwd[:, 2])


def drive_run(
    seed: int = 0, trajectory: Path | str | None = None, image_s: ImageUncertainty | None = None
) -> Run:
    """A KITTI-like drive: ~2.2 km with a loop and a revisit, ~600 objects of 14 classes along
    the streets, stereo depth noise growing with range, visual-odometry drift.

    trajectory: a KITTI pose file (e.g. the real KITTI-00 ground truth) to drive instead of
    the generated street loop; objects are then placed along that path.
    """
    rng = np.random.default_rng([seed, 7])
    if trajectory is not None:
        xy_all, _ = load_kitti_poses(trajectory)
        # drop the poses of a car standing still: a zero-length segment has no heading
        moved = np.linalg.norm(np.diff(xy_all, axis=0), axis=1) > 1e-3
        way = xy_all[np.concatenate([[True], moved])]
    else:
        # a 600 x 300 m block loop, then back along its first 500 m: four loop-closure places
        way = np.array([[0, 0], [600, 0], [600, 300], [0, 300], [0, 0], [500, 0]], float)
        way = way + rng.normal(0, 0.5, way.shape)
    cfg = RunConfig(
        speed_mps=8.0, frame_dt_s=1.0, range_m=(3.0, 35.0), fov_deg=90.0, p_detect=0.8,
        pos_sigma_m=(0.15, 2.5), outlier_rate=0.02, false_per_frame=0.3,
        odo_scale_sigma=0.01, yaw_rw_rad=np.radians(0.05), yaw_bias_rad=np.radians(0.005),
        tracking=TrackingConfig(cos_min=0.6, window_s=10.0),
    )
    path_xy, yaw = _sample_path(way, cfg.speed_mps * cfg.frame_dt_s)
    # objects along the path's first pass, 3-9 m off the centre line, on both sides
    length = np.sum(np.linalg.norm(np.diff(way, axis=0), axis=1))
    split = _first_revisit(path_xy, min_gap=60)
    first = path_xy[:split]
    n_obj = int(600 * min(1.0, split * cfg.speed_mps / 1700.0) * rng.uniform(0.95, 1.05))
    at = rng.integers(0, len(first), size=n_obj)
    side = rng.choice([-1.0, 1.0], size=n_obj) * rng.uniform(3.0, 9.0, size=n_obj)
    nrm = np.column_stack([-np.sin(yaw[at]), np.cos(yaw[at])])
    along = rng.uniform(-cfg.speed_mps / 2, cfg.speed_mps / 2, size=n_obj)
    tang = np.column_stack([np.cos(yaw[at]), np.sin(yaw[at])])
    obj_xy = first[at] + side[:, None] * nrm + along[:, None] * tang
    weights = rng.dirichlet(np.ones(len(KITTI_CLASSES)) * 2.0)
    classes = rng.choice(len(KITTI_CLASSES), size=n_obj, p=weights)
    objects = np.column_stack([obj_xy, rng.uniform(0.0, 3.0, n_obj)])
    model = world_embedding_model(Family.KITTI, seed)
    log.debug("drive of %.0f m, %d objects, revisit from frame %d", length, n_obj, split)
    return _simulate(
        Family.KITTI, "kitti-like drive", seed, path_xy, yaw, np.full(len(path_xy), 1.7),
        split, objects, classes, KITTI_CLASSES, cfg, rng, model, "car1", 100.0, image_s,
    )


def _first_revisit(xy: np.ndarray, min_gap: int, radius_m: float = 15.0) -> int:
    """First frame that comes back within radius_m of a frame at least min_gap frames older."""
    tree = cKDTree(xy)
    for k in range(min_gap, len(xy)):
        for j in tree.query_ball_point(xy[k], radius_m):
            if k - j > min_gap:
                return k
    return len(xy) // 2


__all__ = [
    "SURVEY_SAMPLES",
    "ImageUncertainty",
    "Run",
    "RunConfig",
    "drive_run",
    "image_s_dataset",
    "load_kitti_poses",
    "survey_embeddings",
    "underwater_run",
    "world_embedding_model",
]
