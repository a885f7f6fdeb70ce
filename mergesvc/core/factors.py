"""Match result -> inter-robot factor: what the service sends for an accepted match.

A match of submap b against the objects of session a gives T_map_submap and its 6x6 covariance
(GTSAM's Pose3 tangent order: rotation (rad), then translation (m)). The factor carries the
relative pose, its covariance inflated by the odometry drift (`inflate_covariance`), and the
matched object pairs:

- frame level (submaps without keyframes): T_a_b = T_map_submap ties the two session frames;
- pose level (keyframes): it ties keyframe Ka of a (`anchoring_keyframe`: the keyframe most
  matched map objects hang on) to b's keyframe Kb, T_{Ka,Kb} = inv(T_{a,Ka}) T_{a,Kb}, with the
  match's covariance unchanged (before the drift inflation). Derivation: docs/pose_graph.md.
`odometry_edge` turns a keyframe submap's odometry into the known-inlier edge between two
keyframes of its session. Pure computation: no Zenoh, no files.
"""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from mergesvc.core.frames import FrameId, KeyframeId
from mergesvc.core.model import (
    MAX_ID_LENGTH,
    Correspondence,
    Factor,
    FactorStatus,
    MatchResult,
    Submap,
)
from mergesvc.core.poses import as_pose3, pose3_from_model, transform_from_pose3
from mergesvc.core.verify import (
    align_about_vertical,
    align_weighted,
    pose_covariance_info,
    skew,
)
from mergesvc.errors import InputError

if TYPE_CHECKING:
    from mergesvc.core.pipeline import MatchOutcome


def inflate_covariance(
    covariance: Sequence[Sequence[float]] | np.ndarray, drift_sigma: tuple[float, float]
) -> np.ndarray:
    """`covariance` (6x6, GTSAM Pose3 order) plus the drift: drift_sigma = (rotation rad,
    translation m) is added as variances on the diagonal, sigma_r^2 on the three rotation
    entries, then sigma_t^2 on the three translation entries.

    Odometry frames drift, so the same pair of frames seen through different stretches of two
    trajectories differs by more than the rigid fit's own covariance says."""
    cov = np.asarray(covariance)
    if cov.shape != (6, 6):
        raise InputError(f"covariance must be 6x6, got shape {cov.shape}")
    r_sig, t_sig = drift_sigma
    return cov + np.diag([r_sig**2] * 3 + [t_sig**2] * 3)


_ID_ESCAPES = str.maketrans({"%": "%25", ".": "%2E", "-": "%2D"})


def match_factor_id(frame_a: FrameId, frame_b: FrameId, seq: int) -> str:
    """The id of the factor from submap `seq` of frame_b matched against frame_a (docs/wire.md
    §6.3): "{robot_a}.{session_a}-{robot_b}.{session_b}-{seq}" with `%`, `.` and `-` in each
    name written %25, %2E, %2D, so two tuples never share an id; when that is longer than an
    id may be (128), "h-" and the first 32 hex digits of the SHA-256 of the tuple as compact
    JSON. Deterministic, so a replay of the same submap gives the same id."""
    names = (frame_a.robot, frame_a.session, frame_b.robot, frame_b.session)
    ra, sa, rb, sb = (n.translate(_ID_ESCAPES) for n in names)
    fid = f"{ra}.{sa}-{rb}.{sb}-{seq}"
    if len(fid) <= MAX_ID_LENGTH:
        return fid
    text = json.dumps([*names, seq], separators=(",", ":"), ensure_ascii=False)
    return "h-" + hashlib.sha256(text.encode("utf-8")).hexdigest()[:32]


def yields_factor(result: MatchResult | MatchOutcome) -> bool:
    """True when a match can become a factor: accepted, with a transform and a covariance."""
    res = _result(result)
    return res.accepted and res.transform is not None and res.covariance is not None


def factor_from_match(
    result: MatchResult | MatchOutcome,
    frame_a: FrameId,
    frame_b: FrameId,
    *,
    factor_id: str,
    drift_sigma: tuple[float, float],
    status: FactorStatus = FactorStatus.ACCEPTED,
    keyframe_a: int | None = None,
    keyframe_b: int | None = None,
    T_a_keyframe_a: gtsam.Pose3 | np.ndarray | None = None,
    measured: tuple[gtsam.Pose3, np.ndarray] | None = None,
) -> Factor:
    """The factor T_a_b between frame_a (the map matched against) and frame_b (the submap's),
    its covariance the result's inflated by `drift_sigma`, its correspondences the matched
    pairs (object_a the map object, object_b the submap object).

    Pose level (keyframe_a and keyframe_b both given): the factor ties keyframe keyframe_a of
    frame_a to keyframe keyframe_b of frame_b (the submap's keyframe, its positions' frame):
    T_a_b = inv(T_a_keyframe_a) T_map_submap, T_a_keyframe_a the pose of keyframe_a in
    frame_a's session frame used to place the map (default: identity); the covariance is the
    result's (a constant left factor leaves a right perturbation as it is) inflated. Without
    keyframes: the frame-level factor, T_a_b = T_map_submap.

    measured: T_{keyframe_a, keyframe_b} and its covariance fitted otherwise (`local_fit`),
    used instead of the result's transform and covariance (still inflated by drift_sigma).

    A result that does not `yields_factor` (rejected, or without transform or covariance) is
    refused with `InputError`, and so are one keyframe without the other, or T_a_keyframe_a
    without keyframes. A factor that does not validate (e.g. an id longer than the model
    allows) raises pydantic's ValidationError, as the model does."""
    res = _result(result)
    transform, covariance = res.transform, res.covariance
    if not res.accepted or transform is None or covariance is None:
        raise InputError(
            "only an accepted match with a transform and a covariance becomes a factor "
            f"(this one: {res.reason.value})"
        )
    if (keyframe_a is None) != (keyframe_b is None):
        raise InputError("keyframe_a and keyframe_b go together")
    if keyframe_a is None and T_a_keyframe_a is not None:
        raise InputError("T_a_keyframe_a needs keyframe_a and keyframe_b")
    if measured is not None:
        if keyframe_a is None or T_a_keyframe_a is not None:
            raise InputError("a measured factor ties two keyframes, and needs no T_a_keyframe_a")
        transform, covariance = transform_from_pose3(measured[0]), measured[1]
    elif T_a_keyframe_a is not None:
        T_ka = as_pose3(T_a_keyframe_a, "T_a_keyframe_a")
        transform = transform_from_pose3(T_ka.inverse().compose(pose3_from_model(transform)))
    cov = inflate_covariance(covariance, drift_sigma)
    return Factor(
        factor_id=factor_id,
        robot_a=frame_a.robot, session_a=frame_a.session,
        robot_b=frame_b.robot, session_b=frame_b.session,
        T_a_b=transform, covariance=cov.tolist(),
        correspondences=[Correspondence(object_a=m.map_object, object_b=m.submap_object,
                                        score=m.score) for m in res.matches],
        status=status,
        keyframe_a=keyframe_a, keyframe_b=keyframe_b,
    )


def local_fit(
    sub_xyz: np.ndarray,
    map_body_xyz: np.ndarray,
    map_keyframes: Sequence[int],
    placements: Mapping[int, tuple[gtsam.Pose3, np.ndarray]],
    *,
    up_sub: np.ndarray | None = None,
    up_map: np.ndarray | None = None,
    vertical_sigma_rad: float = np.radians(2.0),
    sigma_floor_m: float = 1e-3,
    range_weighted: bool = True,
    placement_weighted: bool = True,
) -> tuple[gtsam.Pose3, np.ndarray] | None:
    """T_{Ka,Kb} and its covariance from matched objects, the map's placed around keyframe Ka
    by the odometry alone (not by any merged solution, so that errors of the graph do not
    become errors of its factors).

    sub_xyz: (k, 3) submap objects in Kb's frame; map_body_xyz: (k, 3) the matched map
    objects, each in the frame of its own keyframe map_keyframes[i]; placements: keyframe ->
    (T_{Ka,k}, its 6x6 covariance: the odometry composed from Ka). With both verticals (up_sub
    in Kb's frame, up_map in Ka's) the fit is about gravity (4-DoF: yaw and translation, a tilt
    prior of vertical_sigma_rad), else 6-DoF. The covariance is the fit's (sigma from the
    residuals, at least sigma_floor_m) plus the placements' carried through the fit to first
    order: objects placed by one keyframe move together (docs/uncertainty.md). None when the
    pairs do not fix a transform (too few, on a line, or a keyframe not placed).

    range_weighted: an object's noise grows with its range from the keyframe that placed it
    (sonar and stereo both): sigma_i = c (1 + rho_i / median rho), rho_i the larger of its two
    ranges, c from the weighted residuals. placement_weighted: the fit is then redone with
    each pair weighed by its noise plus its placement's (an object placed by a long odometry
    chain from Ka moves with that chain's heading error); the covariance stays the one of the
    fit weighed by noise alone (conservative for it), the tilt turning the points about the
    weighted centroid the fit keeps."""
    k = len(sub_xyz)
    if k == 0 or any(g not in placements for g in map_keyframes):
        return None
    m = np.asarray(map_body_xyz, dtype=np.float64)
    q = np.array([placements[g][0].transformFrom(x) for x, g in zip(m, map_keyframes,
                                                                      strict=True)])
    p = np.asarray(sub_xyz, dtype=np.float64)
    u = np.ones(k)  # each pair's noise, relative
    if range_weighted:
        rho = np.maximum(np.linalg.norm(p, axis=1), np.linalg.norm(m, axis=1))
        u = 1.0 + rho / max(float(np.median(rho)), 1e-9)
    vertical = up_sub is not None and up_map is not None
    if vertical:
        u_s = np.asarray(up_sub, dtype=np.float64) / np.linalg.norm(up_sub)
        u_m = np.asarray(up_map, dtype=np.float64) / np.linalg.norm(up_map)
        centred = p - p.mean(axis=0)
        if k < 2 or np.linalg.norm(centred - np.outer(centred @ u_s, u_s), axis=1).max() < 1e-6:
            return None
        dof = 3 * k - 4

        def fit(w: np.ndarray) -> gtsam.Pose3 | None:
            return align_about_vertical(p, q, u_s, u_m, weights=w)
    else:
        if k < 3:
            return None
        sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if sv[1] < 1e-3 * sv[0]:
            return None
        dof = 3 * k - 6

        def fit(w: np.ndarray) -> gtsam.Pose3 | None:
            return align_weighted(p, q, w)
    T = fit(1.0 / u**2)
    if T is None:
        return None
    R = T.rotation().matrix()
    rss = float(np.sum(np.sum((p @ R.T + T.translation() - q) ** 2, axis=1) / u**2))
    c = max(np.sqrt(rss / dof) if dof > 0 else 0.0, sigma_floor_m)
    sigma = c * u  # each pair's own noise
    # each pair's placement: q_i = P_g m_i moves by G_i eta, G_i = R_g [-[m_i]x, I], eta ~ S_g
    G = {i: placements[g][0].rotation().matrix() @ np.hstack([-skew(m[i]), np.eye(3)])
         for i, g in enumerate(map_keyframes)}
    s_eff = sigma  # the weights of the fit
    if placement_weighted:  # the variance each placement adds to its pair's position
        spread = np.array([np.trace(G[i] @ placements[g][1] @ G[i].T) / 3.0
                           for i, g in enumerate(map_keyframes)])
        if np.any(spread > 0):  # the fit again, weighed by both
            s_eff = np.sqrt(sigma**2 + spread)
            T = fit(1.0 / s_eff**2)
            if T is None:
                return None
            R = T.rotation().matrix()
    # the covariance: the fit weighed by noise alone's (K, and the placements carried through
    # it), at T; under the model the placement-weighted fit spreads less, so this is
    # conservative for it. Its own (a sandwich) was tighter than its errors in the tail: a
    # submap's objects share a rigid error of the vehicle's local map that no residual shows
    # (docs/uncertainty.md)
    try:
        info = pose_covariance_info(T, p, sigma)
        if vertical:  # yaw and translation from the points, tilt from the verticals' prior
            B = np.zeros((6, 4))
            B[:3, 0], B[3:, 1:] = u_s, np.eye(3)
            K = B @ np.linalg.inv(B.T @ info @ B) @ B.T  # data gradient -> fitted directions
        else:
            K = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    cov = K.copy()
    if vertical:
        # the tilt, from the verticals' prior (each frame's up known to vertical_sigma_rad),
        # turns the points about the centroid the fit keeps in place: its weighted one
        w = 1.0 / s_eff**2
        Gc = np.vstack([np.eye(3), skew(w @ p / w.sum())])
        cov += Gc @ (2.0 * vertical_sigma_rad**2 * (np.eye(3) - np.outer(u_s, u_s))) @ Gc.T
    # the placements: the fit moves by K sum_i J_i^T dq_i / sigma_i^2 (J_i = [-R [p_i]x, R],
    # verify.pose_covariance), dq_i = G_i eta_g for the pairs of keyframe g
    M = np.zeros((6, 6))
    for g in dict.fromkeys(map_keyframes):
        Bg = np.zeros((6, 6))
        for i in (i for i, kf in enumerate(map_keyframes) if kf == g):
            J = np.hstack([-R @ skew(p[i]), R])
            Bg += J.T @ G[i] / sigma[i] ** 2
        M += Bg @ placements[g][1] @ Bg.T
    total = cov + K @ M @ K.T
    return T, 0.5 * (total + total.T)


def anchoring_keyframe(
    result: MatchResult | MatchOutcome, keyframe_of: Mapping[str, int]
) -> int:
    """The keyframe of map a a pose-level factor hangs on: the one holding most of the matched
    map objects (`keyframe_of`: map object id -> the keyframe whose frame its position is in);
    a tie goes to the latest keyframe. InputError if no matched object has a keyframe."""
    votes = Counter(
        keyframe_of[m.map_object] for m in _result(result).matches if m.map_object in keyframe_of
    )
    if not votes:
        raise InputError("no matched map object has a keyframe")
    return max(votes, key=lambda k: (votes[k], k))


def factor_nodes(factor: Factor) -> tuple[KeyframeId, KeyframeId]:
    """The two keyframes a factor ties; a frame-level factor (no keyframes) ties keyframe 0 of
    both sessions, their frames' origins."""
    fa, fb = factor_frames(factor)
    return KeyframeId(fa, factor.keyframe_a or 0), KeyframeId(fb, factor.keyframe_b or 0)


@dataclass(frozen=True, slots=True)
class OdometryEdge:
    """The vehicle's own motion between two keyframes of its session: T_from_to (pose of
    `to` in `from_`) with its 6x6 covariance (GTSAM order). A known inlier of the pose graph."""

    from_: KeyframeId
    to: KeyframeId
    T_from_to: gtsam.Pose3
    covariance: np.ndarray

    @property
    def edge_id(self) -> str:
        """"odom:{robot}/{session}#{from}-{to}": one edge per keyframe pair."""
        return f"odom:{self.from_}-{self.to.k}"


def odometry_edge(submap: Submap) -> OdometryEdge | None:
    """The odometry edge a keyframe submap carries (None without odometry)."""
    odo = submap.odometry
    if odo is None or submap.keyframe is None:
        return None
    frame = FrameId(submap.robot_id, submap.session_id)
    cov = np.asarray(odo.covariance, dtype=np.float64)
    cov.setflags(write=False)  # held as is by the pose graph (no copy of its own)
    return OdometryEdge(
        KeyframeId(frame, odo.from_keyframe),
        KeyframeId(frame, submap.keyframe),
        pose3_from_model(odo.T_from_to),
        cov,
    )


def factor_frames(factor: Factor) -> tuple[FrameId, FrameId]:
    """The two frames a factor joins: (frame a, frame b)."""
    return FrameId(factor.robot_a, factor.session_a), FrameId(factor.robot_b, factor.session_b)


def is_loop(factor: Factor) -> bool:
    """Whether a factor ties two keyframes of one session (a loop the vehicle closed)."""
    fa, fb = factor_frames(factor)
    return fa == fb


def _result(result: MatchResult | MatchOutcome) -> MatchResult:
    return result if isinstance(result, MatchResult) else result.result


__all__ = [
    "OdometryEdge",
    "anchoring_keyframe",
    "factor_frames",
    "factor_from_match",
    "factor_nodes",
    "inflate_covariance",
    "is_loop",
    "local_fit",
    "match_factor_id",
    "odometry_edge",
    "yields_factor",
]
