"""The demo's plan (`DemoPlan`: seed, laps, profile, link, its service settings) and its
judgement against the ground truth: correspondences and factors right or wrong,
frame alignment before and after merging, each robot's keyframe trajectory error (odometry
alone and merged, on the same keyframes) and the fleet's in one frame, the lines that say so
(plainly when merging made a robot worse), and the PNG of the merged map.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor
from mergesvc.core.tracking import Frame
from mergesvc.errors import InputError, MergeError
from mergesvc.fleet.config import ServiceConfig, odometry_group
from mergesvc.fleet.local_map import AgentConfig, LocalMap, build_submaps
from mergesvc.fleet.scoring import fleet_ate
from mergesvc.sim import fleet_world
from mergesvc.wire import Profile

ROBOTS = ("auv1", "auv2", "auv3")
SESSION = "s0"  # every vehicle's session in the demo


def _frame(robot: str) -> str:
    """The frame name of a demo vehicle's session."""
    return str(FrameId(robot, SESSION))


@dataclass(frozen=True)
class DemoPlan:
    seed: int = 0
    laps: int = 2
    n_objects: int = 24
    time_scale: float = 0.02  # wall seconds per simulated second
    profile: Profile = Profile.COMPACT
    link: str = "zenoh"  # or "acoustic": through the simulated modem
    timeout_s: float = 120.0
    # the service's Zenoh endpoint, which the vehicles and a live view connect to (None: a
    # free port on 127.0.0.1)
    listen: str | None = None
    # the `service` settings the service process reads (its settings file): the export of its
    # store solves the graph with them (None: the defaults)
    service: ServiceConfig | None = None
    # each vehicle's settings as its process reads them: the score rebuilds the vehicles' maps
    # with them, to know which object each track is (None: the defaults)
    agents: dict[str, AgentConfig] | None = None

    @property
    def fleet(self) -> str:
        """The fleet name the demo's processes use."""
        return f"demo{self.seed}"

    @classmethod
    def quick(cls, **kw: Any) -> DemoPlan:
        return cls(laps=1, time_scale=0.01, timeout_s=60.0, **kw)


def score_demo(plan: DemoPlan, status: dict[str, Any], factors: dict[str, Factor],
               logs: dict[str, Path], out_dir: Path) -> dict[str, Any]:
    """Everything the summary says, against the mission's ground truth."""
    world = fleet_world(plan.seed, ROBOTS, plan.laps, plan.n_objects)
    frames = {r: list(world.frames(r)) for r in ROBOTS}
    local = {r: build_submaps((plan.agents or {}).get(r) or AgentConfig(robot=r), frames[r])[0]
             for r in ROBOTS}

    def truth(robot: str, oid: str) -> str | None:
        try:
            return local[robot].tracker.track(oid).truth_id
        except (KeyError, InputError):  # a robot or an object the replay does not know
            return None

    active = [f for f in factors.values() if f.status is None or f.status.value == "accepted"]
    retracted = {f.factor_id for f in factors.values() if f.status and
                 f.status.value == "retracted"}
    right = wrong = 0
    for f in active:
        if f.factor_id in retracted:
            continue
        for c in f.correspondences:
            ta, tb = truth(f.robot_a, c.object_a), truth(f.robot_b, c.object_b)
            ok = ta is not None and ta == tb
            right += ok
            wrong += not ok
    anchor = status.get("anchor") or _frame(ROBOTS[0])
    a_robot = FrameId.parse(anchor).robot
    poses = {f: np.asarray(T) for f, T in status.get("frame_poses", {}).items()}
    align = {}
    for r in ROBOTS:
        if _frame(r) == anchor:
            continue
        T_true = world.T_rel_true(a_robot, r)
        before = _pose_error(np.eye(4), T_true)
        after = _pose_error(poses[_frame(r)], T_true) if _frame(r) in poses else None
        align[r] = {"before_m": before[0], "before_deg": before[1],
                    "after_m": after[0] if after else None,
                    "after_deg": after[1] if after else None}
    sent = {r: _agent_totals(logs.get(r)) for r in ROBOTS}
    summary = {
        "submaps_sent": sum(s["submaps"] for s in sent.values()),
        "bytes_on_wire": sum(s["bytes"] for s in sent.values()),
        "bytes_per_submap": (sum(s["bytes"] for s in sent.values())
                             / max(sum(s["submaps"] for s in sent.values()), 1)),
        "submaps_processed": status["submaps"]["processed"],
        "factors_accepted": status["factors"]["accepted"],
        "factors_retracted": status["factors"]["retracted"],
        "correspondences_right": right,
        "correspondences_wrong": wrong,
        "precision": right / (right + wrong) if right + wrong else None,
        "alignment": align,
        "anchor": anchor,
        "latency_ms": status["latency_ms"],
    }
    summary["trajectory"] = score_trajectories(world, frames, local, status, anchor, out_dir)
    noise = status.get("noise", {})
    summary["odometry_noise"] = {r: noise[g] for r in ROBOTS if (g := odometry_group(r)) in noise}
    summary["figure"] = str(plot_merged(world, local, poses, anchor, active, out_dir /
                                        "merged_map.png"))
    return summary


def score_trajectories(world: Any, frames: dict[str, list[Frame]],
                       local: dict[str, LocalMap], status: dict[str, Any], anchor: str,
                       out_dir: Path) -> dict[str, dict[str, Any]]:
    """Per robot: the ATE of its keyframe trajectory from odometry alone and as the service
    merged it (on the same keyframes: those the service placed; `ate_odometry_all_m` on every
    keyframe), and the error of the last merged keyframe pose, against the truth; and the
    fleet ATE (every robot's merged keyframes under one alignment).

    Keyframes are frame indices (keyframe k: frame k, true pose T_true, odometry pose T_est).
    The odometry-only trajectory is T_est at keyframe 0 and at every keyframe the vehicle cut
    a submap at (replayed with the default agent settings, as the rest of the scoring is).
    The merged one is the service's `keyframe_poses` of the robot's session (in the anchor
    frame; only keyframes in the anchor's component). Both are aligned to the truth by the
    SE(3) Umeyama transform of their positions (evo's `--align`): the ATE measures the
    trajectory's shape, not where its frame sits (that is `alignment`). `final_*`: the last
    keyframe's error after that alignment (final_rot_err_odometry_deg: the same for the
    odometry-only trajectory). A robot without at least 3 merged keyframes (not connected to
    the anchor, or a service without keyframe poses) gets null merged values.

    Writes TUM files into out_dir/trajectories: {robot}_odometry.tum (own session frame),
    {robot}_merged.tum (anchor frame) and {robot}_truth.tum (all frames, in the anchor's
    true session frame), for evo_ape."""
    from mergesvc.core.trajectory import ate_rmse, final_pose_error
    from mergesvc.wire.formats import write_tum

    T_anchor_world = np.linalg.inv(world.session_start(FrameId.parse(anchor).robot))
    merged_all = status.get("keyframe_poses") or {}
    fleet_poses: dict[str, dict[int, np.ndarray]] = {}
    truths: dict[str, np.ndarray] = {}
    tum_dir = out_dir / "trajectories"
    tum_dir.mkdir(parents=True, exist_ok=True)
    out: dict[str, dict[str, Any]] = {}
    for r in ROBOTS:
        fr = frames[r]
        stamps = np.array([f.stamp_s for f in fr])
        truth = np.stack([T_anchor_world @ f.T_true for f in fr])
        keys_odo = sorted({0, *local[r].keyframes})
        odo = np.stack([fr[k].T_est for k in keys_odo])
        merged_raw = merged_all.get(_frame(r)) or {}
        keys_m = sorted(int(k) for k in merged_raw if 0 <= int(k) < len(fr))
        merged = (np.stack([np.asarray(merged_raw[str(k)], dtype=np.float64) for k in keys_m])
                  if keys_m else np.zeros((0, 4, 4)))
        fleet_poses[r] = dict(zip(keys_m, merged, strict=True))
        truths[r] = truth
        row: dict[str, Any] = {"keyframes": len(keys_odo), "keyframes_merged": len(keys_m),
                               "ate_odometry_m": None, "ate_odometry_all_m": None,
                               "ate_merged_m": None, "merged_over_odometry": None,
                               "final_rot_err_odometry_deg": None,
                               "final_pos_err_m": None, "final_rot_err_deg": None}
        same = keys_m or keys_odo  # odometry scored on the keyframes the service placed
        odo_same = np.stack([fr[k].T_est for k in same])
        with contextlib.suppress(MergeError):  # too few or collinear keyframes: null
            row["ate_odometry_all_m"] = ate_rmse(odo, truth[keys_odo])
        with contextlib.suppress(MergeError):
            row["ate_odometry_m"] = ate_rmse(odo_same, truth[same])
            row["final_rot_err_odometry_deg"] = final_pose_error(odo_same, truth[same])[1]
        with contextlib.suppress(MergeError):
            row["ate_merged_m"] = ate_rmse(merged, truth[keys_m])
            m, deg = final_pose_error(merged, truth[keys_m])
            row["final_pos_err_m"], row["final_rot_err_deg"] = m, deg
        tum = {"odometry": write_tum(tum_dir / f"{r}_odometry.tum", stamps[keys_odo], odo),
               "truth": write_tum(tum_dir / f"{r}_truth.tum", stamps, truth)}
        if keys_m:
            tum["merged"] = write_tum(tum_dir / f"{r}_merged.tum", stamps[keys_m], merged)
        row["tum"] = {k: str(v) for k, v in tum.items()}
        if row["ate_merged_m"] is not None and row["ate_odometry_m"]:
            row["merged_over_odometry"] = row["ate_merged_m"] / row["ate_odometry_m"]
        out[r] = row
    return {"robots": out, "fleet_ate_merged_m": fleet_ate(fleet_poses, truths)}


# merged / odometry ATE above which the demo says a robot got worse: above 1.00 as printed (a
# robot kept to its odometry's shape differs from it by the solve's tolerance and the compact
# codec's rounding of its odometry, which can show as 1.01-1.03x and is said)
WORSE_ABOVE = 1.005


def trajectory_lines(summary: dict[str, Any]) -> list[str]:
    """The summary's trajectory scores for the demo's output: per robot its keyframe ATE from
    odometry alone and merged (the same keyframes), saying plainly when merging made it worse;
    then the fleet ATE in the one common frame, and each robot's odometry noise as the service
    calibrated it (with each scale's standard error)."""

    def num(x: float | None, unit: str, digits: int = 3) -> str:
        return "n/a" if x is None else f"{x:.{digits}f} {unit}"

    traj = summary.get("trajectory", {})
    lines = []
    for r, t in traj.get("robots", {}).items():
        ratio = t.get("merged_over_odometry")
        verdict = ("" if ratio is None else
                   f" ({ratio:.2f}x: WORSE than its own odometry)" if ratio > WORSE_ABOVE else
                   f" ({ratio:.2f}x)")
        lines.append(
            f"  {r}: keyframe ATE odometry {num(t['ate_odometry_m'], 'm')} -> merged "
            f"{num(t['ate_merged_m'], 'm')}{verdict}, {t['keyframes_merged']} of "
            f"{t['keyframes']} keyframes; last keyframe merged "
            f"{num(t['final_pos_err_m'], 'm', 2)} / {num(t['final_rot_err_deg'], 'deg', 1)} "
            f"(odometry {num(t['final_rot_err_odometry_deg'], 'deg', 1)})")
    if "fleet_ate_merged_m" in traj:
        lines.append(f"  fleet ATE, every robot in the anchor frame under one alignment: "
                     f"{num(traj['fleet_ate_merged_m'], 'm')}")
    noise = summary.get("odometry_noise") or {}
    if noise:
        lines.append("  odometry noise as the service calibrated it, sigma / declared (rotation "
                     "x y z | translation x y z; +- the standard error its residuals give: "
                     "where large, the graph barely checks the axis and the declared sigma "
                     "holds):")
    for r, n in noise.items():
        s, se = n["sigma_scale"], n.get("relative_se") or [None] * 6
        pm = ["?" if e is None else f"{100 * e:.0f}" for e in se]
        lines.append(f"    {r}: {' '.join(f'{x:.2f}' for x in s[:3])} | "
                     f"{' '.join(f'{x:.2f}' for x in s[3:])}  (+- {' '.join(pm[:3])} | "
                     f"{' '.join(pm[3:])} %)")
    return lines


def _agent_totals(path: Path | None) -> dict[str, int]:
    """The agent prints one JSON line of totals when it ends."""
    out = {"submaps": 0, "bytes": 0}
    if path is None or not path.exists():
        return out
    for line in path.read_text().splitlines():
        if line.startswith("{") and '"submaps_sent"' in line:
            d = json.loads(line)
            out = {"submaps": d["submaps_sent"], "bytes": d["bytes_sent"]}
    return out


def _pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d = np.linalg.inv(T_true) @ T_est
    ang = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(ang)


def plot_merged(world: Any, local: dict[str, Any], poses: dict[str, np.ndarray], anchor: str,
                factors: list[Factor], path: Path) -> Path:
    """Each robot's trajectory and objects in the anchor frame (as the service aligned them),
    the factors' correspondences drawn (between robots, and a robot's loops); every kind of
    mark in the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5), dpi=110)
    colors = {"auv1": "tab:blue", "auv2": "tab:orange", "auv3": "tab:green"}
    a_robot = FrameId.parse(anchor).robot
    T_aw = np.linalg.inv(world.robot(a_robot).T_world_start)
    obj = (world.objects_xyz_m @ T_aw[:3, :3].T + T_aw[:3, 3])[:, :2]
    ax.scatter(*obj.T, marker="x", c="0.6", s=30, label="true objects (anchor frame)")
    placed: dict[tuple[str, str], np.ndarray] = {}
    for r, lm in local.items():
        T = poses.get(_frame(r))
        if T is None:
            continue
        xy = np.array([T[:3, :3] @ p + T[:3, 3] for p in
                       (t.position_xyz_m for t in lm.tracker.tracks)])
        for t, p in zip(lm.tracker.tracks, xy):
            placed[(r, t.track_id)] = p
        ax.scatter(*xy[:, :2].T, s=12, color=colors.get(r, "k"), label=f"{r} objects")
        traj = np.array(lm.path_xyz_m)
        traj = traj @ T[:3, :3].T + T[:3, 3]
        ax.plot(*traj[:, :2].T, lw=0.7, color=colors.get(r, "k"), alpha=0.6,
                label=f"{r} trajectory (its odometry, placed by the merge)")
    for f in factors:
        for c in f.correspondences:
            a, b = placed.get((f.robot_a, c.object_a)), placed.get((f.robot_b, c.object_b))
            if a is not None and b is not None:
                ax.plot([a[0], b[0]], [a[1], b[1]], color="k", lw=0.6, alpha=0.5)
    ax.plot([], [], color="k", lw=0.6, label="correspondences (between robots; loops)")
    ax.set_aspect("equal")
    ax.set_title(f"merged map in {anchor}'s frame")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


__all__ = ["ROBOTS", "SESSION", "DemoPlan", "plot_merged", "score_demo", "score_trajectories",
           "trajectory_lines"]
