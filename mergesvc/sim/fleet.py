"""A fleet in one pool: several vehicles surveying shared objects, each on its own pattern and in
its own odometry frame (`fleet_world`), for the fleet demo, the agent and the service tests.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from mergesvc.core.tracking import Frame, TrackingConfig
from mergesvc.sim.runs import (
    RunConfig,
    _frames,
    _odometry,
    _pool_objects,
    _pose,
    _sample_path,
    world_embedding_model,
)
from mergesvc.sim.scenario import UNDERWATER_CLASSES, EmbeddingModel, Family

# ----------------------------------------------------------------------- a fleet in one pool


@dataclass(frozen=True)
class FleetRobot:
    """One vehicle of a fleet world: its path and its true start pose (its odometry frame)."""

    name: str
    path_xy: np.ndarray
    yaw: np.ndarray
    z_m: float
    T_world_start: np.ndarray  # (4, 4): where its odometry frame sits in the world


@dataclass(frozen=True)
class FleetWorld:
    """Several vehicles surveying one pool: shared objects and appearance model, one path and
    one odometry frame each. Everything follows from (seed, robot names, laps)."""

    seed: int
    objects_xyz_m: np.ndarray
    object_ids: list[str]
    classes: np.ndarray
    truth_emb: np.ndarray
    model: EmbeddingModel
    robots: list[FleetRobot]
    cfg: RunConfig
    # per-step odometry noise (rotation rad, translation m) drawn white on all six axes, as
    # the pose graph's odometry model assumes (`white_odometry`); None: the pool's dead
    # reckoning (2 % scale error, a heading random walk and a gyro bias)
    white_odometry: tuple[float, float] | None = None

    def robot(self, name: str) -> FleetRobot:
        for r in self.robots:
            if r.name == name:
                return r
        raise ValueError(f"no robot {name!r} in this fleet (have {[r.name for r in self.robots]})")

    def T_rel_true(self, a: str, b: str) -> np.ndarray:
        """True pose of robot b's odometry frame in robot a's: inv(T_world_a) T_world_b."""
        return np.linalg.inv(self.robot(a).T_world_start) @ self.robot(b).T_world_start

    def frames(self, name: str, session: int = 0) -> Iterator[Frame]:
        """The robot's frames, detections placed in its own odometry frame (origin: its start).
        A later session starts where the robot is put back in the water, a new frame."""
        r = self.robot(name)
        idx = [x.name for x in self.robots].index(name)
        rng = np.random.default_rng([self.seed, 31, idx, session])
        path, yaw = r.path_xy, r.yaw
        if session:
            shift = int(len(path) * (0.3 + 0.2 * (session % 2)))
            path, yaw = np.roll(path, -shift, axis=0), np.roll(yaw, -shift)
        n = len(path)
        stamps = np.arange(n) * self.cfg.frame_dt_s
        T0 = _pose(*path[0], r.z_m, yaw[0])
        T0_inv = np.linalg.inv(T0)
        poses_true = np.stack([_pose(*path[k], r.z_m, yaw[k]) for k in range(n)])
        if self.white_odometry is None:
            est_xy, est_yaw = _odometry(path, yaw, self.cfg, rng)
            poses_est = np.stack([T0_inv @ _pose(*est_xy[k], r.z_m, est_yaw[k])
                                  for k in range(n)])
        else:
            poses_est = white_odometry(poses_true, self.white_odometry, rng)
        yield from _frames(Family.UNDERWATER, poses_true, poses_est, stamps, self.objects_xyz_m,
                           self.truth_emb, self.object_ids, len(UNDERWATER_CLASSES), self.cfg,
                           rng, self.model)

    def session_start(self, name: str, session: int = 0) -> np.ndarray:
        """True world pose of the odometry frame of a robot's session."""
        r = self.robot(name)
        if not session:
            return r.T_world_start
        shift = int(len(r.path_xy) * (0.3 + 0.2 * (session % 2)))
        k = shift % len(r.path_xy)
        return _pose(*r.path_xy[k], r.z_m, r.yaw[k])


def white_odometry(poses_true: np.ndarray, sigma: tuple[float, float],
                   rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) dead-reckoned poses from the first: each true step D_k composed with
    Exp(eta_k), eta_k ~ N(0, diag(r, r, r, t, t, t)^2) (rotation rad, translation m)."""
    r, t = sigma
    out = [np.eye(4)]
    noise = rng.normal(0.0, 1.0, size=(len(poses_true) - 1, 6)) * ([r] * 3 + [t] * 3)
    for k in range(1, len(poses_true)):
        D = np.linalg.solve(poses_true[k - 1], poses_true[k])
        out.append(out[-1] @ D @ gtsam.Pose3.Expmap(noise[k - 1]).matrix())
    return np.stack(out)


def fleet_world(seed: int = 0, robots: Sequence[str] = ("auv1", "auv2", "auv3"),
                laps: int = 2, n_objects: int = 24,
                white: tuple[float, float] | None = None) -> FleetWorld:
    """A 30 x 16 m pool with n_objects objects and one vehicle per name, each on its own
    pattern (loops and lawnmowers over overlapping parts of the pool), starting in its own
    place, so their odometry frames differ by an unknown rigid transform. `white`: the
    odometry noise per step on all six axes (FleetWorld.white_odometry)."""
    rng = np.random.default_rng([seed, 5])
    classes, objects = _pool_objects(n_objects, np.array([30.0, 16.0]), rng)
    model = world_embedding_model(Family.UNDERWATER, seed)
    truth_emb = model.instances(classes, rng)
    ids = [f"{UNDERWATER_CLASSES[c]}_{k}" for k, c in enumerate(classes)]
    cfg = RunConfig(
        speed_mps=0.5, frame_dt_s=1.0, range_m=(0.5, 5.0), fov_deg=100.0, p_detect=0.7,
        pos_sigma_m=(0.1, 0.4), outlier_rate=0.03, false_per_frame=0.05,
        odo_scale_sigma=0.02, yaw_rw_rad=np.radians(0.2), yaw_bias_rad=np.radians(0.01),
        tracking=TrackingConfig(cos_min=0.6, window_s=60.0),
    )
    patterns = [
        np.array([[2, 2], [18, 2], [18, 14], [2, 14], [2, 2]], float),  # west loop
        np.array([[28, 14], [12, 14], [12, 2], [28, 2], [28, 14]], float),  # east loop
        np.array([[3, 5], [27, 5], [27, 11], [3, 11], [3, 5]], float),  # middle loop
        np.array([[2, 8], [28, 8], [28, 3], [2, 3], [2, 13], [28, 13]], float),
    ]
    out = []
    for i, name in enumerate(robots):
        way = np.vstack([patterns[i % len(patterns)]] * laps)
        path, yaw = _sample_path(way, cfg.speed_mps * cfg.frame_dt_s)
        zr = -2.0 + 0.3 * i
        out.append(FleetRobot(name, path, yaw, zr, _pose(*path[0], zr, yaw[0])))
    return FleetWorld(seed, objects, ids, classes, truth_emb, model, out, cfg, white)


__all__ = ["FleetRobot", "FleetWorld", "fleet_world", "white_odometry"]
