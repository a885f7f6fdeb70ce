"""`mergesvc bench soak --quick` (issue 14): a real `mergesvc serve` process under 3 robots, one
robot of another embedding model, hostile payloads and a kill -9 restart; the report's
invariants: every valid submap stored and processed exactly once (none lost, failed or
pending, even those sent while the service was down), every hostile payload refused and
answered, the mismatching robot refused and the others never."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from mergesvc.bench.soak import HostileKind, SoakPlan, SoakWorld, hostile_payload
from mergesvc.bench.soak_world import hostile_schedule
from mergesvc.core.model import Submap
from mergesvc.errors import MergeError
from mergesvc.store import CONFLICTS_KEPT
from mergesvc.wire import decode_message

# targets a 10-s soak on a loaded test machine cannot judge: the timings (status p99 <= 100 ms,
# others' p99 within 2x during the flood and the large submap), judged in the long soak, and
# the RSS growth (10 s measure the service's warm-up, not a leak)
NOT_IN_TESTS = {"status_p99_le_100ms", "flood_answered_bounded_others_p99_le_2x",
                "large_submap_answered_others_p99_le_2x", "rss_growth_under_100mb"}


def test_quick_soak_keeps_every_valid_submap_and_refuses_the_rest(tmp_path: Path) -> None:
    out = tmp_path / "soak.json"
    run = subprocess.run(
        [sys.executable, "-m", "mergesvc.cli", "bench", "soak", "--quick", "--out", str(out)],
        capture_output=True, text=True, timeout=240,
    )
    assert out.exists(), run.stdout[-3000:] + run.stderr[-3000:]
    rep = json.loads(out.read_text())
    # every target met but those a test cannot judge (the exit code says whether all were met)
    missed = {k for k, ok in rep["targets"].items() if not ok}
    assert missed <= NOT_IN_TESTS, run.stdout[-3000:] + run.stderr[-3000:]
    assert run.returncode == (1 if missed else 0), run.stdout[-3000:] + run.stderr[-3000:]
    v = rep["valid"]
    assert v["sent"] > 20
    # each valid (robot, session, seq) stored once and processed: none lost, failed, pending
    assert v["stored"] == v["sent"]
    assert (v["lost"], v["duplicated"], v["failed"], v["pending"]) == (0, 0, 0, 0)
    assert v["processed"] + v["no_match"] == v["sent"]
    assert rep["foreign_rows"] == 0
    # the kill happened mid-stream: submaps sent while the service was down came back
    assert len(rep["restarts"]) == 1
    assert rep["restarts"][0]["valid_sent_while_down"] > 0
    # hostile: all refused, all answered, none stored
    h = rep["hostile"]
    assert h["sent"] > 5 and len(h["by_kind"]) >= 3
    # the attacker's quota is the plan's: a loaded machine sends as many as a quiet one
    assert h["sent"] == h["planned"]
    assert h["answered"] == h["sent"] and h["stored"] == 0
    assert set(h["codes"]) <= {"bad_submap", "oversize"}
    # the robot of another model: every one refused with embedding_dim, nobody else answered
    m = rep["mismatch"]
    assert m["robots"] == ["m0"] and m["sent"] > 0 and m["stored"] == 0
    assert set(m["answers"]["m0"]) == {"embedding_dim"} and m["answers"]["m0"]["embedding_dim"] > 0
    assert v["errors_answered"] == {}
    assert rep["store_integrity"] == "ok" and rep["service_log"]["tracebacks"] == 0
    # the conflict flood: every variant answered conflict or rate_limited, a few hashes kept
    f = rep["flood"]
    assert f["sent"] == SoakPlan.quick().flood_variants and f["answered"] == f["sent"]
    assert set(f["codes"]) <= {"conflict", "rate_limited"} and f["codes"].get("conflict", 0) > 0
    assert 0 < f["hashes_kept"] <= CONFLICTS_KEPT and f["bytes_kept"] == 0
    assert "conflict flood: 60 variants" in run.stdout
    assert rep["results_contradictory"] == 0 and not rep["disk_full"]["ran"]
    # the large submap (400 objects: the service's lane, fleet/lane.py) got its final result
    g = rep["large"]
    assert g["sent"] and g["objects"] == 400 and g["status"] in ("processed", "no_match"), g
    assert "large submap: 400 objects" in run.stdout
    # status answered throughout, and after the restart (its cold solve)
    assert rep["status_ms"]["n"] >= 5 and rep["status_ms"]["after_restart_n"] >= 1
    assert "status round trip (probe process): p50" in run.stdout
    assert set(rep["targets"]) > NOT_IN_TESTS, rep["targets"]
    assert out.with_suffix(".png").stat().st_size > 0


def test_every_hostile_kind_is_refused_by_the_decoder_or_is_a_key_mismatch() -> None:
    """The payloads the soak sends as hostile: each undecodable, oversize, or a valid submap
    whose key does not name it (which the service refuses, tests/test_service_limits.py)."""
    plan = SoakPlan.quick()
    world = SoakWorld.make(plan)
    from mergesvc.bench.soak import RobotWalk

    rng = np.random.default_rng(3)
    good = RobotWalk(world, "h0", plan.dim, 6, 4.0, rng).next_submap(10**9)
    other = RobotWalk(world, "r00", plan.dim, 6, 4.0, rng).next_submap(10**9)
    for kind in HostileKind:
        for _ in range(5):
            key, data = hostile_payload(kind, "h0", 10**9, good, other, 4096, rng)
            if kind is HostileKind.OVERSIZE:
                assert len(data) > 4096
                continue
            try:
                _, msg = decode_message(data)
            except MergeError:
                assert kind not in (HostileKind.KEY_SESSION, HostileKind.EXTRA_LEVELS,
                                    HostileKind.OTHER_ROBOT)
                continue
            assert isinstance(msg, Submap)
            assert kind in (HostileKind.KEY_SESSION, HostileKind.EXTRA_LEVELS,
                            HostileKind.OTHER_ROBOT), kind
            assert key != f"submap/{msg.robot_id}/{msg.session_id}"


def test_the_hostile_schedule_fixes_the_count_and_spreads_it_over_the_run() -> None:
    """The expected count of the Poisson stream, whatever the draw, at times over the whole
    run: the attacker's quota does not depend on the machine nor on the seed's luck."""
    for seed in range(20):
        at_s = hostile_schedule(1.32, 10.0, np.random.default_rng(seed))
        assert len(at_s) == 13
        assert np.all(np.diff(at_s) >= 0) and at_s[0] >= 0.0 and at_s[-1] < 10.0
    at_s = hostile_schedule(2.0, 1000.0, np.random.default_rng(0))
    assert len(at_s) == 2000
    # uniform over the run: each tenth holds about a tenth (binomial sd 13)
    assert np.all(np.abs(np.histogram(at_s, bins=10, range=(0, 1000))[0] - 200) < 60)
    assert len(hostile_schedule(0.0, 10.0, np.random.default_rng(0))) == 0
