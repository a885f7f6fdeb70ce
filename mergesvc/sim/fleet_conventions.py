"""A fleet whose vehicles each use their own axis convention (ENU, NED, camera, a random
rotation) for their body and odometry frames: the same world, the same noise, only the axes
renamed (`in_conventions`). What a merge of it gives must not depend on the conventions.

For a vehicle in convention C (p_conv = C p, core axes x forward, y left, z up): each pose
T (body -> odometry) becomes C T C^T in block form (R -> C R C^T, t -> C t); detections and
their covariances in the odometry frame C p, C S C^T; the measured vertical C up; the true pose
T_true C^T and the odometry frame's true start S C^T (`robots`, `robot`, `T_rel_true` and
`session_start` give it so); the world frame and the paths in it are not renamed.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from mergesvc.core.tracking import Frame
from mergesvc.sim.conventions import E_Z, up_in


def _block(C: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = C
    return out


@dataclass(frozen=True)
class _Renamed:
    """A robot of the world (any record: the pool's vehicles, the drive fleet's cars) with its
    odometry frame's true start in its convention."""

    robot: Any
    T_world_start: np.ndarray

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if name.startswith("T_"):  # the record's other poses are in the world's own axes
            raise AttributeError(f"{name} is not renamed: read the fleet's frames")
        return getattr(self.robot, name)


@dataclass(frozen=True)
class ConventionFleet:
    """`world` (a fleet world: robots, frames, session_start, objects_xyz_m, object_ids, and
    optionally up) with robot name -> its convention C (3, 3); robots not listed keep the
    world's axes."""

    world: Any
    conventions: Mapping[str, np.ndarray]

    def __getattr__(self, name: str) -> Any:  # objects, ids, cfg, ...: the world's own
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.world, name)

    @property
    def robots(self) -> list[Any]:
        """The world's robots, each odometry frame's true start in its convention."""
        return [self.robot(r.name) for r in self.world.robots]

    def robot(self, name: str) -> Any:
        return _Renamed(self.world.robot(name), self.session_start(name))

    def T_rel_true(self, a: str, b: str) -> np.ndarray:
        """True pose of robot b's odometry frame in robot a's, both in their conventions."""
        return np.linalg.inv(self.session_start(a)) @ self.session_start(b)

    def convention(self, name: str) -> np.ndarray:
        return np.asarray(self.conventions.get(name, np.eye(3)), dtype=np.float64)

    def up(self, name: str) -> tuple[float, float, float]:
        """The vertical (opposite to gravity) in the robot's odometry frame: the world's own
        (`world.up(name)`, as the drive fleet's camera axes give it), else z, renamed."""
        own = self.world.up(name) if hasattr(self.world, "up") else E_Z
        return tuple(float(x) for x in up_in(self.convention(name), own))  # type: ignore[return-value]

    def frames(self, name: str, session: int = 0) -> Iterator[Frame]:
        C = self.convention(name)
        B = _block(C)
        for f in self.world.frames(name, session):
            dets = [replace(d, position_xyz_m=C @ d.position_xyz_m,
                            position_cov_33=C @ d.position_cov_33 @ C.T)
                    for d in f.detections]
            yield replace(f, T_est=B @ f.T_est @ B.T, T_true=f.T_true @ B.T,
                          detections=dets,
                          up_body=None if f.up_body is None else C @ f.up_body)

    def session_start(self, name: str, session: int = 0) -> np.ndarray:
        return self.world.session_start(name, session) @ _block(self.convention(name)).T


def in_conventions(world: Any, conventions: Mapping[str, np.ndarray]) -> ConventionFleet:
    """`world` with each listed robot's body and odometry axes in its convention."""
    return ConventionFleet(world, dict(conventions))


__all__ = ["ConventionFleet", "in_conventions"]
