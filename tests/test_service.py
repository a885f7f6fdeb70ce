"""The merge service end to end over real Zenoh sessions on 127.0.0.1 (scouting off): vehicle
agents and the service exchange submaps and factors, checked against the mission's truth; the
service killed mid-run loses nothing; garbage is answered; a new session relocalizes."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_for, zenoh_config

from mergesvc.core.model import ErrorMessage, Factor
from mergesvc.fleet.agent import Agent, AgentConfig, build_submaps
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.demo import query_status
from mergesvc.fleet.replies import RelocalizeReply
from mergesvc.fleet.service import MergeService
from mergesvc.sim import fleet_world
from mergesvc.wire import Profile, decode_message, encode_message, keys

ROBOTS = ("auv1", "auv2", "auv3")
FLEET = "t"
ROOT = keys.fleet_root(FLEET)


@pytest.fixture(scope="module")
def world():
    return fleet_world(0, ROBOTS, laps=1)


@pytest.fixture(scope="module")
def truth(world):
    """robot -> track id -> true object id (the agents' tracking is deterministic)."""
    out = {}
    for r in ROBOTS:
        lm, _ = build_submaps(AgentConfig(robot=r), world.frames(r))
        out[r] = {t.track_id: t.truth_id for t in lm.tracker.tracks}
    return out


def run_agents(world, endpoint: str, robots=ROBOTS, stop_after: int | None = None) -> list:
    """Agents in threads, each with its own client session. Returns (agent, session) pairs,
    still open (the caller closes them), after every agent has processed its frames."""
    out, threads = [], []
    for r in robots:
        s = zenoh.open(zenoh_config("client", connect=endpoint))
        ag = Agent(
            AgentConfig(robot=r), s,
            lambda sub, seq, r=r: encode_message(sub, Profile.INT8, r, seq),
            lambda b: decode_message(b)[1],
            f"{ROOT}/submap/{r}/s0", f"{ROOT}/factor/{r}/**", f"{ROOT}/alive/{r}",
        )
        frames = world.frames(r)
        if stop_after is not None:
            frames = (f for f in frames if f.k < stop_after)
        th = threading.Thread(target=ag.run, args=(frames,))
        th.start()
        threads.append(th)
        out.append((ag, s))
    for th in threads:
        th.join(timeout=120)
    return out


def close_all(pairs) -> None:
    for ag, s in pairs:
        ag.close()
        s.close()


def correspondence_precision(factors, truth) -> tuple[int, int]:
    right = wrong = 0
    for f in factors:
        for c in f.correspondences:
            ta = truth[f.robot_a].get(c.object_a)
            ok = ta is not None and ta == truth[f.robot_b].get(c.object_b)
            right += ok
            wrong += not ok
    return right, wrong


def pose_err(T_est: np.ndarray, T_true: np.ndarray) -> float:
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def test_agents_and_service_exchange_correct_factors(world, truth) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, MergeService(
        ServiceConfig(fleet=FLEET, store=":memory:"), rs
    ) as svc:
        pairs = run_agents(world, ep)
        try:
            assert wait_for(lambda: svc.status()["submaps"]["processed"] == sum(
                ag.stats.submaps_sent for ag, _ in pairs) > 0)
            # the solve runs after the batch, off the state lock: status may answer before it
            assert wait_for(lambda: not svc._dirty and len(svc.status()["frame_poses"]) >= 2)
            st = svc.status()
            assert st["factors"]["accepted"] >= 2
            assert set(st["robots_alive"]) == set(ROBOTS)
            # what the service holds as active factors is right against the truth
            right, wrong = correspondence_precision(svc.factors.values(), truth)
            assert right >= 10 and wrong <= 0.1 * (right + wrong)
            # every robot that got a factor put it into its ISAM2 graph
            assert wait_for(lambda: all(ag.stats.factors_received > 0 for ag, _ in pairs
                                        if any(ag.config.robot in (f.robot_a, f.robot_b)
                                               for f in svc.factors.values())))
            # the frames are aligned: each within 3 m of the truth in the anchor frame (a
            # frame's pose is its keyframe 0's, the session start)
            anchor = st["anchor"].split("/")[0]
            for frame, T in st["frame_poses"].items():
                robot = frame.split("/")[0]
                assert pose_err(np.asarray(T), world.T_rel_true(anchor, robot)) < 3.0, frame
            assert len(st["frame_poses"]) >= 2
            # the vehicles send keyframe submaps: the factors tie keyframes, and every keyframe
            # of the aligned sessions is within 3 m of the truth in the anchor frame
            assert all(f.keyframe_a is not None and f.keyframe_b is not None
                       for f in svc.factors.values())
            assert st["keyframe_poses"].keys() == st["frame_poses"].keys()
            T0_inv = np.linalg.inv(world.session_start(anchor))
            for frame, poses in st["keyframe_poses"].items():
                T_true = [f.T_true for f in world.frames(frame.split("/")[0])]
                assert len(poses) >= 2 and poses["0"] == st["frame_poses"][frame]
                for k, T in poses.items():
                    assert pose_err(np.asarray(T), T0_inv @ T_true[int(k)]) < 3.0, (frame, k)
        finally:
            close_all(pairs)


def test_garbage_is_answered_and_the_service_survives(world) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    errors: list[ErrorMessage] = []
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, MergeService(
        ServiceConfig(fleet=FLEET, store=":memory:", max_payload_bytes=200_000), rs
    ) as svc, zenoh.open(zenoh_config("client", connect=ep)) as cs:
        sub = cs.declare_subscriber(f"{ROOT}/error/**",
                                    lambda s: errors.append(decode_message(
                                        s.payload.to_bytes())[1]))
        _, subs = build_submaps(AgentConfig(robot="auv1"), world.frames("auv1"))
        good = encode_message(subs[0], Profile.INT8, "auv1", 0)
        hostile = [
            b"",
            b"\x00\xff garbage",
            os.urandom(5000),
            msgpack.packb([99, 1, 2, "auv1", 0, 0, {}]),  # wrong schema version
            good[: len(good) // 2],  # truncated
            b"x" * 300_000,  # oversize
        ]
        # blocking puts: a burst under default congestion control may be dropped on a loaded
        # machine (zenoh's behaviour, not the service's), which would leave nothing to refuse
        block = zenoh.CongestionControl.BLOCK
        for payload in hostile:
            cs.put(f"{ROOT}/submap/auv1/s0", payload, congestion_control=block)
        # a valid submap published under another robot's key: refused (robot mismatch)
        cs.put(f"{ROOT}/submap/auv2/s0", good, congestion_control=block)
        assert wait_for(lambda: svc.stats.submaps_rejected >= len(hostile) + 1)
        assert wait_for(lambda: len(errors) >= len(hostile) + 1)
        assert all(isinstance(e, ErrorMessage) for e in errors)
        assert {e.code for e in errors} == {"bad_submap", "oversize"}
        # still alive: a valid submap is persisted and processed
        cs.put(f"{ROOT}/submap/auv1/s0", good)
        assert wait_for(lambda: svc.stats.submaps_processed == 1)
        # bad queries get an error reply, status still answers
        replies = list(cs.get(f"{ROOT}/relocalize", payload=b"junk", timeout=5.0))
        assert replies and replies[0].err is not None
        # the one error shape (an ErrorMessage document), as JSON
        err = ErrorMessage.model_validate_json(replies[0].err.payload.to_bytes())
        assert err.code == "bad_request" and err.detail
        assert str(replies[0].err.encoding) == "application/json"
        assert query_status(cs, FLEET)["submaps"]["processed"] == 1
        sub.undeclare()


def _serve(ep: str, store: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mergesvc.cli", "-v", "serve", "--fleet", FLEET, "--store",
         str(store), "--mode", "client", "--connect", ep],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
    )


def _kill(p: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(p.pid, sig)
    p.wait(timeout=15)


def test_service_killed_mid_run_loses_nothing_and_duplicates_nothing(world, tmp_path) -> None:
    """kill -9 of the service process while vehicles publish; on restart it recovers what it
    missed from the vehicles' publication caches, processes every submap once, and its factor
    ids stay unique."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    store = tmp_path / "svc.db"
    with zenoh.open(zenoh_config("router", listen=ep)) as _router, zenoh.open(
        zenoh_config("client", connect=ep)
    ) as cs:
        svc = _serve(ep, store)
        try:
            assert wait_for(lambda: query_status(cs, FLEET, 1.0) is not None, 30.0)
            first = run_agents(world, ep, stop_after=60)  # first part of the mission
            sent_first = sum(ag.stats.submaps_sent for ag, _ in first)
            assert sent_first > 0
            assert wait_for(lambda: (query_status(cs, FLEET, 1.0) or {}).get(
                "submaps", {}).get("received", 0) >= sent_first, 30.0)
            _kill(svc)  # no clean shutdown
            # vehicles keep publishing while the service is down
            for ag, _ in first:
                for fr in world.frames(ag.config.robot):
                    if fr.k >= 60 and ag.local.add_frame(fr):
                        sub = ag.local.cut_submap(ag.stats.submaps_sent, fr.stamp_s)
                        if sub is not None:
                            ag._pub.put(ag._encode(sub, ag.stats.submaps_sent))
                            ag.stats.submaps_sent += 1
            total = sum(ag.stats.submaps_sent for ag, _ in first)
            assert total > sent_first
            svc = _serve(ep, store)
            assert wait_for(lambda: (query_status(cs, FLEET, 1.0) or {}).get(
                "store", {}).get("rows", {}).get("submaps", 0) >= total, 60.0)
            st = query_status(cs, FLEET)
            assert wait_for(lambda: query_status(cs, FLEET)["submaps"]["queued"] == 0, 60.0)
            close_all(first)
        finally:
            _kill(svc, signal.SIGTERM)
        from mergesvc.store import Store

        with Store(store) as db:
            rows = db.submaps()
            keys_ = [(r.robot_id, r.session_id, r.seq) for r in rows]
            assert len(keys_) == len(set(keys_)) == total  # nothing lost, nothing twice
            assert not db.unprocessed_submaps()
            fids = [f.factor_id for f in db.factors()]
            assert len(fids) == len(set(fids))
        assert st is not None


def test_relocalization_of_a_new_session(world) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, MergeService(
        ServiceConfig(fleet=FLEET, store=":memory:"), rs
    ) as svc, zenoh.open(zenoh_config("client", connect=ep)) as cs:
        pairs = run_agents(world, ep)
        try:
            assert wait_for(lambda: svc.status()["submaps"]["queued"] == 0 and
                            svc.status()["submaps"]["processed"] > 0)
            anchor = svc.status()["anchor"]
            # auv1 back in the water: a new session (new odometry frame) sends its first submaps
            frames = list(world.frames("auv1", session=1))
            _, subs = build_submaps(AgentConfig(robot="auv1", session="s1"), frames)
            assert subs
            verdicts = []
            for sub in subs[:6]:
                payload = encode_message(sub, Profile.INT8, "auv1", sub.seq or 0)
                reply = next(iter(cs.get(f"{ROOT}/relocalize", payload=payload, timeout=10.0)))
                assert reply.ok is not None
                v = RelocalizeReply.model_validate_json(reply.ok.payload.to_bytes())
                assert v.keyframe == sub.keyframe
                verdicts.append(v)
            assert all(v.reason for v in verdicts)
            located = [v for v in verdicts if v.localized]
            assert located, [v.reason for v in verdicts]
            v = located[0]
            # the answer is the pose of the submap's frame in the anchor frame (the anchor
            # session's keyframe 0, its start): the keyframe's pose for a keyframe submap, the
            # new session's start for one without keyframe
            T_where = (world.session_start("auv1", 1) if v.keyframe is None
                       else frames[v.keyframe].T_true)
            T_true = np.linalg.inv(world.session_start(anchor.split("/")[0])) @ T_where
            T = np.eye(4)
            from scipy.spatial.transform import Rotation

            w, x, y, z = v.T_anchor_session.quaternion_wxyz
            T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
            T[:3, 3] = v.T_anchor_session.translation
            # the map it is matched against depends on the order submaps arrived over Zenoh:
            # measured up to 3.03 under load (2.x alone)
            assert pose_err(T, T_true) < 4.0
            assert np.allclose(np.asarray(v.covariance), np.asarray(v.covariance).T)
        finally:
            close_all(pairs)


def test_factor_messages_decode_for_the_vehicles(world) -> None:
    """What goes to a vehicle on factor/{robot}/** is a compact Factor it can decode."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    got: list[Factor] = []
    with zenoh.open(zenoh_config("router", listen=ep)) as rs, MergeService(
        ServiceConfig(fleet=FLEET, store=":memory:"), rs
    ) as svc, zenoh.open(zenoh_config("client", connect=ep)) as cs:
        sub = cs.declare_subscriber(f"{ROOT}/factor/auv3/**",
                                    lambda s: got.append(decode_message(s.payload.to_bytes())[1]))
        pairs = run_agents(world, ep)
        try:
            assert wait_for(lambda: len(got) > 0)
            assert all(isinstance(f, Factor) and "auv3" in (f.robot_a, f.robot_b) for f in got)
            assert len(encode_message(got[0], Profile.COMPACT, "mergesvc", 1)) < 400
            assert svc.stats.factors_accepted >= len({f.factor_id for f in got}) > 0
        finally:
            sub.undeclare()
            close_all(pairs)
