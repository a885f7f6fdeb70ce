"""File formats other tools read: TUM trajectories (evo, the TUM RGB-D benchmark tools) and g2o
pose graphs (g2o, GTSAM's readG2o, SE-Sync, ...).

TUM: one pose T_world_body per line, `timestamp tx ty tz qx qy qz qw` (the scalar LAST). g2o
(3-D): VERTEX_SE3:QUAT and EDGE_SE3:QUAT lines, an edge's information matrix in g2o's order
(translation first): write_g2o inverts and permutes mergesvc's GTSAM-order covariances exactly
as gtsam.writeG2o does and gtsam.readG2o undoes.

Numbers are written with Python's shortest round-trip repr (a file read back gives the same
floats); quaternions with qw >= 0. Files are written to a temporary file in the same folder and
renamed over the target, so a reader never sees half a file. The lines: docs/export.md.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mergesvc.core.trajectory import as_poses
from mergesvc.errors import DecodeError, InputError

TUM_FIELDS = "timestamp tx ty tz qx qy qz qw"
# A TUM quaternion whose norm is further than this from 1 is refused (not merely rounded).
QUAT_NORM_TOL = 1e-2
# g2o's EDGE_SE3:QUAT (translation, rotation) index of each GTSAM Pose3 (rotation,
# translation) tangent index, and back (the permutation is its own inverse).
G2O_FROM_GTSAM = np.array([3, 4, 5, 0, 1, 2])


def _num(x: float) -> str:
    return repr(float(x))


def _quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, w >= 0."""
    q = Rotation.from_matrix(R).as_quat()  # scipy: scalar last
    return -q if q[3] < 0 else q


def _pose_fields(T: np.ndarray) -> list[str]:
    """`x y z qx qy qz qw` of a 4x4 pose, as strings."""
    return [_num(v) for v in (*T[:3, 3], *_quat_xyzw(T[:3, :3]))]


def _write_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write text to a new file beside `path`, then rename it over `path` (the new file is
    created like any other, so it gets the usual permissions, not mkstemp's 0600)."""
    out = Path(path)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    created = False
    try:
        with open(tmp, "x", encoding="utf-8", newline="\n") as fh:
            created = True
            fh.write(text)
        os.replace(tmp, out)
    except BaseException as exc:
        if created:
            tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise InputError(f"cannot write {out}: {exc.strerror or exc}") from exc
        raise
    return out


def write_tum(
    path: str | os.PathLike[str], stamps_s: np.ndarray, poses: np.ndarray
) -> Path:
    """Write a trajectory as a TUM file (one `timestamp tx ty tz qx qy qz qw` line per pose).

    stamps_s: (n,) seconds; poses: (n, 4, 4) T_world_body. Returns the path written.
    InputError: no poses, shapes that disagree, NaN or inf, a pose that is not rigid."""
    stamps = np.asarray(stamps_s, dtype=float)
    T = as_poses(poses, "write_tum poses")
    if stamps.ndim != 1 or len(stamps) != len(T):
        raise InputError(
            f"write_tum: {len(T)} poses need {len(T)} timestamps, got shape {stamps.shape}"
        )
    if len(T) == 0:
        raise InputError("write_tum: no poses to write")
    if not np.all(np.isfinite(stamps)):
        bad = int(np.argwhere(~np.isfinite(stamps))[0][0])
        raise InputError(f"write_tum: timestamp {bad} is NaN or inf")
    lines = [f"# {TUM_FIELDS}"]
    lines += [" ".join([_num(s), *_pose_fields(Ti)]) for s, Ti in zip(stamps, T)]
    return _write_atomic(path, "\n".join(lines) + "\n")


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file: ((n,) timestamps in seconds, (n, 4, 4) poses).

    Blank lines and lines starting with `#` are skipped; quaternions are normalised.
    DecodeError (naming the file and line): unreadable file, a line without exactly 8 numbers,
    NaN or inf, a quaternion whose norm is not 1 (within QUAT_NORM_TOL), or no pose at all."""
    src = Path(path)
    try:
        text = src.read_text(encoding="utf-8")
    except OSError as exc:
        raise DecodeError(f"cannot read {src}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise DecodeError(f"{src} is not a text file: {exc.reason}") from exc
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{src}, line {lineno}"
        fields = line.split()
        if len(fields) != 8:
            raise DecodeError(
                f"{where}: expected 8 numbers '{TUM_FIELDS}', found {len(fields)} field(s): "
                f"{line[:80]!r}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            bad = next(f for f in fields if not _is_float(f))
            raise DecodeError(f"{where}: {bad!r} is not a number ({TUM_FIELDS})") from None
        if not all(np.isfinite(values)):
            raise DecodeError(f"{where}: NaN or inf in {line[:80]!r}")
        norm = float(np.linalg.norm(values[4:]))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise DecodeError(
                f"{where}: the quaternion qx qy qz qw = {' '.join(fields[4:])} has norm "
                f"{norm:.6g}, not 1 (is the file in the TUM order '{TUM_FIELDS}'?)"
            )
        rows.append(values)
    if not rows:
        raise DecodeError(f"{src}: no pose lines ('{TUM_FIELDS}')")
    a = np.array(rows)
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()  # scipy: scalar last
    poses[:, :3, 3] = a[:, 1:4]
    return a[:, 0].copy(), poses


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _vertex_id(v: object, what: str) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise InputError(f"write_g2o: {what} {v!r} is not an integer")
    if v < 0:
        raise InputError(f"write_g2o: {what} {v} is negative (g2o ids are non-negative)")
    return int(v)


def g2o_information(covariance: np.ndarray, what: str = "covariance") -> np.ndarray:
    """A 6x6 Pose3 covariance in GTSAM's order (rotation, translation) -> the information
    matrix in g2o's EDGE_SE3:QUAT order (translation, rotation).

    InputError: not 6x6, NaN or inf, not symmetric, or not positive definite."""
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6):
        raise InputError(f"{what}: expected a 6x6 covariance, got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise InputError(f"{what}: the covariance holds NaN or inf")
    if np.abs(C - C.T).max() > 1e-9 * np.abs(C).max():
        raise InputError(f"{what}: the covariance is not symmetric")
    C = (C + C.T) / 2.0
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise InputError(f"{what}: the covariance is not positive definite") from None
    L_inv = np.linalg.inv(L)
    info = L_inv.T @ L_inv  # C^-1, symmetric by construction
    if not np.all(np.isfinite(info)):
        raise InputError(f"{what}: the covariance is too close to singular to invert")
    return info[np.ix_(G2O_FROM_GTSAM, G2O_FROM_GTSAM)]


def write_g2o(
    path: str | os.PathLike[str],
    vertices: Mapping[int, np.ndarray],
    edges: Sequence[tuple[int, int, np.ndarray, np.ndarray]],
) -> Path:
    """Write a 3-D pose graph as a g2o file (VERTEX_SE3:QUAT, EDGE_SE3:QUAT lines).

    vertices: id -> 4x4 pose in the world (written in increasing id order). edges: (i, j,
    T_ij = T_i^-1 T_j, 6x6 covariance of T_ij in GTSAM's Pose3 tangent order: rotation, then
    translation), written in the order given with the information matrix in g2o's order.
    Returns the path written. InputError: ids that are not non-negative integers, an edge to a
    vertex not in `vertices` or from a vertex to itself, NaN or inf, a pose that is not rigid,
    a covariance that is not symmetric positive definite."""
    lines: list[str] = []
    ids: set[int] = set()
    for key in sorted(vertices, key=lambda k: _vertex_id(k, "vertex id")):
        vid = _vertex_id(key, "vertex id")
        T = as_poses(np.asarray(vertices[key], dtype=float)[None], f"write_g2o vertex {vid}")[0]
        lines.append(" ".join(["VERTEX_SE3:QUAT", str(vid), *_pose_fields(T)]))
        ids.add(vid)
    for k, edge in enumerate(edges):
        if len(edge) != 4:
            raise InputError(
                f"write_g2o: edge {k} must be (i, j, T_ij 4x4, covariance 6x6), got {len(edge)} "
                "items"
            )
        i, j = _vertex_id(edge[0], f"edge {k} vertex"), _vertex_id(edge[1], f"edge {k} vertex")
        missing = [v for v in (i, j) if v not in ids]
        if missing:
            raise InputError(f"write_g2o: edge {k} ({i}, {j}) names vertex {missing[0]}, "
                             "which is not among the vertices")
        if i == j:
            raise InputError(f"write_g2o: edge {k} goes from vertex {i} to itself")
        T = as_poses(np.asarray(edge[2], dtype=float)[None], f"write_g2o edge {k} ({i}, {j})")
        info = g2o_information(edge[3], f"write_g2o edge {k} ({i}, {j})")
        upper = info[np.triu_indices(6)]  # row by row, as g2o reads it
        lines.append(
            " ".join(
                ["EDGE_SE3:QUAT", str(i), str(j), *_pose_fields(T[0]), *map(_num, upper)]
            )
        )
    return _write_atomic(path, "\n".join(lines) + "\n")


__all__ = [
    "G2O_FROM_GTSAM",
    "QUAT_NORM_TOL",
    "TUM_FIELDS",
    "g2o_information",
    "read_tum",
    "write_g2o",
    "write_tum",
]
