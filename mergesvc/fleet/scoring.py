"""A replayed fleet scored against its truth, as a user of the merged map would judge it:
  - the fleet ATE: every robot's merged keyframes in the one common frame, one alignment for
    them all (what a user of a merged map needs; odometry alone has no common frame);
  - the "align once" baseline: each robot's odometry placed in the common frame once, by one
    early inter-robot factor, and never again: the first one, and the best of the first few
    (chosen with the truth: a generous baseline);
  - how honest the covariances are (core/whitened.py) for odometry edges and factors;
  - which wrong correspondences an agent's tracker caused (a track that took detections of
    two objects, matched as the one it holds fewer of).
Pure computation on arrays the replay collects; the truth is used to score only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mergesvc.core.model import Factor
from mergesvc.core.poses import pose3_from_model
from mergesvc.core.trajectory import ate_rmse
from mergesvc.core.whitened import tangent_error, whitened_stats
from mergesvc.errors import MergeError

ALIGN_ONCE_CANDIDATES = 5  # the first factors of a robot the "best" one-shot alignment tries


@dataclass(frozen=True)
class OdometryEdgeRecord:
    """An odometry edge as the service held it: keyframes, T_from_to (4, 4), the covariance
    declared on the wire and the one the graph solved with (calibrated)."""

    from_k: int
    to_k: int
    T_from_to: np.ndarray
    declared: np.ndarray
    solved: np.ndarray


def fleet_ate(poses: Mapping[str, Mapping[int, np.ndarray]],
              truth: Mapping[str, np.ndarray]) -> float:
    """ATE (m) of every robot's keyframe poses {robot: {k: (4, 4)}} in one frame against the
    truth {robot: (n, 4, 4)} in one frame, under one rigid alignment for all; NaN when they
    fix none."""
    est, ref = [], []
    for r, kf in poses.items():
        for k, T in kf.items():
            if r in truth and 0 <= k < len(truth[r]):
                est.append(np.asarray(T, dtype=np.float64))
                ref.append(truth[r][k])
    try:
        return ate_rmse(np.stack(est), np.stack(ref)) if est else float("nan")
    except MergeError:
        return float("nan")


def align_once(factors: Sequence[Factor], odometry: Mapping[str, np.ndarray],
               keyframes: Mapping[str, Sequence[int]], truth: Mapping[str, np.ndarray],
               anchor: str) -> dict[str, float]:
    """Fleet ATE of the "align once" baseline (module docstring): robots placed one after the
    other, each by one factor to a robot already placed; `first`: its first such factor,
    `best`: of its first ALIGN_ONCE_CANDIDATES, the one that puts it nearest its truth.
    odometry: {robot: (n, 4, 4) odometry poses}; keyframes: those to score per robot."""
    out = {}
    for pick in ("first", "best"):
        placed = {anchor: np.eye(4)}
        progress = True
        while progress:
            progress = False
            for r in odometry:
                if r in placed:
                    continue
                cands = [P for f in factors if (P := _placement(f, r, placed, odometry))
                         is not None][:ALIGN_ONCE_CANDIDATES]
                if not cands:
                    continue
                placed[r] = cands[0] if pick == "first" else min(
                    cands, key=lambda P, r=r: _placement_error(P, r, odometry, keyframes,
                                                               truth))
                progress = True
        poses = {r: {k: P @ odometry[r][k] for k in keyframes.get(r, ())
                     if k < len(odometry[r])} for r, P in placed.items()}
        out[pick] = fleet_ate(poses, truth)
    return out


def _placement(f: Factor, r: str, placed: Mapping[str, np.ndarray],
               odometry: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """Robot r's odometry frame in the common frame by factor f to a placed robot, or None."""
    T = _matrix(f)
    ka, kb = f.keyframe_a or 0, f.keyframe_b or 0
    if f.robot_b == r and f.robot_a in placed:
        other, k_other, k_me, T_other_me = f.robot_a, ka, kb, T
    elif f.robot_a == r and f.robot_b in placed:
        other, k_other, k_me, T_other_me = f.robot_b, kb, ka, np.linalg.inv(T)
    else:
        return None
    O_o, O_m = odometry[other], odometry[r]
    if k_other >= len(O_o) or k_me >= len(O_m):
        return None
    return placed[other] @ O_o[k_other] @ T_other_me @ np.linalg.inv(O_m[k_me])


def _placement_error(P: np.ndarray, r: str, odometry: Mapping[str, np.ndarray],
                     keyframes: Mapping[str, Sequence[int]],
                     truth: Mapping[str, np.ndarray]) -> float:
    ks = [k for k in keyframes.get(r, ()) if k < len(odometry[r]) and k < len(truth[r])]
    if not ks:
        return float("inf")
    d = [(P @ odometry[r][k])[:3, 3] - truth[r][k][:3, 3] for k in ks]
    return float(np.sqrt(np.mean(np.square(d))))


def odometry_honesty(edges: Sequence[OdometryEdgeRecord], truth: np.ndarray
                     ) -> dict[str, Any]:
    """whitened_stats of a robot's odometry edges against its truth (n, 4, 4), with the
    covariance the graph solved with and (`declared_`) the one the robot sent."""
    rows = [e for e in edges if e.to_k < len(truth)]
    err = [tangent_error(e.T_from_to, np.linalg.solve(truth[e.from_k], truth[e.to_k]))
           for e in rows]
    solved = whitened_stats(err, [e.solved for e in rows])
    declared = whitened_stats(err, [e.declared for e in rows])
    return {**solved, "declared_whitened_rms": declared["whitened_rms"],
            "declared_over_99_percent": declared["over_99_percent"]}


def wrong_on_merged_tracks(pairs: Sequence[tuple[str | None, str | None]],
                           counts_a: Sequence[Mapping[str, int]],
                           counts_b: Sequence[Mapping[str, int]]) -> int:
    """Of the correspondences (truth of a's object, truth of b's), per pair the truth counts of
    the two tracks' detections: the wrong ones (truths differ, both known) where one side's
    track also took detections of the other side's object."""
    return sum(a is not None and b is not None and a != b and (b in ca or a in cb)
               for (a, b), ca, cb in zip(pairs, counts_a, counts_b, strict=True))


def _matrix(f: Factor) -> np.ndarray:
    return np.asarray(pose3_from_model(f.T_a_b).matrix(), dtype=np.float64)


__all__ = ["ALIGN_ONCE_CANDIDATES", "OdometryEdgeRecord", "align_once", "fleet_ate",
           "odometry_honesty", "wrong_on_merged_tracks"]
