"""KISS-Matcher run from its own package beside mergesvc (bench/peers.py): the wrapper's answers
against the scenarios' truth, the peer's rows in `bench match` and `bench generalize`, and a
missing package as one line."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mergesvc.bench.match import run_match_bench
from mergesvc.bench.peers import (
    KISS_METHOD,
    MIN_MATCHES,
    KissSettings,
    kiss_outcome,
    load_kiss,
)
from mergesvc.bench.scoring import score_case
from mergesvc.errors import InputError
from mergesvc.sim import Family, make_scenario
from tests.helpers import run_cli

pytest.importorskip("kiss_matcher", reason="the peers extra (kiss-matcher) is not installed")


def _rotation_error_deg(quaternion_wxyz: tuple[float, ...], R_true: np.ndarray) -> float:
    w, x, y, z = quaternion_wxyz
    dR = Rotation.from_quat([x, y, z, w]).as_matrix().T @ R_true
    return float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("seed", [0, 3])
def test_the_peer_places_a_kitti_like_submap(seed: int) -> None:
    sc = make_scenario(Family.KITTI, seed)
    outcome = kiss_outcome(sc.map, sc.submap)
    res = outcome.result
    assert res.accepted and res.transform is not None
    assert _rotation_error_deg(res.transform.quaternion_wxyz, sc.R_map_submap) < 5.0
    assert score_case(sc, outcome)["accuracy"] >= 0.9
    # one map object per submap object, each the assignment's
    got = [m.map_object for m in res.matches]
    assert len(got) == len(set(got))
    ids = sc.map.arrays().ids
    assert {(m.submap_object, m.map_object) for m in res.matches} == {
        (sc.submap.arrays().ids[i], ids[a]) for i, a in enumerate(outcome.assignment) if a >= 0}


def test_one_map_object_takes_one_submap_object() -> None:
    """A submap object cloned 5 cm away has the same best candidate as its original: only one
    of the two is matched to that map object."""
    sc = make_scenario(Family.KITTI, 0)
    first = next(o for o in sc.submap.objects if sc.truth.get(o.id))
    twin = first.model_copy(update={"id": f"{first.id}-twin", "position": tuple(
        x + 0.05 for x in first.position)})
    sub = sc.submap.model_copy(update={"objects": [*sc.submap.objects, twin]})
    res = kiss_outcome(sc.map, sub).result
    got = [m.map_object for m in res.matches]
    assert res.accepted and sc.truth[first.id] in got
    assert len(got) == len(set(got))
    assert sum(m.submap_object in (first.id, twin.id) for m in res.matches) == 1


def test_fewer_than_three_matches_are_refused() -> None:
    """Two right matches are returned but not accepted: no evidence of a place."""
    sc = make_scenario(Family.KITTI, 0)
    two = [o for o in sc.submap.objects if sc.truth.get(o.id)][:2]
    res = kiss_outcome(sc.map, sc.submap.model_copy(update={"objects": two})).result
    assert MIN_MATCHES == 3 and not res.accepted
    assert len(res.matches) == 2 and all(sc.truth[m.submap_object] == m.map_object
                                         for m in res.matches)


def test_the_gate_bounds_the_matches() -> None:
    """Every match lies within gate_m of where the peer's transform puts its object; a gate of
    zero leaves none (the transform is not exact), so the answer is refused."""
    sc = make_scenario(Family.KITTI, 0)
    res = kiss_outcome(sc.map, sc.submap, KissSettings(gate_m=2.0)).result
    w, x, y, z = res.transform.quaternion_wxyz
    R, t = Rotation.from_quat([x, y, z, w]).as_matrix(), np.asarray(res.transform.translation)
    sub = {o.id: np.asarray(o.position) for o in sc.submap.objects}
    mp = {o.id: np.asarray(o.position) for o in sc.map.objects}
    assert res.matches
    for m in res.matches:  # the positions in float32, as the peer was given them
        assert np.linalg.norm(R @ sub[m.submap_object] + t - mp[m.map_object]) <= 2.0 + 1e-4
    none = kiss_outcome(sc.map, sc.submap, KissSettings(gate_m=0.0)).result
    assert not none.accepted and none.matches == []


def test_bench_match_runs_the_peer_beside_ours() -> None:
    lines: list[str] = []
    report = run_match_bench(repeats=2, seeds=1, paper=False, echo=lines.append,
                             families=(Family.KITTI,), one_thread=False,
                             peer=KissSettings(gate_m=7.0))
    assert report["settings"][KISS_METHOD] == {"top_k": 1, "noise_m": 2.0, "gate_m": 7.0}
    peer = report["results"][f"kitti/{KISS_METHOD}"]
    assert peer["runs"] == 2 and peer["scenarios"] == 1 and peer["accepted"] == 1
    assert peer["node_accuracy"] >= 0.9 and peer["cpu_ms"] is not None
    assert "kitti/verified/ucos" in report["results"]
    assert any("KISS-Matcher p50 in this run: kitti" in line for line in lines)


def test_a_missing_peer_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "kiss_matcher", None)  # import fails as if absent
    with pytest.raises(InputError, match=r"pip install 'mergesvc\[peers\]'"):
        load_kiss()
    r = run_cli("bench", "match", "--peer", "--seeds", "1", "--repeats", "1", "--no-paper",
                "--fresh", "0")
    assert r.returncode == 2
    assert "KISS-Matcher is not installed" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("bench", "generalize", "--quick", "--no-paper", "--cell", "gen-pool", "--peer")
    assert r.returncode == 2 and "KISS-Matcher is not installed" in r.stderr


def test_bench_generalize_scores_the_peer_in_a_cell() -> None:
    from mergesvc.bench.generalize import GeneralizePlan, run_generalize

    plan = GeneralizePlan.quick()
    plan.cells = [c for c in plan.cells if c.name == "gen-pool/camera"]
    plan.methods = ("verified", KISS_METHOD)
    report = run_generalize(plan)
    peer = report["cells"]["gen-pool/camera"]["methods"][KISS_METHOD]["over_seeds"]
    assert peer["cases"] == plan.cells[0].n_cases
    assert 0.0 < peer["node_accuracy"]["median"] <= 1.0
    assert "unrelated" in peer and "lacking" in peer  # probed with places the map lacks
    assert f"| {KISS_METHOD} |" in report["markdown"]


def test_the_peers_settings_need_the_peer() -> None:
    r = run_cli("bench", "match", "--peer-top-k", "3", "--seeds", "1")
    assert r.returncode == 2 and "need --peer" in r.stderr
