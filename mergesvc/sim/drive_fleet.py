"""A drive-scale fleet from the real KITTI-00 trajectory (`drive_fleet`): three cars, each
driving one overlapping stretch of the ground truth (KITTI-00 revisits its streets, so the
stretches pass each other's places), objects along the road, and odometry that drifts with the
error structure of the real ORB-SLAM2 estimate of the same drive.

Odometry composes D_gt Exp(gain Log(E_k)) per step, E_k = inv(D_gt) D_orb the real step error
(ORB-SLAM2's translation scaled by the drive's Sim(3) scale); gain 1 (the default) is the
ORB-SLAM2 estimate re-anchored at the stretch's start. `drift="vo"` draws each car's step errors
as a seeded block bootstrap (runs of `VO_BLOCK`) of the real ones: visual odometry without loop
closures. Frames are KITTI's camera axes (x right, y down, z forward), world and body: the
service must not assume z up. Visibility and noise are simulated in gravity-aligned axes and
expressed in camera axes afterwards. The model and its drift: docs/benchmarks/merge.md.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from mergesvc.core.tracking import Detection, Frame, TrackingConfig
from mergesvc.core.trajectory import umeyama_alignment
from mergesvc.errors import InputError
from mergesvc.sim.conventions import C_CAMERA, E_Z, up_in
from mergesvc.sim.real_data import (
    DEFAULT_DATA_DIR,
    KITTI_GT,
    KITTI_ORB,
    camera_to_gravity,
    data_available,
    load_kitti_poses_34,
)
from mergesvc.sim.runs import RunConfig, _frames, world_embedding_model
from mergesvc.sim.scenario import KITTI_CLASSES, Family

# frame ranges [start, end) of the full-rate KITTI-00 poses (4541): each stretch revisits
# places of the others (KITTI-00's loop closures: 0-250 at 1500-1750 and 4250-4540, 250 at
# 2250 and 3250, 500-750 at 3500-3750, 2250 at 3250)
STRETCHES_FULL = ((0, 1650), (1400, 3050), (2900, 4541))
# a short version for tests: 0-250 is driven again at 1500-1750 and 4250-4540
STRETCHES_QUICK = ((0, 300), (1450, 1800), (4200, 4541))
A_CAM = np.eye(4)
A_CAM[:3, :3] = C_CAMERA  # camera coords = C gravity coords


def drive_config(step_s: float) -> RunConfig:
    """The KITTI-like sensor of `drive_run` (stereo depth 3-35 m, noise growing with range)."""
    return RunConfig(
        speed_mps=8.0, frame_dt_s=step_s, range_m=(3.0, 35.0), fov_deg=90.0, p_detect=0.8,
        pos_sigma_m=(0.15, 2.5), outlier_rate=0.02, false_per_frame=0.3,
        odo_scale_sigma=0.0, yaw_rw_rad=0.0, yaw_bias_rad=0.0,  # odometry: from ORB-SLAM2
        tracking=TrackingConfig(cos_min=0.6, window_s=10.0),
    )


@dataclass(frozen=True)
class DriveCar:
    name: str
    frames_idx: np.ndarray  # indices into the full-rate KITTI-00 poses
    T_true: np.ndarray  # (n, 4, 4) camera axes, world = KITTI's first camera
    T_est: np.ndarray  # (n, 4, 4) camera axes, the car's odometry frame (identity at start)
    T_true_grav: np.ndarray
    T_est_grav: np.ndarray  # the same two in gravity-aligned axes (x forward, z up)

    @property
    def T_world_start(self) -> np.ndarray:
        return self.T_true[0]


@dataclass(frozen=True)
class DriveFleet:
    """Several cars on stretches of KITTI-00; the interface of sim.fleet.FleetWorld (robots,
    frames(name), session_start(name), objects_xyz_m, object_ids) and up(name), in camera
    axes."""

    seed: int
    objects_xyz_m: np.ndarray  # camera axes (world = KITTI's first camera)
    objects_grav: np.ndarray
    object_ids: list[str]
    classes: np.ndarray
    truth_emb: np.ndarray
    cars: list[DriveCar]
    cfg: RunConfig
    odometry_step_sigma: tuple[float, float]  # measured per-step error std: rad, m
    # measured std of the odometry's error at a keyframe relative to its stretch's start
    # (rad x3, m x3, GTSAM order): a loop-closed estimate's bound; None for drift="vo"
    odometry_bound_sigma: tuple[float, ...] | None = None
    # ... and the distance (m) over which that error stays alike (its autocorrelation's 1/e)
    odometry_bound_span_m: float | None = None

    @property
    def robots(self) -> list[DriveCar]:
        return self.cars

    def robot(self, name: str) -> DriveCar:
        for c in self.cars:
            if c.name == name:
                return c
        raise ValueError(f"no car {name!r} in this fleet (have {[c.name for c in self.cars]})")

    def session_start(self, name: str, session: int = 0) -> np.ndarray:
        return self.robot(name).T_world_start

    def up(self, name: str) -> np.ndarray:
        """The vertical (opposite to gravity) in a car's odometry frame (camera axes; its
        start's camera, tilted as the road is there)."""
        return up_in(C_CAMERA, self.robot(name).T_true_grav[0][:3, :3].T @ E_Z)

    def frames(self, name: str, session: int = 0) -> Iterator[Frame]:
        """The car's frames in camera axes, detections placed in its odometry frame."""
        car = self.robot(name)
        idx = [c.name for c in self.cars].index(name)
        rng = np.random.default_rng([self.seed, 41, idx])
        model = world_embedding_model(Family.KITTI, self.seed)
        stamps = np.arange(len(car.frames_idx)) * self.cfg.frame_dt_s
        C = C_CAMERA
        for fr in _frames(Family.KITTI, car.T_true_grav, car.T_est_grav, stamps,
                          self.objects_grav, self.truth_emb, self.object_ids,
                          len(KITTI_CLASSES), self.cfg, rng, model):
            dets = [Detection(d.embedding_d, d.uncertainty_s, C @ d.position_xyz_m,
                              C @ d.position_cov_33 @ C.T, d.stamp_s, d.truth_id)
                    for d in fr.detections]
            up = None if fr.up_body is None else C @ fr.up_body  # the IMU, in camera axes
            yield Frame(fr.k, fr.stamp_s, car.T_est[fr.k], car.T_true[fr.k], dets, up_body=up)


def _to_camera(T_grav: np.ndarray) -> np.ndarray:
    return A_CAM @ T_grav @ np.linalg.inv(A_CAM)


def _step_errors(G: np.ndarray, orb: np.ndarray) -> list[np.ndarray]:
    """E_k = inv(D_gt) D_orb per step (k = 1..n-1), as Pose3 tangent vectors (rot, trans)."""
    out = []
    for k in range(1, len(G)):
        d_gt = gtsam.Pose3(np.linalg.inv(G[k - 1]) @ G[k])
        d_orb = gtsam.Pose3(np.linalg.inv(orb[k - 1]) @ orb[k])
        out.append(gtsam.Pose3.Logmap(d_gt.between(d_orb)))
    return out


DRIFTS = ("orbslam", "vo")
VO_BLOCK = 25  # steps of 0.4 s: 10 s of correlated error per block


def _block_bootstrap(pool: np.ndarray, n: int, block: int, rng: np.random.Generator
                     ) -> np.ndarray:
    """n rows of `pool` as runs of `block` consecutive rows from random starts."""
    if len(pool) <= block:
        raise InputError(f"{len(pool)} step errors: too few for blocks of {block}")
    starts = rng.integers(0, len(pool) - block, size=n // block + 1)
    return np.concatenate([pool[s:s + block] for s in starts])[:n]


def drive_fleet(
    seed: int = 0,
    robots: Sequence[str] = ("car1", "car2", "car3"),
    stretches: Sequence[tuple[int, int]] = STRETCHES_FULL,
    step: int = 4,
    object_spacing_m: float = 6.0,
    drift_gain: float = 1.0,
    data_dir: Path | None = None,
    drift: str = "orbslam",
) -> DriveFleet:
    """Cars on the given stretches of KITTI-00 (full-rate frame ranges), every `step`-th pose
    (KITTI is 10 Hz: step 4 is 0.4 s, ~3 m), objects every ~object_spacing_m of road on either
    side (3-9 m off the centre line, 0-3 m above the road; none within 2 m of another).
    drift: "orbslam" (the estimate's own step errors) or "vo" (block-bootstrapped; module doc).
    InputError when the KITTI-00 files are not in data_dir (default ../shared/data)."""
    if drift not in DRIFTS:
        raise InputError(f"unknown drift {drift!r}: use one of {', '.join(DRIFTS)}")
    d = Path(data_dir or DEFAULT_DATA_DIR)
    if not data_available(d, KITTI_GT, KITTI_ORB):
        raise InputError(f"the KITTI-00 poses ({KITTI_GT}, {KITTI_ORB}) are not under {d}")
    if len(stretches) != len(robots):
        raise InputError(f"{len(robots)} robots but {len(stretches)} stretches")
    G_cam = load_kitti_poses_34(d / KITTI_GT)
    O_cam = load_kitti_poses_34(d / KITTI_ORB)
    _, _, scale = umeyama_alignment(O_cam[:, :3, 3], G_cam[:, :3, 3], with_scale=True)
    O_cam = O_cam.copy()
    O_cam[:, :3, 3] *= scale
    G = camera_to_gravity(G_cam)
    orb = camera_to_gravity(O_cam)
    rng = np.random.default_rng([seed, 43])
    cfg = drive_config(0.1 * step)

    # objects along the whole drive, both sides of the road
    xy, yaw = G[:, :2, 3], np.arctan2(G[:, 1, 0], G[:, 0, 0])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    at = np.searchsorted(arc, np.arange(0.0, arc[-1], object_spacing_m / 2.0))
    at = np.clip(at, 0, len(xy) - 1)
    side = rng.choice([-1.0, 1.0], size=len(at)) * rng.uniform(3.0, 9.0, size=len(at))
    along = rng.uniform(-object_spacing_m / 2, object_spacing_m / 2, size=len(at))
    nrm = np.column_stack([-np.sin(yaw[at]), np.cos(yaw[at])])
    tang = np.column_stack([np.cos(yaw[at]), np.sin(yaw[at])])
    cand = np.column_stack([xy[at] + side[:, None] * nrm + along[:, None] * tang,
                            G[at, 2, 3] - 1.65 + rng.uniform(0.0, 3.0, len(at))])
    road = cKDTree(xy)
    kept: list[np.ndarray] = []
    for p in cand:
        if road.query(p[:2])[0] < 2.5:
            continue  # on the road of another pass
        if kept and np.min(np.linalg.norm(np.asarray(kept) - p, axis=1)) < 2.0:
            continue
        kept.append(p)
    objects = np.asarray(kept)
    weights = rng.dirichlet(np.ones(len(KITTI_CLASSES)) * 2.0)
    classes = rng.choice(len(KITTI_CLASSES), size=len(objects), p=weights)
    model = world_embedding_model(Family.KITTI, seed)
    truth_emb = model.instances(classes, rng)
    ids = [f"{KITTI_CLASSES[c]}_{k}" for k, c in enumerate(classes)]

    cars, errs = [], []
    pool = np.asarray(_step_errors(G[::step], orb[::step])) if drift == "vo" else None
    vo_rng = np.random.default_rng([seed, 44])
    for name, (a, b) in zip(robots, stretches):
        idx = np.arange(a, min(b, len(G)), step)
        Gs, orb_s = G[idx], orb[idx]
        e = _step_errors(Gs, orb_s)
        if pool is not None:
            e = list(_block_bootstrap(pool, len(e), VO_BLOCK, vo_rng))
        errs += e
        est = [np.eye(4)]
        for k in range(1, len(idx)):
            d_gt = gtsam.Pose3(np.linalg.inv(Gs[k - 1]) @ Gs[k])
            step_T = d_gt.compose(gtsam.Pose3.Expmap(drift_gain * e[k - 1]))
            est.append(est[-1] @ step_T.matrix())
        T_est_grav = np.stack(est)
        # the car's odometry frame is its true start (identity there)
        cars.append(DriveCar(
            name, idx, np.stack([_to_camera(T) for T in Gs]),
            np.stack([_to_camera(T) for T in T_est_grav]), Gs, T_est_grav))
    ev = np.asarray(errs)
    sigma = (float(np.sqrt((ev[:, :3] ** 2).mean())), float(np.sqrt((ev[:, 3:] ** 2).mean())))
    return DriveFleet(seed, (C_CAMERA @ objects.T).T, objects, ids, classes, truth_emb, cars,
                      cfg, sigma, *((None, None) if drift == "vo" else _bound(cars)))


def _bound(cars: Sequence[DriveCar]) -> tuple[tuple[float, ...], float]:
    """What a loop-closed estimate's owner would declare: the RMS per axis (GTSAM order, body
    frame, camera axes) of the odometry's error at every pose relative to its car's start, and
    the distance over which that error stays alike (the mean over cars of the path length at
    which its translation's autocorrelation falls below 1/e)."""
    errs, spans = [], []
    for c in cars:
        e = np.array([gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(c.T_true[0]) @ T)
                                         .between(gtsam.Pose3(E)))
                      for T, E in zip(c.T_true, c.T_est)])
        errs.append(e)
        x = e[:, 3:] - e[:, 3:].mean(axis=0)
        step_m = np.mean(np.linalg.norm(np.diff(c.T_true[:, :3, 3], axis=0), axis=1))
        lag = next((lag for lag in range(1, len(x) // 2) if np.mean(
            [np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)]) < np.exp(-1)),
            len(x) // 2)
        spans.append(lag * step_m)
    rms = np.sqrt(np.mean(np.square(np.vstack(errs)), axis=0))
    return tuple(float(v) for v in rms), float(np.mean(spans))


__all__ = ["DRIFTS", "STRETCHES_FULL", "STRETCHES_QUICK", "DriveCar", "DriveFleet", "drive_config",
           "drive_fleet"]
