"""The vehicle's local map (fleet/agent.py LocalMap) without a network: submaps anchored at
keyframes, their odometry chain, and pose-level inter-robot factors correcting the own
trajectory, all against a fleet world's ground truth."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import pytest

from mergesvc.core.model import Factor, FactorStatus
from mergesvc.core.odometry import chain_covariance, step_covariance
from mergesvc.fleet.local_map import AgentConfig, LocalMap, _transform, build_submaps
from mergesvc.sim import fleet_world

try:
    from mergesvc.core.trajectory import ate_rmse
except ImportError:  # the trajectory module is not there yet: positions after aligning x_0

    def ate_rmse(est: np.ndarray, ref: np.ndarray) -> float:  # type: ignore[misc]
        """RMSE of the positions with both trajectories expressed relative to their first
        pose (the session origin: keyframe 0), no further alignment."""
        e = np.linalg.inv(est[0]) @ est
        r = np.linalg.inv(ref[0]) @ ref
        return float(np.sqrt(np.mean(np.sum((e[:, :3, 3] - r[:, :3, 3]) ** 2, axis=1))))


ROBOTS = ("auv1", "auv2", "auv3")


@pytest.fixture(scope="module")
def world():
    return fleet_world(0, ROBOTS, laps=2)


@pytest.fixture(scope="module")
def frames(world):
    return {r: list(world.frames(r)) for r in ROBOTS}


def _pose(t) -> np.ndarray:
    return gtsam.Pose3(gtsam.Rot3.Quaternion(*t.quaternion_wxyz),
                       gtsam.Point3(*t.translation)).matrix()


def _true_xyz(world, lm: LocalMap, oid: str) -> np.ndarray | None:
    tid = lm.tracker.track(oid).truth_id
    return None if tid is None else world.objects_xyz_m[world.object_ids.index(tid)]


@pytest.mark.parametrize("robot", ROBOTS)
def test_submaps_are_anchored_at_their_keyframe(world, frames, robot) -> None:
    """Positions are in the keyframe's body frame: through the TRUE keyframe pose they land on
    the true objects, at least as well as the session-frame positions (what the agent sent
    before) do through the true session frame."""
    fr = frames[robot]
    lm, subs = build_submaps(AgentConfig(robot=robot), fr)
    assert len(subs) >= 3
    ks = [s.keyframe for s in subs]
    assert ks == lm.keyframes and all(k is not None for k in ks)
    assert ks == sorted(set(ks)) and ks[-1] < len(fr)
    est = lm.own_poses()
    T_world_start = world.robot(robot).T_world_start
    err_key, err_session = [], []
    for s in subs:
        T_true_k = fr[s.keyframe].T_true
        for o in s.objects:
            truth = _true_xyz(world, lm, o.id)
            if truth is None:  # a false detection
                continue
            p = np.array(o.position)
            err_key.append(np.linalg.norm(T_true_k[:3, :3] @ p + T_true_k[:3, 3] - truth))
            p_session = est[s.keyframe][:3, :3] @ p + est[s.keyframe][:3, 3]
            q = T_world_start[:3, :3] @ p_session + T_world_start[:3, 3]
            err_session.append(np.linalg.norm(q - truth))
    assert len(err_key) >= 10
    assert np.median(err_key) < 0.5 and np.percentile(err_key, 90) < 1.0
    assert np.median(err_key) <= np.median(err_session) + 0.05


def test_a_lost_submaps_odometry_is_bridged(frames) -> None:
    """Once a submap is known lost (`LocalMap.lost`: refused for good, failed) the next
    submap's odometry starts from the keyframe before it: the raw odometry between the two,
    its covariance composed over the whole stretch."""
    fr = frames["auv2"]
    cfg = AgentConfig(robot="auv2")
    lm = LocalMap(cfg)
    cuts = []
    for f in fr:
        if lm.add_frame(f):
            sub = lm.cut_submap(len(cuts), f.stamp_s)
            if sub is not None:
                cuts.append(sub)
                if len(cuts) == 2:
                    lm.lost.add(sub.keyframe)  # the second submap never arrives
                if len(cuts) == 3:
                    break
    assert len(cuts) == 3
    odo = cuts[2].odometry
    assert odo is not None and odo.from_keyframe == cuts[0].keyframe
    raw = np.linalg.inv(fr[cuts[0].keyframe].T_est) @ fr[cuts[2].keyframe].T_est
    np.testing.assert_allclose(_pose(odo.T_from_to), raw, atol=1e-6)
    expected = chain_covariance([f.T_est for f in fr[cuts[0].keyframe:cuts[2].keyframe + 1]],
                                step_covariance(cfg.odometry_sigma))
    np.testing.assert_allclose(odo.covariance, expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("robot", ROBOTS)
def test_odometry_chain_composes_to_the_raw_odometry(frames, robot) -> None:
    fr = frames[robot]
    cfg = AgentConfig(robot=robot)
    _, subs = build_submaps(cfg, fr)
    T = np.eye(4)
    prev = 0
    for s in subs:
        odo = s.odometry
        assert odo is not None and odo.from_keyframe == prev  # the first one from keyframe 0
        step = _pose(odo.T_from_to)
        raw = np.linalg.inv(fr[prev].T_est) @ fr[s.keyframe].T_est
        np.testing.assert_allclose(step, raw, atol=1e-6)
        # the steps' covariance composed to first order (core/odometry.py), checked there
        expected = chain_covariance([f.T_est for f in fr[prev:s.keyframe + 1]],
                                    step_covariance(cfg.odometry_sigma))
        np.testing.assert_allclose(odo.covariance, expected, rtol=1e-9, atol=1e-15)
        T = T @ step
        prev = s.keyframe
    np.testing.assert_allclose(T, fr[subs[-1].keyframe].T_est, atol=1e-6)


def _factor(fid: str, me: str, own_k: int, T_me_other: np.ndarray, other_k: int,
            cov: np.ndarray, me_is_a: bool = True) -> Factor:
    """A pose-level factor between my keyframe own_k and keyframe other_k of robot "other",
    written from either side (me as robot_a, or as robot_b with the inverse transform and
    its covariance carried over by the adjoint)."""
    if me_is_a:
        return Factor(factor_id=fid, robot_a=me, session_a="s0", robot_b="other",
                      session_b="s0", T_a_b=_transform(T_me_other), covariance=cov.tolist(),
                      keyframe_a=own_k, keyframe_b=other_k)
    Ad = gtsam.Pose3(T_me_other).AdjointMap()
    cov_inv = Ad @ cov @ Ad.T
    return Factor(factor_id=fid, robot_a="other", session_a="s0", robot_b=me, session_b="s0",
                  T_a_b=_transform(np.linalg.inv(T_me_other)),
                  covariance=(0.5 * (cov_inv + cov_inv.T)).tolist(),
                  keyframe_a=other_k, keyframe_b=own_k)


@pytest.mark.parametrize("robot", ROBOTS)
def test_two_factors_to_one_other_keyframe_correct_the_own_trajectory(frames, robot) -> None:
    """Two pose-level factors (from the truth) tie an early and a late own keyframe to one
    keyframe of another robot: a loop through it, the own trajectory's ATE goes down. One
    factor alone only places the other keyframe; retracting the second undoes the loop."""
    fr = frames[robot]
    other = frames["auv2" if robot != "auv2" else "auv1"]
    # a loose odometry model (the default when this was written), pinned: the local map's
    # smoothed trajectory then drifts well away from the truth, so there is a lot to correct
    lm, subs = build_submaps(AgentConfig(robot=robot, odometry_sigma=(0.02, 0.05)), fr)
    truth = np.stack([f.T_true for f in fr])

    def ate() -> float:
        return ate_rmse(lm.own_poses(), truth)

    j = 5  # the other robot's keyframe both factors see
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)
    cov[3, 4] = cov[4, 3] = 0.5 * 0.05**2  # not diagonal: the adjoint must carry it over

    def rel(k: int) -> np.ndarray:
        return np.linalg.inv(truth[k]) @ other[j].T_true

    k1, k2 = subs[0].keyframe, subs[-1].keyframe
    assert k2 - k1 > 100  # most of the mission apart: the drift between them is large
    before = ate()
    line = lm.add_inter_robot(_factor("f1", robot, k1, rel(k1), j, cov))
    assert "first estimate" in line and "moved max" in line
    assert ate() == pytest.approx(before, abs=0.02)  # one factor: no loop, nothing corrected
    line = lm.add_inter_robot(_factor("f2", robot, k2, rel(k2), j, cov, me_is_a=False))
    after = ate()
    moved_max = float(line.split("moved max ")[1].split(" m")[0])
    assert after < 0.85 * before and moved_max > 0.2, (before, after, line)
    assert len(lm.other_keys) == 1  # both factors tie to the same other keyframe
    # the same factor again changes nothing; retracted, it leaves the graph
    assert "already in the graph" in lm.add_inter_robot(
        _factor("f2", robot, k2, rel(k2), j, cov, me_is_a=False))
    line = lm.add_inter_robot(_factor("f2", robot, k2, rel(k2), j, cov, me_is_a=False)
                              .model_copy(update={"status": FactorStatus.RETRACTED}))
    assert "removed" in line
    assert ate() == pytest.approx(before, abs=0.05)
    # the last factor on the other keyframe retracted too: the graph stays solvable
    line = lm.add_inter_robot(_factor("f1", robot, k1, rel(k1), j, cov)
                              .model_copy(update={"status": FactorStatus.RETRACTED}))
    assert "removed" in line and ate() == pytest.approx(before, abs=0.05)
    assert "not in the graph" in lm.add_inter_robot(
        _factor("f9", robot, k1, rel(k1), j, cov)
        .model_copy(update={"status": FactorStatus.RETRACTED}))


def test_a_factor_on_a_keyframe_not_reached_yet_is_held_until_then(frames) -> None:
    """A vehicle restarted on its session is told of its earlier factors at once, some on
    keyframes it has not reached again yet: each is held, added when the map reaches its
    keyframe (the same correction as when both came late), or dropped when retracted first."""
    fr, other = frames["auv1"], frames["auv2"]
    truth = np.stack([f.T_true for f in fr])
    cfg = AgentConfig(robot="auv1", odometry_sigma=(0.02, 0.05))
    ref, subs = build_submaps(cfg, fr)
    before = ate_rmse(ref.own_poses(), truth)
    k1, k2 = subs[0].keyframe, subs[-1].keyframe
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)

    def factor(fid: str, k: int) -> Factor:
        return _factor(fid, "auv1", k, np.linalg.inv(truth[k]) @ other[5].T_true, 5, cov)

    for f in (factor("f1", k1), factor("f2", k2)):
        ref.add_inter_robot(f)
    lm = LocalMap(cfg)
    for f in fr[:k1 + 1]:
        lm.add_frame(f)
    assert "first estimate" in lm.add_inter_robot(factor("f1", k1))
    assert "held until then" in lm.add_inter_robot(factor("f2", k2))
    assert "held until then" in lm.add_inter_robot(factor("f3", k2 - 1))
    assert "it was held" in lm.add_inter_robot(
        factor("f3", k2 - 1).model_copy(update={"status": FactorStatus.RETRACTED}))
    lines: list[str] = []
    for f in fr[k1 + 1:]:
        lm.add_frame(f)
        lines += [(lm.frames_seen - 1, line) for line in lm.add_held()]
    assert [(k, line.split(":")[0]) for k, line in lines] == [(k2, "factor f2")]
    assert f"from my keyframe {k2}" in lines[0][1] and "moved max" in lines[0][1]
    np.testing.assert_allclose(lm.own_poses()[:, :3, 3], ref.own_poses()[:, :3, 3], atol=0.02)
    assert ate_rmse(lm.own_poses(), truth) < 0.85 * before


def test_the_inverse_side_gives_the_same_correction(frames) -> None:
    """A factor received as robot_b (T_a_b inverted, covariance through the adjoint) corrects
    the trajectory exactly as the same factor received as robot_a."""
    fr, other = frames["auv3"], frames["auv1"]
    truth = np.stack([f.T_true for f in fr])
    cov = np.diag([0.02**2, 0.01**2, 0.03**2, 0.05**2, 0.2**2, 0.1**2])
    out = []
    for me_is_a in (True, False):
        lm, subs = build_submaps(AgentConfig(robot="auv3"), fr)
        for i, s in enumerate((subs[0], subs[-1])):
            T = np.linalg.inv(truth[s.keyframe]) @ other[7].T_true
            lm.add_inter_robot(_factor(f"f{i}", "auv3", s.keyframe, T, 7, cov, me_is_a))
        out.append(lm.own_poses())
    np.testing.assert_allclose(out[0][:, :3, 3], out[1][:, :3, 3], atol=1e-3)


def test_frame_level_factor_is_anchored_at_keyframe_0(frames) -> None:
    """Without keyframes a factor ties the session origins: x_0 and the other session's
    keyframe 0 (the same variable a pose-level factor to that keyframe 0 uses)."""
    lm, subs = build_submaps(AgentConfig(robot="auv1"), frames["auv1"])
    T = np.eye(4)
    T[:3, 3] = [4.0, -2.0, 0.5]
    cov = np.diag([0.01] * 3 + [0.1] * 3)
    f = Factor(factor_id="fr", robot_a="other", session_a="s0", robot_b="auv1",
               session_b="s0", T_a_b=_transform(np.linalg.inv(T)), covariance=cov.tolist())
    line = lm.add_inter_robot(f)
    assert "from my keyframe 0" in line and "[4.0, -2.0, 0.5]" in line
    assert list(lm.other_keys) == [("other/s0", 0)]
    g = _factor("pk", "auv1", subs[0].keyframe, np.eye(4), 0, cov)
    lm.add_inter_robot(g)
    assert list(lm.other_keys) == [("other/s0", 0)]
    # factors between two other sessions are not for this map
    h = f.model_copy(update={"factor_id": "x", "robot_b": "auv9"})
    assert "ignored" in lm.add_inter_robot(h)


def test_a_loop_within_the_session_ties_two_own_poses(frames) -> None:
    """A factor between two of its own keyframes (a loop the service found in the session's
    map), from the truth: a BetweenFactor of the two own poses, no other robot's variable;
    the trajectory's ATE goes down, and back when it is retracted. One on a keyframe not
    reached yet is held; one tying a keyframe to itself is ignored."""
    robot = "auv3"
    fr = frames[robot]
    lm, subs = build_submaps(AgentConfig(robot=robot, odometry_sigma=(0.02, 0.05)), fr)
    truth = np.stack([f.T_true for f in fr])
    k1, k2 = subs[1].keyframe, subs[-1].keyframe
    cov = np.diag([0.01**2] * 3 + [0.05**2] * 3)

    def loop(fid: str, ka: int, kb: int) -> Factor:
        return Factor(factor_id=fid, robot_a=robot, session_a="s0", robot_b=robot,
                      session_b="s0", T_a_b=_transform(np.linalg.inv(truth[ka]) @ truth[kb]),
                      covariance=cov.tolist(), keyframe_a=ka, keyframe_b=kb)

    before = ate_rmse(lm.own_poses(), truth)
    line = lm.add_inter_robot(loop("L", k1, k2))
    assert "moved max" in line and not lm.other_keys
    after = ate_rmse(lm.own_poses(), truth)
    assert after < 0.85 * before, (before, after)
    ahead = loop("H", k1, k2).model_copy(update={"keyframe_b": lm.frames_seen + 3})
    assert "held until then" in lm.add_inter_robot(ahead)
    assert "to itself" in lm.add_inter_robot(loop("S", k2, k2))
    line = lm.add_inter_robot(loop("L", k1, k2).model_copy(
        update={"status": FactorStatus.RETRACTED}))
    assert "removed" in line and not lm.other_keys
    assert ate_rmse(lm.own_poses(), truth) == pytest.approx(before, abs=0.05)


def test_submaps_declare_the_ahrs_gravity_of_their_keyframe(frames) -> None:
    """A frame with an AHRS reading (up_body) makes the submap cut there declare it as `up`;
    without one and without `agent.up`, nothing is declared; with `agent.up` only, the
    vehicle rotates it into the keyframe with its own estimate."""
    fr = frames["auv1"]
    _, subs = build_submaps(AgentConfig(robot="auv1"), fr)
    for s in subs:
        R_true = fr[s.keyframe].T_true[:3, :3]
        assert np.allclose(s.up, R_true.T @ np.array([0.0, 0.0, 1.0]), atol=1e-9)
    bare = [f.__class__(f.k, f.stamp_s, f.T_est, f.T_true, f.detections) for f in fr]
    _, subs = build_submaps(AgentConfig(robot="auv1"), bare)
    assert subs and all(s.up is None for s in subs)
    lm, subs = build_submaps(AgentConfig(robot="auv1", up=(0.0, 0.0, 1.0)), bare)
    est = lm.isam.calculateEstimate()  # smoothed since the cuts: close, not equal
    for s in subs:
        R_est = est.atPose3(gtsam.symbol("x", s.keyframe)).rotation().matrix()
        assert np.allclose(s.up, R_est.T @ np.array([0.0, 0.0, 1.0]), atol=0.02)


@pytest.mark.parametrize(
    "up", [(0.0, 0.0, 0.0), (float("nan"), 0.0, 1.0), (0.0, float("inf"), 0.0)]
)
def test_agent_up_must_be_a_direction(up) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="finite, non-zero direction"):
        AgentConfig(robot="auv1", up=up)


def test_the_agent_takes_factors_of_either_profile_and_counts_its_results(frames, caplog
                                                                          ) -> None:
    """Over real Zenoh (loopback, scouting off): the service may code factors full (`serve
    --factor-profile full`) or compact; the agent takes both into its graph. The service's
    result of each submap (JSON on result/{robot}) is counted per outcome."""
    import json

    import zenoh
    from helpers import free_port, wait_for, zenoh_config

    from mergesvc.fleet.agent import Agent, decode_factor
    from mergesvc.wire import Profile, encode_message, keys

    root = keys.fleet_root("ag")
    ep = f"tcp/127.0.0.1:{free_port()}"
    cov = (np.eye(6) * 0.01).tolist()
    factors = [Factor(factor_id=f"auv2.s0-auv1.s0-{k}", robot_a="auv2", session_a="s0",
                      robot_b="auv1", session_b="s0", keyframe_a=0, keyframe_b=k,
                      T_a_b={"translation": [1.0, float(k), 0.0],
                             "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]}, covariance=cov)
                 for k in (3, 5)]
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, zenoh.open(
        zenoh_config("client", connect=ep)
    ) as cs, Agent(
        AgentConfig(robot="auv1"), cs,
        lambda sub, seq: encode_message(sub, Profile.INT8, "auv1", seq), decode_factor,
        keys.submap_key(root, "auv1", "s0"), keys.robot_factors(root, "auv1"),
        keys.alive_key(root, "auv1"), result_key=keys.result_key(root, "auv1"),
    ) as ag:
        ag.run(frames["auv1"][:20])
        for f, profile in zip(factors, (Profile.FULL, Profile.COMPACT), strict=True):
            rs.put(keys.factor_key(root, "auv1", f.factor_id),
                   encode_message(f, profile, "mergesvc", 1))
        # another vehicle's (or run's) session under this robot's name: not this one's result
        rs.put(keys.result_key(root, "auv1"), json.dumps({
            "robot": "auv1", "session": "s1", "seq": 0, "outcome": "processed", "factors": []}))
        for outcome in ("no_match", "processed", "no_match"):
            doc = {"robot": "auv1", "session": "s0", "seq": 0, "outcome": outcome,
                   "reason": "too_few_matches" if outcome == "no_match" else None,
                   "factors": [] if outcome == "no_match" else [factors[0].factor_id]}
            rs.put(keys.result_key(root, "auv1"), json.dumps(doc))
        assert wait_for(lambda: ag.stats.factors_received == 2
                        and sum(ag.stats.results.values()) == 3, 10.0)
        assert ag.stats.bad_messages == 0
        assert ag.stats.results == {"no_match": 2, "processed": 1}
        assert set(ag.local._received) == {f.factor_id for f in factors}
        # a submap the service will never hold is lost: the next one's odometry bridges it
        assert ag.stats.submaps_sent == 1 and not ag.local.lost
        kf = ag._sent[("s0", 0)][1]
        for n, (outcome, code, lost) in enumerate((("refused", "busy", set()),  # sent again
                                                    ("failed", "processing", {kf}))):
            rs.put(keys.result_key(root, "auv1"), json.dumps({
                "robot": "auv1", "session": "s0", "seq": 0, "outcome": outcome,
                "code": code, "detail": "test"}))
            assert wait_for(lambda n=n: sum(ag.stats.results.values()) == 4 + n, 10.0)
            assert ag.local.lost == lost
        # refused for good: counted once a submap, said by default the first time of a code
        assert ag.stats.submaps_refused == 1 and ag.stats.last_refusal == "processing: test"
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="mergesvc.fleet.agent"):
            for session, seq, code in ((None, None, "bad_submap"), ("s0", 0, "conflict"),
                                       (None, None, "bad_submap"), ("s0", 0, "conflict")):
                # a submap the service could not read carries no seq: each counts
                rs.put(keys.result_key(root, "auv1"), json.dumps({
                    "robot": "auv1", "session": session, "seq": seq, "outcome": "refused",
                    "code": code, "detail": "no"}))
            assert wait_for(lambda: ag.stats.results.get("refused") == 5, 10.0)
        assert ag.stats.submaps_refused == 3  # seq 0 once, the two unread ones
        said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert said == [
            "auv1: a submap refused for good, not sent again; the service said: bad_submap: no",
            "auv1: submap s0/0 refused for good, not sent again; the service said: conflict: "
            "no"]
        assert not ag.stats.all_refused()  # one was processed
