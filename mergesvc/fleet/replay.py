"""A fleet replayed in-process, scored against its ground truth: each vehicle's frames through
its LocalMap (`build_submaps`), the submaps into a MergeService without Zenoh (session None,
store ':memory:', `ingest` in the calling thread), delivered in time order or through the
simulated acoustic link (late, out of order, lost), then every number `bench merge` reports.

This is the driver of `mergesvc bench merge`: it lives in fleet (it runs the service and the
agents' maps), bench/merge.py only plans, aggregates and tabulates (bench may not import
fleet); cli/bench.py hands `replay_world` to `run_merge_bench`.

A world is anything with `robots` (each with `.name`), `frames(name)`, `session_start(name)`
(true world pose of the vehicle's odometry frame), `objects_xyz_m` and `object_ids`:
sim.fleet.FleetWorld and sim.drive_fleet.DriveFleet.
"""

from __future__ import annotations

import contextlib
import logging
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from mergesvc.core.calibration import scale_covariance
from mergesvc.core.frames import FrameId
from mergesvc.core.model import Factor, Submap
from mergesvc.core.trajectory import ate_rmse, final_pose_error, rotation_error_deg
from mergesvc.core.whitened import lag1_correlation, whitened_stats
from mergesvc.errors import MergeError
from mergesvc.fleet.bound import BOUND_DRAWS, closure_bound
from mergesvc.fleet.bound import error_sigma as bound_error_sigma
from mergesvc.fleet.config import ServiceConfig, odometry_group
from mergesvc.fleet.local_map import AgentConfig, L, LocalMap, build_submaps
from mergesvc.fleet.scoring import (
    OdometryEdgeRecord,
    align_once,
    fleet_ate,
    odometry_honesty,
    wrong_on_merged_tracks,
)
from mergesvc.fleet.service import MergeService
from mergesvc.link.config import LinkConfig
from mergesvc.link.simulator import Delivery, LinkSimulator
from mergesvc.wire import Profile, Projection, decode_message, encode_message

log = logging.getLogger(__name__)

SESSION = "s0"
TOPSIDE = "topside"


@dataclass(frozen=True)
class FactorTolerance:
    """A factor is correct when its transform is within these of the truth relative pose."""

    metres: float = 1.0
    degrees: float = 5.0


def _deliver_in_order(subs: list[Submap]) -> tuple[list[Submap], dict[str, Any]]:
    order = sorted(subs, key=lambda s: (s.stamp or 0.0, s.robot_id))
    return order, {"offered": len(subs), "delivered": len(subs), "lost": 0, "odometry_rebased": 0,
                   "out_of_order": 0, "latency_p50_s": 0.0, "latency_max_s": 0.0}


def _deliver_acoustic(subs: list[Submap], link: LinkConfig, projection: Projection,
                      profile: Profile, seed: int,
                      rebase: Callable[[Submap, int], Submap] | None = None
                      ) -> tuple[list[Submap], dict[str, Any]]:
    """Each submap offered at its stamp from its vehicle to the topside; delivered ones come
    back decoded, in arrival order. With `rebase`, a vehicle sends each submap's odometry from
    its last keyframe it knows arrived (a delivery is known one TDMA cycle later, when the
    topside's slot has acked it; keyframe 0, the session origin, before any): a lost submap then
    leaves no gap in its odometry chain (`rebase(submap, from_keyframe)` re-cuts the odometry)."""
    robots = sorted({s.robot_id for s in subs})
    cfg = link.model_copy(deep=True)
    cfg.tdma.slot_order = [TOPSIDE, *robots]
    got: list[Delivery] = []
    sim = LinkSimulator(cfg, rng=np.random.default_rng([seed, 17]), on_deliver=got.append)
    step_s = cfg.tdma.slot_s * len(cfg.tdma.slot_order)
    keyframe_of: dict[int, tuple[str, int]] = {}  # handle -> (robot, keyframe)
    known: dict[str, int] = {}  # robot -> its last keyframe known delivered
    seen = 0  # deliveries (in delivery order) counted into `known`
    rebased = 0
    for s in sorted(subs, key=lambda s: s.stamp or 0.0):
        at = float(s.stamp or 0.0)
        sim.run_until(at)
        while seen < len(got) and got[seen].delivered_s + step_s <= at:
            robot, k = keyframe_of[got[seen].handle]
            known[robot] = max(known.get(robot, 0), k)
            seen += 1
        if rebase is not None and s.odometry is not None:
            base = known.get(s.robot_id, 0)
            if base < s.odometry.from_keyframe:
                s = rebase(s, base)
                rebased += 1
        payload = encode_message(s, profile, s.robot_id, s.seq or 0, projection=projection)
        keyframe_of[sim.offer(s.robot_id, TOPSIDE, payload, at_s=at)] = (
            s.robot_id, s.keyframe if s.keyframe is not None else -1)
    end = max((s.stamp or 0.0) for s in subs) if subs else 0.0
    sim.run_until(end)
    while sim.pending() and sim.now_s < end + cfg.arq.message_timeout_s + step_s:
        sim.run_until(sim.now_s + step_s)
    out: list[Submap] = []
    last_seq: dict[str, int] = {}
    out_of_order = 0
    for d in got:
        _, sub = decode_message(d.payload, [projection])
        if not isinstance(sub, Submap):
            continue
        seq = sub.seq or 0
        if seq < last_seq.get(sub.robot_id, -1):
            out_of_order += 1
        last_seq[sub.robot_id] = max(seq, last_seq.get(sub.robot_id, -1))
        out.append(sub)
    lat = [d.latency_s for d in got]
    return out, {"offered": len(subs), "delivered": len(out), "lost": len(subs) - len(out),
                 "out_of_order": out_of_order, "odometry_rebased": rebased,
                 "latency_p50_s": float(np.median(lat)) if lat else float("nan"),
                 "latency_max_s": float(max(lat)) if lat else float("nan")}


def replay_world(
    world: Any,
    *,
    service: ServiceConfig,
    agent: Callable[[str], AgentConfig],
    link: LinkConfig | None = None,
    projection: Projection | None = None,
    profile: Profile = Profile.COMPACT,
    seed: int = 0,
    tolerance: FactorTolerance = FactorTolerance(),
) -> dict[str, Any]:
    """Replay one world and score it: per robot the keyframe ATE (odometry only and merged),
    the merged final-pose errors, object position RMSE (own map and merged); per world the
    factors (accepted, retracted, correct, retracted while correct), the precision of the
    correspondences in force, the service's cost per submap and the delivery."""
    names = [r.name for r in world.robots]
    frames = {r: list(world.frames(r)) for r in names}
    local: dict[str, LocalMap] = {}
    subs: list[Submap] = []
    for r in names:
        cfg = agent(r).model_copy(update={"robot": r, "session": SESSION})
        local[r], own = build_submaps(cfg, frames[r])
        subs += own
    if link is None:
        order, delivery = _deliver_in_order(subs)
    else:
        if projection is None:
            raise MergeError("the acoustic link needs the fleet projection")
        order, delivery = _deliver_acoustic(
            subs, link, projection, profile, seed,
            lambda sub, k: sub.model_copy(update={
                "odometry": local[sub.robot_id].odometry(k, sub.keyframe)}))
    svc = MergeService(service.model_copy(update={"store": ":memory:"}), session=None)
    try:
        for s in order:
            svc.ingest(s)
        status = svc.status()
        stored = svc.store.factors()
        sent_ids = {f.factor_id for f in stored}
        held_rows = [f for f in svc.store.held_factors() if f.factor_id not in sent_ids]
        all_factors = [Factor.model_validate_json(f.payload) for f in [*stored, *held_rows]]
        retracted_ids = {f.factor_id for f in stored if f.status == "retracted"}
        held_ids = {f.factor_id for f in held_rows}
        held = {name: {oid: (h.keyframe, np.asarray(h.position, dtype=np.float64))
                       for oid, h in st.objects.items()} for name, st in svc.sessions.items()}
        latency = list(svc.stats.latency_ms)
        matches_tried = svc.stats.matches_tried
        edges = {name: [_edge_record(svc, e) for e in st.edges.values()]
                 for name, st in svc.sessions.items()}
        solved_cov = {f.factor_id: svc.graph.scaled_covariance(f.factor_id)
                      for f in all_factors if f.factor_id not in retracted_ids
                      and f.factor_id in svc.graph.factor_ids}
        noise_scales = {g: v.tolist() for g, v in svc.graph.noise_scales.items()}
    finally:
        svc.close()

    anchor = status.get("anchor") or str(FrameId(names[0], SESSION))
    T_aw = np.linalg.inv(world.session_start(FrameId.parse(anchor).robot))
    truth_T = {r: np.stack([T_aw @ f.T_true for f in frames[r]]) for r in names}
    obj_world = {oid: p for oid, p in zip(world.object_ids, world.objects_xyz_m)}

    def truth_of(robot: str, oid: str) -> str | None:
        try:
            return local[robot].tracker.track(oid).truth_id
        except (KeyError, MergeError):
            return None

    def counts_of(robot: str, oid: str) -> Mapping[str, int]:
        try:
            return local[robot].tracker.track(oid).truth_counts
        except (KeyError, MergeError):
            return {}

    # factors: correct by transform against the truth relative pose of their two keyframes
    factor_rows = []
    for f in all_factors:
        ka, kb = f.keyframe_a or 0, f.keyframe_b or 0
        Ta, Tb = truth_T.get(f.robot_a), truth_T.get(f.robot_b)
        ok_T, err_m, err_deg, nees = None, float("nan"), float("nan"), float("nan")
        tangent: list[float] | None = None
        if Ta is not None and Tb is not None and ka < len(Ta) and kb < len(Tb):
            T_true = np.linalg.inv(Ta[ka]) @ Tb[kb]
            w, x, y, z = f.T_a_b.quaternion_wxyz
            T_est = np.eye(4)
            T_est[:3, :3] = _quat_to_R(w, x, y, z)
            T_est[:3, 3] = f.T_a_b.translation
            err_m = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
            err_deg = rotation_error_deg(T_est, T_true)
            ok_T = err_m <= tolerance.metres and err_deg <= tolerance.degrees
            # the error as a right perturbation of the truth: T_est = T_true Exp(e)
            e = gtsam.Pose3.Logmap(gtsam.Pose3(T_true).between(gtsam.Pose3(T_est)))
            nees = _nees(e, solved_cov.get(f.factor_id,
                                          np.asarray(f.covariance, dtype=np.float64)))
            tangent = e.tolist()
        pairs = [(truth_of(f.robot_a, c.object_a), truth_of(f.robot_b, c.object_b))
                 for c in f.correspondences]
        right = sum(a is not None and a == b for a, b in pairs)
        mixed = wrong_on_merged_tracks(
            pairs, [counts_of(f.robot_a, c.object_a) for c in f.correspondences],
            [counts_of(f.robot_b, c.object_b) for c in f.correspondences])
        factor_rows.append({"id": f.factor_id, "retracted": f.factor_id in retracted_ids,
                            "held": f.factor_id in held_ids,
                            "correct": bool(ok_T), "err_m": err_m, "err_deg": err_deg,
                            "nees": nees, "err_tangent": tangent,
                            "keyframes": [ka, kb], "robots": [f.robot_a, f.robot_b],
                            "corr_right": right,
                            "corr_wrong": len(pairs) - right, "corr_wrong_mixed": mixed})
    active = [r for r in factor_rows if not r["retracted"] and not r["held"]]
    retracted = [r for r in factor_rows if r["retracted"]]
    right = sum(r["corr_right"] for r in active)
    wrong = sum(r["corr_wrong"] for r in active)
    wrong_mixed = sum(r["corr_wrong_mixed"] for r in active)

    merged_all = status.get("keyframe_poses") or {}
    # the bounds: on what the service received (the delivered submaps), exact closures and
    # closures as far off as this run's factors with right correspondences typically were (per
    # axis of their own keyframe frame: mostly heading, almost no tilt), the latter the median
    # over BOUND_DRAWS draws of the errors
    anchor_robot = FrameId.parse(anchor).robot
    bound = closure_bound(order, truth_T, truth_of, anchor=anchor_robot)
    error_sigma = bound_error_sigma(active)
    draws = ([closure_bound(order, truth_T, truth_of, anchor=anchor_robot,
                            error_sigma=error_sigma, rng=np.random.default_rng([seed, 23, d]))
              for d in range(BOUND_DRAWS)] if error_sigma is not None else [])
    robots: dict[str, dict[str, Any]] = {}
    for r in names:
        fr = frames[r]
        T_rw = np.linalg.inv(world.session_start(r))
        keys_odo = sorted({0, *local[r].keyframes})
        odo = np.stack([fr[k].T_est for k in keys_odo])
        raw = merged_all.get(str(FrameId(r, SESSION))) or {}
        keys_m = sorted(int(k) for k in raw if 0 <= int(k) < len(fr))
        row: dict[str, Any] = {"keyframes": len(keys_odo), "keyframes_merged": len(keys_m),
                               "ate_odometry_m": float("nan"), "ate_merged_m": float("nan"),
                               "final_rot_err_odometry_deg": float("nan"),
                               "final_pos_err_m": float("nan"),
                               "final_rot_err_deg": float("nan"),
                               "ate_bound_m": float("nan"), "final_rot_bound_deg": float("nan"),
                               "ate_bound_factor_accuracy_m": float("nan"),
                               "final_rot_bound_factor_accuracy_deg": float("nan"),
                               "keyframes_bound": 0,
                               "closures_bound": bound.get(r, (None, 0))[1]}
        # odometry and merged on the same keyframes (those the service placed), and the
        # odometry on all of them
        same = keys_m or keys_odo
        row["ate_odometry_all_m"] = _scores(odo, truth_T[r][keys_odo])[0]
        row["ate_odometry_m"], row["final_rot_err_odometry_deg"] = _scores(
            np.stack([fr[k].T_est for k in same]), truth_T[r][same])
        honesty = odometry_honesty(edges.get(str(FrameId(r, SESSION)), []), truth_T[r])
        row["odometry_whitened_rms"] = honesty["whitened_rms"]
        row["odometry_over_99_percent"] = honesty["over_99_percent"]
        row["odometry_declared_whitened_rms"] = honesty["declared_whitened_rms"]
        row["odometry_declared_over_99_percent"] = honesty["declared_over_99_percent"]
        row["odometry_scale"] = noise_scales.get(odometry_group(r), [1.0] * 6)
        noise = status.get("noise", {}).get(odometry_group(r), {})  # the scale's precision
        row["odometry_redundancy"] = noise.get("redundancy")
        row["odometry_scale_relative_se"] = noise.get("relative_se")
        if keys_m:
            merged = np.stack([np.asarray(raw[str(k)], dtype=np.float64) for k in keys_m])
            with contextlib.suppress(MergeError):
                row["ate_merged_m"] = ate_rmse(merged, truth_T[r][keys_m])
                m, deg = final_pose_error(merged, truth_T[r][keys_m])
                row["final_pos_err_m"], row["final_rot_err_deg"] = m, deg
        if (b := bound.get(r, (None, 0))[0]) is not None:
            row["keyframes_bound"] = len(b)
            row["ate_bound_m"], row["final_rot_bound_deg"] = _scores_of(b, truth_T[r])
        acc = [_scores_of(b, truth_T[r]) for d in draws
               if (b := d.get(r, (None, 0))[0]) is not None]
        if acc:
            row["ate_bound_factor_accuracy_m"], row["final_rot_bound_factor_accuracy_deg"] = (
                float(x) for x in np.median(acc, axis=0))
        # objects: the robot's own map (ISAM2 landmarks, own frame) and the same objects as
        # the service places them (its keyframe's merged pose, anchor frame), against the
        # truth in each frame; objects with a truth id only
        own_err, merged_err = [], []
        est = local[r].isam.calculateEstimate()
        placed = {int(k): np.asarray(T, dtype=np.float64) for k, T in raw.items()}
        for oid, (k, p_k) in held.get(str(FrameId(r, SESSION)), {}).items():
            tid = truth_of(r, oid)
            if tid is None or tid not in obj_world:
                continue
            p_w = obj_world[tid]
            lkey = L(local[r].landmark_of[oid]) if oid in local[r].landmark_of else None
            if lkey is not None and est.exists(lkey):
                p_own = np.asarray(est.atPoint3(lkey), dtype=np.float64)
                own_err.append(np.linalg.norm(p_own - (T_rw[:3, :3] @ p_w + T_rw[:3, 3])))
            if k in placed:
                T = placed[k]
                p_m = T[:3, :3] @ p_k + T[:3, 3]
                merged_err.append(np.linalg.norm(p_m - (T_aw[:3, :3] @ p_w + T_aw[:3, 3])))
        row["objects_own"] = len(own_err)
        row["objects_merged"] = len(merged_err)
        row["object_rmse_own_m"] = _rms(own_err)
        row["object_rmse_merged_m"] = _rms(merged_err)
        robots[r] = row
    lat = np.asarray(latency, dtype=np.float64)
    merged_poses = {r: {int(k): np.asarray(T, dtype=np.float64) for k, T in
                        (merged_all.get(str(FrameId(r, SESSION))) or {}).items()} for r in names}
    once = align_once([f for f in all_factors if f.keyframe_a is not None],
                      {r: np.stack([f.T_est for f in frames[r]]) for r in names},
                      {r: sorted(merged_poses[r]) for r in names}, truth_T,
                      FrameId.parse(anchor).robot)
    honest = _factor_honesty(active, solved_cov)
    return {
        "fleet_ate_merged_m": fleet_ate(merged_poses, truth_T),
        "fleet_ate_align_once_first_m": once["first"],
        "fleet_ate_align_once_best_m": once["best"],
        "factor_whitened_rms": honest["whitened_rms"],
        "factor_over_99_percent": honest["over_99_percent"],
        "factor_nees_median": honest["nees_median"],
        "factor_lag1_correlation": honest["lag1_correlation"],
        "noise_scales": noise_scales,
        "anchor": anchor,
        "robots": robots,
        "submaps": len(subs),
        "delivery": delivery,
        "factors_accepted": len(factor_rows) - len(held_ids),
        "factors_held": len(held_ids),
        "held_correct": sum(r["correct"] for r in factor_rows if r["held"]),
        "factors_retracted": len(retracted),
        "factors_correct": sum(r["correct"] for r in factor_rows),
        "retracted_correct": sum(r["correct"] for r in retracted),
        "retracted_right_correspondences": sum(r["corr_wrong"] == 0 for r in retracted),
        "active_factors": len(active),
        "active_correct": sum(r["correct"] for r in active),
        "correspondences_right": right,
        "correspondences_wrong": wrong,
        "precision": right / (right + wrong) if right + wrong else float("nan"),
        "correspondences_wrong_mixed": wrong_mixed,
        "service_ms_median": float(np.median(lat)) if lat.size else float("nan"),
        "service_ms_p90": float(np.percentile(lat, 90)) if lat.size else float("nan"),
        "matches_tried": matches_tried,
        "factors": factor_rows,
        "factor_error_sigma": error_sigma.tolist() if error_sigma is not None else None,
    }


def _edge_record(svc: MergeService, e: Any) -> OdometryEdgeRecord:
    """An odometry edge of the service with the covariance its graph solves with."""
    try:
        solved = svc.graph.scaled_covariance(e.edge_id)
    except MergeError:  # sealed (frozen): its declared covariance, scaled as its group is
        s = svc.graph.noise_scales.get(odometry_group(e.from_.frame.robot), np.ones(6))
        solved = scale_covariance(e.covariance, s)
    return OdometryEdgeRecord(e.from_.k, e.to.k, np.asarray(e.T_from_to.matrix()),
                              np.asarray(e.covariance), solved)


def _factor_honesty(active: list[dict[str, Any]], cov: dict[str, np.ndarray]
                    ) -> dict[str, Any]:
    """whitened_stats of the factors in force with the covariances the graph solves with,
    and the lag-1 correlation of successive factors' errors between the same two sessions
    (in the order they were accepted), averaged over the pairs weighted by their size."""
    rows = [r for r in active if r["err_tangent"] is not None and r["id"] in cov]
    out = whitened_stats([r["err_tangent"] for r in rows], [cov[r["id"]] for r in rows])
    pairs: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        pairs["/".join(r["robots"])].append(r)
    corr = [(lag1_correlation([x["err_tangent"] for x in p], [cov[x["id"]] for x in p]),
             len(p)) for p in pairs.values()]
    corr = [(c, n) for c, n in corr if np.isfinite(c)]
    out["lag1_correlation"] = (float(np.average([c for c, _ in corr],
                                                weights=[n for _, n in corr]))
                               if corr else float("nan"))
    return out


def _scores(est: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(ATE m, final rotation error deg) of (n, 4, 4) poses against the truth's, associated by
    index; nan when they do not fix an alignment."""
    try:
        return ate_rmse(est, ref), final_pose_error(est, ref)[1]
    except MergeError:
        return float("nan"), float("nan")


def _scores_of(poses: dict[int, np.ndarray], truth: np.ndarray) -> tuple[float, float]:
    """`_scores` of {keyframe: pose} against the truth's poses of those keyframes."""
    keys = sorted(poses)
    return _scores(np.stack([poses[k] for k in keys]), truth[keys])


def _nees(e: np.ndarray, cov: np.ndarray) -> float:
    """A factor's error under its own covariance: e' inv(cov) e with e = Log(inv(T_true) T_est)
    in GTSAM's Pose3 tangent order (rotation, translation); chi2 with 6 degrees of freedom
    (mean 6) when the covariance is honest."""
    try:
        return float(e @ np.linalg.solve(cov, e))
    except np.linalg.LinAlgError:
        return float("nan")


def _rms(x: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")


def _quat_to_R(w: float, x: float, y: float, z: float) -> np.ndarray:
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


__all__ = ["FactorTolerance", "replay_world"]
