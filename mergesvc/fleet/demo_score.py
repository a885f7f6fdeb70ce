"""The demo's plan (`DemoPlan`: seed, laps, profile, link, its service settings) and its
judgement against the ground truth: correspondences and factors right or wrong,
frame alignment before and after merging, each robot's keyframe trajectory error (odometry
alone and merged, on the same keyframes) and the fleet's in one frame, the lines that say so
(plainly when merging made a robot worse), and the PNG of the merged map.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Sequence
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
    placed = placed_trajectories(world, frames, status, anchor)
    summary["trajectory"] = score_trajectories(frames, local, placed, out_dir)
    noise = status.get("noise", {})
    summary["odometry_noise"] = {r: noise[g] for r in ROBOTS if (g := odometry_group(r)) in noise}
    summary["robots_worse"] = robots_worse(summary)
    summary["figure"] = str(plot_merged(
        world, local, poses, anchor, active, out_dir / "merged_map.png",
        placed, summary["trajectory"], frames))
    return summary


def placed_trajectories(world: Any, frames: dict[str, list[Frame]], status: dict[str, Any],
                        anchor: str) -> tuple[dict[str, np.ndarray], dict[str, dict[int, Any]]]:
    """Per robot, in the anchor's frame: its true poses at every frame ((n, 4, 4), from the
    anchor session's true start) and its keyframe poses as the service merged them ({frame
    index: (4, 4)}; empty when the service placed none)."""
    T_anchor_world = np.linalg.inv(world.session_start(FrameId.parse(anchor).robot))
    merged_all = status.get("keyframe_poses") or {}
    truths, merged = {}, {}
    for r in ROBOTS:
        truths[r] = np.stack([T_anchor_world @ f.T_true for f in frames[r]])
        raw = merged_all.get(_frame(r)) or {}
        merged[r] = {int(k): np.asarray(T, dtype=np.float64) for k, T in raw.items()
                     if 0 <= int(k) < len(frames[r])}
    return truths, merged


def score_trajectories(frames: dict[str, list[Frame]], local: dict[str, LocalMap],
                       placed: tuple[dict[str, np.ndarray], dict[str, dict[int, Any]]],
                       out_dir: Path) -> dict[str, dict[str, Any]]:
    """Per robot: the ATE of its keyframe trajectory from odometry alone and as the service
    merged it (on the same keyframes: those the service placed; `ate_odometry_all_m` on every
    keyframe), and the error of the last merged keyframe pose, against the truth; and the
    fleet ATE (every robot's merged keyframes under one alignment).

    Keyframes are frame indices (keyframe k: frame k, true pose T_true, odometry pose T_est).
    The odometry-only trajectory is T_est at keyframe 0 and at every keyframe the vehicle cut
    a submap at (replayed with the default agent settings, as the rest of the scoring is).
    The merged one is the service's `keyframe_poses` of the robot's session (in the anchor
    frame; only keyframes in the anchor's component): `placed`, `placed_trajectories`' truths
    and merged keyframes. Both are aligned to the truth by the
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

    truths, fleet_poses = placed
    tum_dir = out_dir / "trajectories"
    tum_dir.mkdir(parents=True, exist_ok=True)
    out: dict[str, dict[str, Any]] = {}
    for r in ROBOTS:
        fr, truth = frames[r], truths[r]
        stamps = np.array([f.stamp_s for f in fr])
        keys_odo = sorted({0, *local[r].keyframes})
        odo = np.stack([fr[k].T_est for k in keys_odo])
        keys_m = sorted(fleet_poses[r])
        merged = (np.stack([fleet_poses[r][k] for k in keys_m]) if keys_m
                  else np.zeros((0, 4, 4)))
        row: dict[str, Any] = {"keyframes": len(keys_odo), "keyframes_merged": len(keys_m),
                               "ate_odometry_m": None, "ate_odometry_all_m": None,
                               "ate_merged_m": None, "merged_over_odometry": None,
                               "final_pos_err_odometry_m": None,
                               "final_rot_err_odometry_deg": None,
                               "final_pos_err_m": None, "final_rot_err_deg": None}
        same = keys_m or keys_odo  # odometry scored on the keyframes the service placed
        odo_same = np.stack([fr[k].T_est for k in same])
        with contextlib.suppress(MergeError):  # too few or collinear keyframes: null
            row["ate_odometry_all_m"] = ate_rmse(odo, truth[keys_odo])
        with contextlib.suppress(MergeError):
            row["ate_odometry_m"] = ate_rmse(odo_same, truth[same])
            row["final_pos_err_odometry_m"], row["final_rot_err_odometry_deg"] = (
                final_pose_error(odo_same, truth[same]))
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
    fleet = fleet_ate(fleet_poses, truths)
    return {"robots": out, "fleet_ate_merged_m": fleet if np.isfinite(fleet) else None}


# merged / odometry ATE above which the demo says a robot got worse: above 1.00 as printed (a
# robot kept to its odometry's shape differs from it by the solve's tolerance and the compact
# codec's rounding of its odometry, which can show as 1.01-1.03x and is said)
WORSE_ABOVE = 1.005
# the last keyframe's heading error is said to be worse than the odometry's above the larger of
# HEADING_ALLOWED_DEG and the odometry's own (a degree of heading is within what the factors
# can tell) by more than HEADING_MARGIN_DEG (a single pose's heading: 0.1 deg is its noise)
HEADING_ALLOWED_DEG = 1.0
HEADING_MARGIN_DEG = 0.2


def robots_worse(summary: dict[str, Any]) -> list[str]:
    """The robots whose merged keyframe ATE is above their odometry's (`WORSE_ABOVE`)."""
    robots = summary.get("trajectory", {}).get("robots", {})
    return [r for r, t in robots.items()
            if (t.get("merged_over_odometry") or 0.0) > WORSE_ABOVE]


def add_received_odometry(summary: dict[str, Any], export_dir: Path) -> None:
    """Each robot's odometry as the service received it (the export's
    {robot}_s0_odometry.tum: the compact codec rounds it), scored as `ate_odometry_m` is (on
    the merged keyframes, against the truth's TUM file score_trajectories wrote):
    `ate_odometry_received_m` and `merged_over_received`; left out for a robot whose files are
    missing or do not fix an alignment."""
    from mergesvc.core.trajectory import ate_rmse
    from mergesvc.wire.formats import read_tum

    for r, t in summary.get("trajectory", {}).get("robots", {}).items():
        tum = t.get("tum") or {}
        received = export_dir / "trajectories" / f"{_frame(r).replace('/', '_')}_odometry.tum"
        if "merged" not in tum or not received.is_file():
            continue
        with contextlib.suppress(MergeError):  # DecodeError among them
            stamps_t, truth = read_tum(tum["truth"])
            stamps_m, _ = read_tum(tum["merged"])
            stamps_o, odo = read_tum(received)
            at = {round(float(x), 6): i for i, x in enumerate(stamps_o)}
            idx = [at.get(round(float(x), 6)) for x in stamps_m]
            if any(i is None for i in idx):
                continue
            ref = truth[np.searchsorted(stamps_t, stamps_m)]
            t["ate_odometry_received_m"] = ate_rmse(odo[idx], ref)
            if t.get("ate_merged_m") is not None and t["ate_odometry_received_m"] > 0:
                t["merged_over_received"] = t["ate_merged_m"] / t["ate_odometry_received_m"]


def trajectory_lines(summary: dict[str, Any]) -> list[str]:
    """The summary's trajectory scores for the demo's output: per robot its keyframe ATE from
    odometry alone and merged (the same keyframes), saying plainly when merging made it worse,
    and its last keyframe's error both ways; the fleet ATE in the one common frame; which
    robots got worse; each robot's odometry noise as the service calibrated it (with each
    scale's standard error)."""

    def num(x: float | None, unit: str, digits: int = 3) -> str:
        return "n/a" if x is None else f"{x:.{digits}f} {unit}"

    traj = summary.get("trajectory", {})
    lines = []
    if summary.get("anchor"):
        lines.append(f"  merged map in {summary['anchor']}'s frame (the anchor: the session "
                     f"of the first submap the service merged); errors against the truth:")
    for r, t in traj.get("robots", {}).items():
        ratio = t.get("merged_over_odometry")
        verdict = "" if ratio is None else f" ({ratio:.2f}x)"
        if ratio is not None and ratio > WORSE_ABOVE:
            mm = 1e3 * (round(t["ate_merged_m"], 3) - round(t["ate_odometry_m"], 3))
            verdict = (f" ({ratio:.2f}x: WORSE than its own odometry, by "
                       f"{100 * (ratio - 1):.0f} % or {mm:.0f} mm{_received_note(t)})")
        odo_deg, deg = t.get("final_rot_err_odometry_deg"), t.get("final_rot_err_deg")
        heading = ("; its heading WORSE than the odometry's" if odo_deg is not None and
                   deg is not None and
                   deg > max(HEADING_ALLOWED_DEG, odo_deg) + HEADING_MARGIN_DEG else "")
        lines.append(
            f"  {r}: keyframe ATE odometry {num(t['ate_odometry_m'], 'm')} -> merged "
            f"{num(t['ate_merged_m'], 'm')}{verdict}, {t['keyframes_merged']} of "
            f"{t['keyframes']} keyframes; last keyframe odometry "
            f"{num(t.get('final_pos_err_odometry_m'), 'm', 2)} / {num(odo_deg, 'deg', 1)} -> "
            f"merged {num(t['final_pos_err_m'], 'm', 2)} / {num(deg, 'deg', 1)}{heading}")
    if "fleet_ate_merged_m" in traj:
        lines.append(f"  fleet ATE, every robot in the anchor frame under one alignment: "
                     f"{num(traj['fleet_ate_merged_m'], 'm')} (odometry alone has no common "
                     f"frame)")
    if traj.get("robots"):
        worse = robots_worse(summary)
        lines.append("  merging made no robot's trajectory worse than its own odometry" if not
                     worse else f"  merging made {len(worse)} "
                     f"{'robot' if len(worse) == 1 else 'robots'} WORSE than its own "
                     f"odometry: " + ", ".join(
                         f"{r} ({traj['robots'][r]['merged_over_odometry']:.2f}x"
                         f"{_received_note(traj['robots'][r])})" for r in worse))
    noise = summary.get("odometry_noise") or {}
    if noise:
        lines.append("  odometry noise as the service calibrated it, sigma / declared, "
                     "rotation x y z | translation x y z (+- its standard error: where large, "
                     "the declared sigma holds):")
    for r, n in noise.items():
        s, se = n["sigma_scale"], n.get("relative_se") or [None] * 6
        pm = ["?" if e is None else f"{100 * e:.0f}" for e in se]
        lines.append(f"    {r}: {' '.join(f'{x:.2f}' for x in s[:3])} | "
                     f"{' '.join(f'{x:.2f}' for x in s[3:])}  (+- {' '.join(pm[:3])} | "
                     f"{' '.join(pm[3:])} %)")
    return lines


def _received_note(t: dict[str, Any]) -> str:
    """What a robot's merged trajectory is against its odometry as the service received it,
    when that explains a loss: the compact codec's rounding, not the merge."""
    received = t.get("merged_over_received")
    if received is None or received > WORSE_ABOVE:
        return ""
    return (f"; {received:.2f}x the odometry the service received: the compact codec's "
            f"rounding, not the merge")


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


def merged_path(merged: dict[int, np.ndarray], est: Sequence[np.ndarray]) -> np.ndarray:
    """(n, 3) positions of a robot's merged trajectory at every frame from its first merged
    keyframe to its last: frame j after keyframe k is merged[k] inv(est[k]) est[j] (its
    odometry from the last keyframe before it), so frame k itself is merged[k]; frames after
    the last keyframe were never sent and are left out."""
    keys = sorted(merged)
    return np.array([(merged[k] @ np.linalg.solve(est[k], est[j]))[:3, 3]
                     for k, nxt in zip(keys, [*keys[1:], keys[-1] + 1]) for j in range(k, nxt)])


def plot_merged(world: Any, local: dict[str, Any], poses: dict[str, np.ndarray], anchor: str,
                factors: list[Factor], path: Path,
                placed: tuple[dict[str, np.ndarray], dict[str, dict[int, Any]]],
                trajectory: dict[str, Any], frames: dict[str, list[Frame]]) -> Path:
    """Left, the fleet in the anchor's frame: each robot's trajectory as the service merged it
    (`placed`: truths and merged keyframes, `placed_trajectories`; between keyframes, from
    `frames`, the odometry from the last one: a jump where the merge corrected it) over its
    true path (dashed), its objects placed by the merge, the true objects and the factors'
    correspondences. Right, each robot's keyframe ATE from odometry alone and merged, and the
    fleet's (`trajectory`: score_trajectories' result). Every kind of mark in a legend that
    covers no data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 6.5), dpi=110, layout="constrained",
                                 gridspec_kw={"width_ratios": [3, 1]})
    colors = {"auv1": "tab:blue", "auv2": "tab:orange", "auv3": "tab:green"}
    a_robot = FrameId.parse(anchor).robot
    T_aw = np.linalg.inv(world.robot(a_robot).T_world_start)
    obj = (world.objects_xyz_m @ T_aw[:3, :3].T + T_aw[:3, 3])[:, :2]
    ax.scatter(*obj.T, marker="x", c="0.5", s=30, label="true objects")
    truths, merged = placed
    spots: dict[tuple[str, str], np.ndarray] = {}
    for r, lm in local.items():
        c = colors.get(r, "k")
        ax.plot(*truths[r][:, :2, 3].T, lw=0.8, ls="--", color=c, alpha=0.45,
                label=f"{r} true path")
        keys = sorted(merged[r])
        if keys:
            xy = merged_path(merged[r], [f.T_est for f in frames[r]])[:, :2]
            ax.plot(*xy.T, lw=1.1, color=c, label=f"{r} merged (keyframes + odometry)")
            kf = np.array([merged[r][k][:2, 3] for k in keys])
            ax.scatter(*kf.T, s=14, color=c, marker="o", edgecolors="k", linewidths=0.4)
        T = poses.get(_frame(r))
        if T is None:
            continue
        pts = np.array([T[:3, :3] @ t.position_xyz_m + T[:3, 3] for t in lm.tracker.tracks])
        for t, q in zip(lm.tracker.tracks, pts):
            spots[(r, t.track_id)] = q
        ax.scatter(*pts[:, :2].T, s=10, color=c, alpha=0.7,
                   label=f"{r} objects (its map, placed by the merge)")
    for f in factors:
        for corr in f.correspondences:
            a, b = spots.get((f.robot_a, corr.object_a)), spots.get((f.robot_b, corr.object_b))
            if a is not None and b is not None:
                ax.plot([a[0], b[0]], [a[1], b[1]], color="k", lw=0.6, alpha=0.5)
    ax.plot([], [], color="k", lw=0.6, label="correspondences of the factors")
    ax.set_aspect("equal")
    ax.set_title(f"The fleet in one frame: {a_robot}'s start (the anchor)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")

    rows = trajectory.get("robots", {})
    names = [r for r in rows if rows[r].get("ate_odometry_m") is not None]
    x = np.arange(len(names))
    odo = [rows[r]["ate_odometry_m"] for r in names]
    mrg = [rows[r]["ate_merged_m"] or 0.0 for r in names]
    bx.bar(x - 0.2, odo, 0.4, color="0.7", label="odometry alone")
    bx.bar(x + 0.2, mrg, 0.4, color=[colors.get(r, "k") for r in names],
           label="merged (ratio above)")
    for i, r in enumerate(names):
        ratio = rows[r].get("merged_over_odometry")
        bx.annotate("not placed" if rows[r]["ate_merged_m"] is None else
                    f"{ratio:.2f}x" if ratio is not None else "", (x[i] + 0.2, mrg[i]),
                    ha="center", va="bottom", fontsize=8, rotation=90 if ratio is None else 0)
    ticks = list(names)
    if (fleet := trajectory.get("fleet_ate_merged_m")) is not None:
        bx.bar(len(names), fleet, 0.4, color="k", label="fleet, one alignment")
        ticks.append("fleet")
    bx.set_xticks(np.arange(len(ticks)), ticks)
    bx.set_ylabel("keyframe ATE [m]")
    bx.set_title("Keyframe ATE per robot")
    handles, labels = ax.get_legend_handles_labels()
    more = bx.get_legend_handles_labels()
    fig.legend(handles + more[0], labels + more[1], loc="outside lower center", ncol=4,
               fontsize=7)
    fig.savefig(path)
    plt.close(fig)
    return path


__all__ = ["ROBOTS", "SESSION", "DemoPlan", "add_received_odometry", "merged_path",
           "placed_trajectories", "plot_merged", "robots_worse", "score_demo",
           "score_trajectories", "trajectory_lines"]
