"""Frame conventions: a convention is a rotation C taking gravity-aligned coordinates (x forward,
y left, z up) into its axes (ENU, NED, camera, a random rotation). Points, the truth and the
optional `up` field re-expressed with it, `match` files written in it and parsed back
(`rotate_world`: a scenario in other conventions, e.g. for tests and the generalization worlds).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.model import ObjectArrays, ObjectMap, Submap, parse_model
from mergesvc.sim.scenario import Scenario

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


__all__ = [
    "CONVENTIONS",
    "C_CAMERA",
    "C_ENU",
    "C_NED",
    "E_Z",
    "convention_rotation",
    "random_rotation",
    "rotate_points",
    "rotate_truth",
    "rotate_world",
    "supports_up",
    "up_in",
]
