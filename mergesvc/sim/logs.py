"""Recorded observation logs: a vehicle's perception output as JSON Lines (the format below),
written from simulated frames and read back, validated, as `Frame`s for `mergesvc agent --log`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.tracking import Detection, Frame
from mergesvc.errors import DecodeError, MergeError, SchemaError

# ------------------------------------------------------------------- recorded observation logs
#
# A real vehicle's perception output, replayed by `mergesvc agent --log FILE`. JSON Lines, one
# frame per line:
#   {"stamp_s": 12.0,
#    "pose": {"translation": [x, y, z], "quaternion_wxyz": [w, x, y, z]},   odometry estimate
#    "up_body": [x, y, z],                          optional: gravity's opposite, body frame
#    "detections": [{"embedding": [d floats], "uncertainty": s,             image uncertainty
#                    "position_body_m": [x, y, z], "position_sigma_m": 0.3}, ...]}
# The pose is the vehicle's own estimate in its odometry frame: p_odom = R p_body + t, with R
# from quaternion_wxyz (Hamilton, scalar first) and t = translation. Its body frame is whatever
# axes the vehicle's odometry uses (x forward / z up, or a camera's x right / y down / z
# forward): nothing is assumed about them. position_body_m is a detection's centre in that body
# frame at that stamp (p_odom = R position_body_m + t), in metres, with an isotropic standard
# deviation position_sigma_m. up_body, when the vehicle has an attitude sensor (AHRS, IMU), is
# the measured upward direction in the same body frame (any length > 0; normalised on reading):
# the agent declares it on every submap cut at that frame, and the service then fits factors
# about gravity (yaw and translation only). Without it, `agent.up` in the settings (one
# direction in the odometry frame) is used, else no vertical is declared.


def write_observation_log(frames: Iterator[Frame] | Sequence[Frame], path: Path | str) -> int:
    """Write frames as an observation log (the format above); returns the frame count."""
    n = 0
    with open(path, "w") as fh:
        for fr in frames:
            T = fr.T_est
            q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
            T_inv = np.linalg.inv(T)
            dets = []
            for d in fr.detections:
                body = T_inv[:3, :3] @ d.position_xyz_m + T_inv[:3, 3]
                dets.append({
                    "embedding": d.embedding_d.tolist(),
                    "uncertainty": float(np.mean(d.uncertainty_s)),
                    "position_body_m": body.tolist(),
                    "position_sigma_m": float(np.sqrt(np.trace(d.position_cov_33) / 3.0)),
                })
            rec = {
                "stamp_s": fr.stamp_s,
                "pose": {"translation": T[:3, 3].tolist(),
                         "quaternion_wxyz": [q[3], q[0], q[1], q[2]]},
            }
            if fr.up_body is not None:
                rec["up_body"] = np.asarray(fr.up_body, dtype=np.float64).tolist()
            rec["detections"] = dets
            fh.write(json.dumps(rec) + "\n")
            n += 1
    return n


def read_observation_log(path: Path | str) -> Iterator[Frame]:
    """Frames of an observation log, validated line by line (InputError names the line).
    The log is UTF-8 (JSON's encoding), whatever the machine's locale."""
    with open(path, "rb") as fh:
        for k, raw in enumerate(fh, start=1):
            if not raw.strip():
                continue
            try:
                rec = json.loads(raw.decode("utf-8"))
                t = np.asarray(rec["pose"]["translation"], dtype=np.float64)
                w, x, y, z = rec["pose"]["quaternion_wxyz"]
                if t.shape != (3,) or not np.all(np.isfinite(t)):
                    raise ValueError("pose.translation must be 3 finite numbers")
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
                T[:3, 3] = t
                stamp = float(rec["stamp_s"])
                up = rec.get("up_body")
                if up is not None:
                    up = np.asarray(up, dtype=np.float64)
                    if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.any(up):
                        raise ValueError("up_body must be 3 finite numbers, not all zero")
                    up = up / np.linalg.norm(up)
                dets = []
                for i, d in enumerate(rec.get("detections", [])):
                    body = np.asarray(d["position_body_m"], dtype=np.float64)
                    if body.shape != (3,) or not np.all(np.isfinite(body)):
                        raise ValueError("position_body_m must be 3 finite numbers")
                    sigma = float(d["position_sigma_m"])
                    if not (math.isfinite(sigma) and sigma > 0):
                        raise ValueError("position_sigma_m must be a finite number > 0")
                    p = T[:3, :3] @ body + T[:3, 3]
                    cov = T[:3, :3] @ np.eye(3) * sigma**2 @ T[:3, :3].T
                    try:
                        dets.append(Detection(np.asarray(d["embedding"], dtype=np.float64),
                                              float(d["uncertainty"]), p, cov, stamp))
                    except MergeError as exc:  # named as the log names its fields
                        raise SchemaError(f"detections[{i}]: " + str(exc).replace(
                            "embedding_d", "embedding").replace("uncertainty_s", "uncertainty")
                        ) from exc
            except json.JSONDecodeError as exc:
                raise DecodeError(f"{path}:{k}: not JSON: {exc.msg}") from exc
            except UnicodeDecodeError as exc:
                raise DecodeError(f"{path}:{k}: not UTF-8: {exc.reason}") from exc
            except RecursionError as exc:  # json recurses once per nesting level
                raise DecodeError(f"{path}:{k}: JSON nested too deeply") from exc
            # OverflowError: an integer too large for a float (a 400-digit number)
            except (KeyError, TypeError) as exc:  # a field missing or of another shape
                raise SchemaError(f"{path}:{k}: not an observation record ({type(exc).__name__}:"
                                  f" {exc}): a line holds stamp_s, pose {{translation, "
                                  "quaternion_wxyz}, detections [...] (README: observation logs)"
                                  ) from exc
            except (ValueError, OverflowError) as exc:
                raise SchemaError(f"{path}:{k}: {type(exc).__name__}: {exc}") from exc
            except MergeError as exc:  # tracking.py's InputError for bad values
                raise SchemaError(f"{path}:{k}: {exc}") from exc
            yield Frame(k - 1, stamp, T, T, dets, up_body=up)


__all__ = ["read_observation_log", "write_observation_log"]
