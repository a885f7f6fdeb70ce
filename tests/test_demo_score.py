"""The demo's judgement, on hand-made inputs: the lines that say which robot merging made worse
(and when the compact codec's rounding, not the merge, did), the merged path the figure draws,
and the odometry as the service received it scored against the truth's TUM file."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np

from mergesvc.core.trajectory import ate_rmse
from mergesvc.fleet.demo_score import (
    add_received_odometry,
    merged_path,
    robots_worse,
    trajectory_lines,
)
from mergesvc.wire.formats import write_tum


def _row(odo: float, merged: float, odo_deg: float, deg: float, **more: float) -> dict:
    return {"keyframes": 10, "keyframes_merged": 10, "ate_odometry_m": odo,
            "ate_merged_m": merged, "merged_over_odometry": merged / odo,
            "final_pos_err_odometry_m": 0.2, "final_rot_err_odometry_deg": odo_deg,
            "final_pos_err_m": 0.1, "final_rot_err_deg": deg, **more}


def test_the_lines_say_which_robot_got_worse_and_why() -> None:
    summary = {"anchor": "auv1/s0", "trajectory": {"fleet_ate_merged_m": 0.12, "robots": {
        "auv1": _row(0.100, 0.050, 2.0, 2.1),  # better; heading within 0.2 deg
        "auv2": _row(0.066, 0.068, 1.0, 1.6, merged_over_received=1.0),  # the codec's rounding
        "auv3": _row(0.100, 0.120, 0.5, 0.9),  # worse through the merge; heading within 1 deg
    }}}
    assert robots_worse(summary) == ["auv2", "auv3"]
    lines = trajectory_lines(summary)
    by = {r: next(x for x in lines if x.strip().startswith(f"{r}:")) for r in ("auv1", "auv2",
                                                                               "auv3")}
    assert "(0.50x)" in by["auv1"] and "WORSE" not in by["auv1"]
    assert "last keyframe odometry 0.20 m / 2.0 deg -> merged 0.10 m / 2.1 deg" in by["auv1"]
    # 0.066 -> 0.068 m as printed: 2 mm; 1.00x of what the service received
    assert "WORSE than its own odometry, by 3 % or 2 mm; 1.00x the odometry the service " \
           "received: the compact codec's rounding, not the merge" in by["auv2"]
    assert by["auv2"].endswith("; its heading WORSE than the odometry's")
    assert "by 20 % or 20 mm)" in by["auv3"] and "received" not in by["auv3"]
    assert "heading WORSE" not in by["auv3"]
    verdict = [x for x in lines if x.strip().startswith("merging made")]
    assert verdict == ["  merging made 2 robots WORSE than its own odometry: auv2 (1.03x; "
                       "1.00x the odometry the service received: the compact codec's rounding, "
                       "not the merge), auv3 (1.20x)"]
    assert any("fleet ATE" in x and "0.120 m" in x for x in lines)
    summary["trajectory"]["robots"] = {"auv1": _row(0.1, 0.05, 1.0, 0.5)}
    assert "  merging made no robot's trajectory worse than its own odometry" in (
        trajectory_lines(summary))


def _pose(rng: np.random.Generator) -> np.ndarray:
    return gtsam.Pose3.Expmap(rng.normal(0.0, 0.5, 6)).matrix()


def test_the_merged_path_is_each_keyframe_then_its_odometry() -> None:
    rng = np.random.default_rng(3)
    est = [_pose(rng) for _ in range(12)]
    merged = {k: _pose(rng) for k in (2, 5, 9)}
    path = merged_path(merged, est)
    assert path.shape == (8, 3)  # frames 2..9: none before the first keyframe or after the last
    for k in (2, 5, 9):
        np.testing.assert_allclose(path[k - 2], merged[k][:3, 3], atol=1e-12)
    # frame 7 follows keyframe 5 by the odometry's own step from 5 to 7
    step = np.linalg.solve(est[5], est[7])
    np.testing.assert_allclose(path[5], (merged[5] @ step)[:3, 3], atol=1e-12)


def test_the_received_odometry_is_scored_on_the_merged_keyframes(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    stamps = np.arange(20, dtype=float)
    truth = np.stack([_pose(rng) for _ in stamps])
    keys = [0, 3, 7, 12, 19]
    merged = truth[keys] @ np.stack([gtsam.Pose3.Expmap(rng.normal(0, 0.01, 6)).matrix()
                                     for _ in keys])
    received = truth[keys] @ np.stack([gtsam.Pose3.Expmap(rng.normal(0, 0.02, 6)).matrix()
                                       for _ in keys])
    files = {"truth": write_tum(tmp_path / "auv1_truth.tum", stamps, truth),
             "merged": write_tum(tmp_path / "auv1_merged.tum", stamps[keys], merged)}
    (tmp_path / "export" / "trajectories").mkdir(parents=True)
    write_tum(tmp_path / "export" / "trajectories" / "auv1_s0_odometry.tum", stamps[keys],
              received)
    ate_merged = ate_rmse(merged, truth[keys])
    summary = {"trajectory": {"robots": {
        "auv1": {"tum": {k: str(v) for k, v in files.items()}, "ate_merged_m": ate_merged},
        "auv2": {"tum": {}, "ate_merged_m": None}}}}  # placed nowhere: left alone
    add_received_odometry(summary, tmp_path / "export")
    row = summary["trajectory"]["robots"]["auv1"]
    assert abs(row["ate_odometry_received_m"] - ate_rmse(received, truth[keys])) < 1e-5
    assert row["merged_over_received"] == ate_merged / row["ate_odometry_received_m"]
    assert "ate_odometry_received_m" not in summary["trajectory"]["robots"]["auv2"]
