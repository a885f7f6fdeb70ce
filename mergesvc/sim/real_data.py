"""Real data in `../shared/data` (next to the repository): the KITTI-00 ground truth and
ORB-SLAM2 poses, 12 real DINO ViT-S centroids of underwater objects; their loaders and the
change from KITTI's camera axes to gravity-aligned ones.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mergesvc.sim.conventions import C_CAMERA

# <repo>/mergesvc/sim/real_data.py -> parents[3] is the repository's parent: ../shared/data
DEFAULT_DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
KITTI_GT = "kitti00/KITTI_00_gt.txt"
KITTI_ORB = "kitti00/KITTI_00_ORB.txt"
DINO_CENTROIDS = "dino_underwater/object_encodings_2obj1loop.txt"


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


__all__ = [
    "DEFAULT_DATA_DIR",
    "DINO_CENTROIDS",
    "KITTI_GT",
    "KITTI_ORB",
    "camera_to_gravity",
    "data_available",
    "load_dino_centroids",
    "load_kitti_poses_34",
]
