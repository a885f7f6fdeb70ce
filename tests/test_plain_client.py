"""The independent client (clients/plain_client.py: eclipse-zenoh + msgpack + json + numpy, no
mergesvc) against a real `mergesvc serve --factor-profile full` on loopback: its own coding of
a submap is what mergesvc decodes; it gets its submap's result and factor, status and
relocalize answers, all plain JSON / msgpack that validate against schemas/ (issue 15)."""

from __future__ import annotations

import ast
import contextlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import zenoh
from helpers import free_port, wait_for, zenoh_config
from jsonschema import Draft202012Validator

from mergesvc.core.model import ObjectNode, Odometry, Submap
from mergesvc.wire import Profile, decode_message, encode_message, keys

REPO = Path(__file__).resolve().parents[1]
CLIENT = REPO / "clients" / "plain_client.py"
FLEET = "plain"
ROOT = keys.fleet_root(FLEET)
YAW, T_AB = 0.5, np.array([5.0, -3.0, 0.5])  # robot b's frame in robot a's


def load_client() -> ModuleType:
    spec = importlib.util.spec_from_file_location("plain_client", CLIENT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def schema(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((REPO / "schemas" / name).read_text()))


def pair(n: int = 8, seed: int = 0) -> tuple[Submap, Submap]:
    """Robot a's submap and robot b's view of the same n objects from a frame at yaw YAW,
    translation T_AB in a's (p_a = R p_b + t): one factor between them."""
    rng = np.random.default_rng(seed)
    emb = rng.normal(size=(n, 384))
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    pos_a = rng.uniform(-10, 10, (n, 3))
    c, s = np.cos(YAW), np.sin(YAW)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pos_b = (pos_a - T_AB) @ R

    def sub(robot: str, pos: np.ndarray) -> Submap:
        return Submap(robot_id=robot, session_id="s0", seq=0, objects=[
            ObjectNode(id=f"{robot}-{i}", position=tuple(float(x) for x in p),
                       embedding=[float(x) for x in e], variance=0.01, n_obs=3)
            for i, (p, e) in enumerate(zip(pos, emb, strict=True))])

    return sub("a", pos_a), sub("b", pos_b)


def test_the_client_imports_no_mergesvc() -> None:
    tree = ast.parse(CLIENT.read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert names and not any(m.split(".")[0] == "mergesvc" for m in names)


def test_the_clients_own_coding_is_what_mergesvc_decodes() -> None:
    """Every optional part of §4 the client writes (labels, per-dimension and isotropic
    variances, n_obs, up, keyframe and odometry) decodes to the document it was given."""
    client = load_client()
    rng = np.random.default_rng(3)
    objs = [ObjectNode(id=f"o{i}", position=tuple(rng.normal(size=3) * 7),
                       embedding=list(rng.normal(size=16).astype(np.float32).astype(float)),
                       variance=0.25 if i % 2 else list(np.full(16, 0.5 + i)),
                       n_obs=1 + 3 * i, label=None if i == 1 else f"l{i % 3}")
            for i in range(5)]
    odo = Odometry(from_keyframe=2, T_from_to={"translation": [1.0, 0.5, -0.25],
                                               "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
                   covariance=(np.eye(6) * 0.01).tolist())
    sub = Submap(robot_id="auv9", session_id="s3", seq=7, stamp=12.5, objects=objs,
                 up=(0.0, 0.0, 1.0), keyframe=5, odometry=odo)
    data = client.encode_submap(json.loads(sub.model_dump_json()), "auv9", 7)
    env, got = decode_message(data)
    assert env.profile is Profile.FULL and env.sender == "auv9" and env.seq == 7
    # float32 embeddings and variances: what the full profile keeps
    assert got == decode_message(encode_message(sub, Profile.FULL, "auv9", 7))[1]
    assert got.keyframe == 5 and got.odometry.from_keyframe == 2 and got.up == (0.0, 0.0, 1.0)


def _serve(ep: str, store: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mergesvc.cli", "serve", "--fleet", FLEET, "--store", str(store),
         "--mode", "client", "--connect", ep, "--factor-profile", "full"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True,
        env={k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")},
    )


def _status(session: zenoh.Session) -> dict | None:
    for reply in session.get(keys.status_key(ROOT), timeout=2.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def test_plain_client_says_in_one_line_when_nothing_answers(tmp_path: Path) -> None:
    """No router at --connect, or no submap file: exit 2 and one line on stderr, no traceback."""
    (tmp_path / "b.json").write_text(pair()[1].model_dump_json())
    dead = f"tcp/127.0.0.1:{free_port()}"
    for submap in ("b.json", "missing.json"):
        run = subprocess.run(
            [sys.executable, str(CLIENT), "--connect", dead, "--no-multicast-scouting",
             "--fleet", FLEET, "--robot", "b", "--submap", str(tmp_path / submap),
             "--timeout", "5"], capture_output=True, text=True, timeout=60)
        assert run.returncode == 2 and run.stdout == "", (submap, run)
        (line,) = run.stderr.strip().splitlines()
        assert line.startswith("plain_client: ") and "check --connect" in line, line
        assert ("Unable to connect" if submap == "b.json" else "No such file") in line, line


def test_plain_client_against_a_running_service(tmp_path: Path) -> None:
    sub_a, sub_b = pair()
    (tmp_path / "b.json").write_text(sub_b.model_dump_json())
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)) as _router, zenoh.open(
        zenoh_config("client", connect=ep)
    ) as cs:
        svc = _serve(ep, tmp_path / "svc.db")
        try:
            assert wait_for(lambda: _status(cs) is not None, 60.0)
            cs.put(keys.submap_key(ROOT, "a", "s0"), encode_message(sub_a, Profile.FULL, "a", 0),
                   congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for(lambda: (_status(cs) or {}).get("submaps", {}).get("processed") == 1)
            run = subprocess.run(
                [sys.executable, str(CLIENT), "--connect", ep, "--no-multicast-scouting",
                 "--fleet", FLEET, "--robot", "b", "--session", "s0", "--seq", "0",
                 "--submap", str(tmp_path / "b.json"), "--timeout", "30"],
                capture_output=True, text=True, timeout=120)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(svc.pid, signal.SIGTERM)
            svc.wait(timeout=30)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)

    result = out["result"]
    assert result["outcome"] == "processed" and result["robot"] == "b"
    assert [t["frame"] for t in result["tried"]] == ["a/s0"]
    assert result["tried"][0]["reason"] == "verified"
    assert result["factors"] == [result["tried"][0]["factor_id"]]
    # the factor the client decoded itself: b's frame in a's, as the two views were made
    (factor,) = out["factors"]
    assert factor["factor_id"] == result["factors"][0]
    assert (factor["robot_a"], factor["robot_b"]) == ("a", "b")
    assert np.allclose(factor["T_a_b"]["translation"], T_AB, atol=1e-6)
    assert np.allclose(factor["T_a_b"]["quaternion_wxyz"],
                       [np.cos(YAW / 2), 0.0, 0.0, np.sin(YAW / 2)], atol=1e-6)
    assert len(factor["correspondences"]) == 8
    status = out["status"]
    assert status["results"] == {"processed": 1, "no_match": {"no_frames": 1}, "refused": {},
                                 "failed": 0}
    assert status["factors"]["accepted"] == 1
    assert out["relocalize"]["localized"] is True and out["relocalize"]["anchor"] == "a/s0"
    assert out["relocalize_error"]["error"]["code"] == "bad_request"
    assert out["encodings"] == {
        "result": "application/json", "factor": "application/msgpack",
        "status": "application/json", "relocalize": "application/json",
        "relocalize_error": "application/json"}
    # every reply validates against its schema (an off-the-shelf 2020-12 validator)
    for name, doc in (("submap_result", result), ("factor", factor), ("status_reply", status),
                      ("relocalize_reply", out["relocalize"]),
                      ("error_message", out["relocalize_error"]["error"])):
        assert list(schema(f"{name}.schema.json").iter_errors(doc)) == [], name


@pytest.mark.parametrize("profile", [Profile.COMPACT, Profile.INT8])
def test_the_client_refuses_what_it_cannot_decode(profile: Profile) -> None:
    """A compact factor is not decoded by the client (it says how to get full ones)."""
    client = load_client()
    sub_a, _ = pair(n=4)
    if profile is Profile.INT8:  # not a factor at all
        data = encode_message(sub_a, profile, "a", 0)
    else:
        from mergesvc.core.model import Factor

        f = Factor(factor_id="f1", robot_a="a", session_a="s0", robot_b="b", session_b="s0",
                   T_a_b={"translation": [1.0, 2.0, 3.0], "quaternion_wxyz": [1.0, 0, 0, 0]},
                   covariance=(np.eye(6) * 0.01).tolist())
        data = encode_message(f, profile, "mergesvc", 1)
    with pytest.raises(ValueError, match="factor"):
        client.decode_factor(data)
