"""Match result -> inter-robot factor: what the service sends for an accepted match.

A match of submap b (robot b's session frame) against the objects of frame a gives T_a_b (the
result's T_map_submap) and its 6x6 covariance, in GTSAM's Pose3 tangent order: rotation (rad),
then translation (m). The factor carries that transform with the covariance inflated by the
odometry drift (`inflate_covariance`), and the matched object pairs.

Pure computation: no Zenoh, no files.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from mergesvc.core.frames import FrameId
from mergesvc.core.model import Correspondence, Factor, FactorStatus, MatchResult
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


def match_factor_id(frame_a: FrameId, frame_b: FrameId, seq: int) -> str:
    """The id of the factor from submap `seq` of frame_b matched against frame_a:
    "{robot_a}.{session_a}-{robot_b}.{session_b}-{seq}". Deterministic, so a replay of the
    same submap gives the same id (the store keeps the factor once)."""
    return f"{frame_a.robot}.{frame_a.session}-{frame_b.robot}.{frame_b.session}-{seq}"


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
) -> Factor:
    """The factor T_a_b between frame_a (the map matched against) and frame_b (the submap's),
    its covariance the result's inflated by `drift_sigma`, its correspondences the matched
    pairs (object_a the map object, object_b the submap object).

    A result that does not `yields_factor` (rejected, or without transform or covariance) is
    refused with `InputError`. A factor that does not validate (e.g. an id longer than the
    model allows) raises pydantic's ValidationError, as the model does."""
    res = _result(result)
    transform, covariance = res.transform, res.covariance
    if not res.accepted or transform is None or covariance is None:
        raise InputError(
            "only an accepted match with a transform and a covariance becomes a factor "
            f"(this one: {res.reason.value})"
        )
    cov = inflate_covariance(covariance, drift_sigma)
    return Factor(
        factor_id=factor_id,
        robot_a=frame_a.robot, session_a=frame_a.session,
        robot_b=frame_b.robot, session_b=frame_b.session,
        T_a_b=transform, covariance=cov.tolist(),
        correspondences=[Correspondence(object_a=m.map_object, object_b=m.submap_object,
                                        score=m.score) for m in res.matches],
        status=status,
    )


def factor_frames(factor: Factor) -> tuple[FrameId, FrameId]:
    """The two frames a factor joins: (frame a, frame b)."""
    return FrameId(factor.robot_a, factor.session_a), FrameId(factor.robot_b, factor.session_b)


def _result(result: MatchResult | MatchOutcome) -> MatchResult:
    return result if isinstance(result, MatchResult) else result.result


__all__ = [
    "factor_frames",
    "factor_from_match",
    "inflate_covariance",
    "match_factor_id",
    "yields_factor",
]
