"""The `mergesvc` command as a user runs it: real files; in this process through typer's runner
(`run`), and in processes of their own where only a process shows it (`run_process`)."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import gtsam
import pytest
from helpers import run_cli as run

from mergesvc.fleet.demo_score import WORSE_ABOVE
from mergesvc.sim import Family, make_scenario

CLI = [sys.executable, "-m", "mergesvc.cli"]


def run_process(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """The command in a process of its own; a developer's MERGESVC_* settings left out (`env`
    adds variables)."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300,
                          env=clean | (env or {}))


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ex")
    r = run("example", str(out), "--family", "underwater", "--seed", "4")
    assert r.returncode == 0, r.stderr
    return out


def test_match_json_output_is_exactly_the_documented_object(files: Path) -> None:
    r = run("match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"),
            "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)  # exactly one JSON object on stdout
    assert set(out) == {"accepted", "reason", "matches", "transform", "covariance", "timings_ms"}
    truth = json.loads((files / "truth.json").read_text())["matches"]
    for m in out["matches"]:
        assert set(m) == {"submap_object", "map_object", "score"}
        assert truth[m["submap_object"]] == m["map_object"]
    assert out["accepted"] is True and out["reason"] == "verified"
    assert set(out["transform"]) == {"translation", "quaternion_wxyz"}
    assert len(out["covariance"]) == 6 and all(len(row) == 6 for row in out["covariance"])
    assert "total" in out["timings_ms"]


@pytest.mark.parametrize("mode", ["paper", "verified"])
@pytest.mark.parametrize("solver", ["rrwm", "sm", "ipfp", "exact"])  # ngm: test_ngm.py
def test_match_all_modes_and_solvers(files: Path, mode: str, solver: str) -> None:
    r = run("match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"),
            "--mode", mode, "--solver", solver, "--affinity", "mahalanobis", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    if mode == "paper":
        assert len(out["matches"]) == 6  # every submap object matched, outlier included


def test_human_output(files: Path) -> None:
    r = run("match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"))
    assert r.returncode == 0 and "accepted" in r.stdout and "T_map_submap" in r.stdout


def test_file_format_from_the_issue(tmp_path: Path) -> None:
    """Hand-written files in the documented shape, scalar and per-dimension variances."""
    sc = make_scenario(Family.KITTI, seed=3, n_map=40, n_sub=8, n_outliers=0)
    doc = json.loads(sc.map.model_dump_json())
    for k, o in enumerate(doc["objects"]):
        o.pop("label", None)
        if k % 2:
            o["variance"] = 0.2
    (tmp_path / "m.json").write_text(json.dumps(doc))
    sub = json.loads(sc.submap.model_dump_json())
    for o in sub["objects"]:
        o.pop("label", None)
    sub.pop("seq")
    (tmp_path / "s.json").write_text(json.dumps(sub))
    r = run("match", "--map", str(tmp_path / "m.json"), "--submap", str(tmp_path / "s.json"),
            "--json")
    assert r.returncode == 0, r.stderr
    got = {m["submap_object"]: m["map_object"] for m in json.loads(r.stdout)["matches"]}
    assert sum(got.get(s) == m for s, m in sc.truth.items()) >= 7


@pytest.mark.parametrize(
    "content",
    [
        "{not json",
        '{"schema_version": 2, "robot_id": "a", "session_id": "s", "objects": []}',
        '{"schema_version": 1, "robot_id": "a", "session_id": "s", "objects": [{"id": "x", '
        '"position": [0, 0, NaN], "embedding": [1, 2], "variance": 1}]}',
        "[]",
    ],
)
def test_bad_input_is_one_line_exit_2(files: Path, tmp_path: Path, content: str) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    r = run("match", "--map", str(files / "map.json"), "--submap", str(bad), "--json")
    assert r.returncode == 2
    assert r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


@pytest.mark.parametrize(("field", "at", "value"), [
    ("embedding", 0, "0.1"), ("position", 1, True), ("variance", None, "0.2")])
def test_numbers_written_as_text_or_booleans_are_refused(files: Path, tmp_path: Path, field,
                                                         at, value) -> None:
    """As the published schema refuses them (a number in quotes is not silently read)."""
    doc = json.loads((files / "submap.json").read_text())
    if at is None:
        doc["objects"][0][field] = value
    else:
        doc["objects"][0][field][at] = value
    (tmp_path / "s.json").write_text(json.dumps(doc))
    r = run("match", "--map", str(files / "map.json"), "--submap", str(tmp_path / "s.json"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert f"objects.0.{field}" in r.stderr and "valid number" in r.stderr


def test_missing_file_and_dimension_mismatch(files: Path, tmp_path: Path) -> None:
    r = run("match", "--map", str(tmp_path / "nope.json"), "--submap", str(files / "map.json"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    doc = json.loads((files / "submap.json").read_text())
    for o in doc["objects"]:
        o["embedding"] = o["embedding"][:10]
        o["variance"] = 0.1
    (tmp_path / "short.json").write_text(json.dumps(doc))
    r = run("match", "--map", str(files / "map.json"), "--submap", str(tmp_path / "short.json"))
    assert r.returncode == 2 and "dimensions differ" in r.stderr


@pytest.mark.parametrize("args", [
    ("match", "--map", "x.json"),  # --submap missing
    ("matc",),  # no such command
    ("match", "--map", "a", "--submap", "b", "--solver", "foo"),
    ("bench", "merge", "--seeds", "0"),
])
def test_usage_errors_are_one_line_exit_2(args: tuple[str, ...]) -> None:
    r = run(*args)
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "--help)" in lines[0]


@pytest.mark.parametrize("args", [("example",), ("schemas",),
                                  ("scenario", "underwater", "--per-size", "1")])
def test_an_output_folder_that_cannot_be_made_is_one_line_exit_2(tmp_path: Path, args) -> None:
    taken = tmp_path / "a_file"
    taken.write_text("")
    r = run(*args[:2 if args[0] == "scenario" else 1], str(taken), *args[2:])
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"error: cannot use {taken}: File exists (a file, where a folder is wanted: give a "
        "folder's path)"]


def test_a_negative_example_seed_names_the_option(tmp_path: Path) -> None:
    r = run("example", str(tmp_path / "ex"), "--seed", "-1")
    assert r.returncode == 2 and "--seed" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_paper_mode_exact_on_a_large_problem_says_what_to_do(tmp_path: Path) -> None:
    assert run("example", str(tmp_path)).returncode == 0  # kitti: 23 vs 605 objects
    r = run("match", "--map", str(tmp_path / "map.json"), "--submap",
            str(tmp_path / "submap.json"), "--mode", "paper", "--solver", "exact")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "too large for the exact solver" in r.stderr and "--mode verified" in r.stderr


def test_errors_say_what_is_wrong_with_the_file(files: Path, tmp_path: Path) -> None:
    """A map given for a submap, a binary map to a command that reads JSON, a missing binary
    map: one line that names the file and what it is."""
    npz = tmp_path / "map.npz"
    assert run("convert", str(files / "map.json"), str(npz)).returncode == 0
    cases = {
        ("match", "--map", str(files / "submap.json"), "--submap", str(files / "submap.json")):
            "is a submap file, not a map (map and submap swapped?)",
        ("codec", "encode", str(npz), str(tmp_path / "x.bin")):
            f"is a binary map file and this reads JSON: `mergesvc convert {npz} OUT.json`",
        ("match", "--map", str(tmp_path / "none.npz"), "--submap", str(files / "submap.json")):
            f"cannot read {tmp_path / 'none.npz'}: No such file or directory; check the path",
        ("match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"),
         "--solver", "foo"): "Invalid value for '--solver': 'foo' is not one of 'rrwm'",
        ("example", str(tmp_path / "e"), "--family", "reef"):
            "--family must be one of underwater, kitti, not 'reef'",
    }
    for args, text in cases.items():
        r = run(*args)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, (args, r.stderr)
        assert text in r.stderr, (args, r.stderr)


def test_all_zero_embeddings_are_matched_with_a_warning(files: Path, tmp_path: Path) -> None:
    """Their cosine with anything is 0: the match runs, and stderr says which objects nothing
    can match by appearance, for a JSON submap and a binary map alike."""
    sub = json.loads((files / "submap.json").read_text())
    for o in sub["objects"][:2]:
        o["embedding"] = [0.0] * len(o["embedding"])
    (tmp_path / "sub.json").write_text(json.dumps(sub))
    m = json.loads((files / "map.json").read_text())
    m["objects"][3]["embedding"] = [0.0] * len(m["objects"][3]["embedding"])
    (tmp_path / "map.json").write_text(json.dumps(m))
    assert run("convert", str(tmp_path / "map.json"), str(tmp_path / "map.npz")).returncode == 0
    r = run("match", "--map", str(tmp_path / "map.npz"), "--submap", str(tmp_path / "sub.json"),
            "--json")
    assert r.returncode == 0, r.stderr
    ids = [o["id"] for o in sub["objects"][:2]]
    assert r.stderr.strip().splitlines() == [
        f"warning: {tmp_path / 'map.npz'}: 1 object with an all-zero embedding "
        f"({m['objects'][3]['id']}): nothing matches it by appearance",
        f"warning: {tmp_path / 'sub.json'}: 2 objects with an all-zero embedding "
        f"({', '.join(ids)}): nothing matches them by appearance"]
    assert json.loads(r.stdout)["accepted"] in (True, False)  # the JSON answer, as ever
    assert run("match", "--map", str(files / "map.json"), "--submap",
               str(files / "submap.json")).stderr == ""


def test_a_check_of_a_folder_that_is_not_there_says_so(tmp_path: Path) -> None:
    for args in (("schemas", str(tmp_path / "none"), "--check"),
                 ("codec", "golden", "--out", str(tmp_path / "none"), "--check")):
        r = run(*args)
        assert r.returncode == 2 and r.stderr.strip().splitlines() == [
            f"error: no {'schema folder' if args[0] == 'schemas' else 'golden vectors'} at "
            f"{tmp_path / 'none'}: give the folder to check (the repository's "
            f"{'schemas/' if args[0] == 'schemas' else 'tests/golden'})"]


def test_version() -> None:
    r = run("--version")
    assert r.returncode == 0 and re.fullmatch(r"mergesvc \d+\.\d+\S*\n", r.stdout), r.stdout


def test_help_keeps_bracketed_text() -> None:
    """Help texts are plain, not markup: `mergesvc[view]` is what to install."""
    r = run("view", "--help")
    assert r.returncode == 0 and "mergesvc[view]" in " ".join(r.stdout.split())


def test_schemas_check_and_bench_quick(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[1]
    assert run("schemas", str(repo / "schemas"), "--check").returncode == 0
    (tmp_path / "empty").mkdir()
    assert run("schemas", str(tmp_path / "empty"), "--check").returncode == 1  # out of date
    out = tmp_path / "bench.json"
    r = run(
        "bench", "match", "--repeats", "2", "--seeds", "1", "--no-paper", "--affinity", "ucos",
        "--out", str(out),
    )
    assert r.returncode == 0, r.stderr
    report = json.loads(out.read_text())
    # verified mode with default threads and, interleaved, on one BLAS thread
    assert set(report["results"]) == {
        "kitti/verified/ucos", "underwater/verified/ucos",
        "kitti/verified (1 thread)/ucos", "underwater/verified (1 thread)/ucos"}
    kitti = report["results"]["kitti/verified/ucos"]
    assert kitti["runs"] == 2 and kitti["scenarios"] == 1
    assert report["results"]["kitti/verified (1 thread)/ucos"]["runs"] == 2
    # CPU time per match in both thread modes, p99 beside the median
    lat = kitti["latency_ms"]
    assert kitti["cpu_ms"]["median"] > 0 and lat["min"] <= lat["p99"] <= lat["max"]
    assert report["results"]["kitti/verified (1 thread)/ucos"]["cpu_ms"]["median"] > 0
    assert kitti["node_accuracy"] >= 0.9  # seed 0 is an easy, fully recoverable scenario
    assert "| kitti/verified/ucos |" in r.stdout
    # the first match of a new `mergesvc match` process, both thread settings, same answers
    assert set(report["fresh"]) == {"kitti/verified/ucos", "underwater/verified/ucos"}
    fresh = report["fresh"]["kitti/verified/ucos"]
    assert fresh["runs"] == 2 and fresh["same_answers"] == 2
    for label in ("default", "1 thread"):
        assert 0 < fresh["ms"][f"{label} match"]["max"] < fresh["ms"][f"{label} wall"]["min"]
    assert "| kitti/verified/ucos | 2/2 |" in r.stdout


def test_bench_paper_quick_end_to_end(tmp_path: Path) -> None:
    """The paper-table harness: both table layouts, both modes, figures, a scale sweep."""
    out = tmp_path / "paper"
    r = run("bench", "paper", "--quick", "--out", str(out))
    assert r.returncode == 0, r.stderr
    report = json.loads((out / "paper_bench.json").read_text())
    assert set(report["table1"]) == {"paper/rrwm/ucos", "verified/rrwm/ucos",
                                     "paper/ngm/ucos", "verified/ngm/ucos"}
    assert set(report["table1"]["paper/rrwm/ucos"]) == {"run1/n3", "run1/n5", "average"}
    assert "verified/rrwm/ucos" in report["table2"] and "verified/ngm/ucos" in report["table2"]
    # the neural solver beside the paper's best neural cell, and each solver's solve time
    ngm_rows = report["ngm_vs_paper"]["table1"]
    assert set(ngm_rows) == {"paper/ucos", "verified/ucos"}
    assert ngm_rows["paper/ucos"]["cells"] == 2
    assert 0 <= ngm_rows["paper/ucos"]["cells_above"] <= 2
    assert set(report["solve_ms"]["underwater"]) == {"paper/rrwm", "paper/ngm", "verified/rrwm",
                                                     "verified/ngm"}
    for table in (report["table1"], report["table2"]):
        for row in table.values():
            assert all(0.0 <= v <= 1.0 for v in row.values())
    verified = report["summary"]["underwater"]["verified/rrwm/ucos"]
    assert verified["cases"] == 4 and 0.0 <= verified["precision"] <= 1.0
    assert [s["map_objects"] for s in report["scale"]] == [600, 2000]
    for name in report["figures"].values():
        png = (out / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    md = (out / "paper_bench.md").read_text()
    assert "### Table I" in md and "### Table II" in md and "| verified | rrwm | ucos |" in md
    assert "### The neural solver" in md and "| paper | ngm | ucos |" in md


def test_scenario_files_feed_match(tmp_path: Path) -> None:
    r = run("scenario", "underwater", str(tmp_path), "--run", "2", "--size", "4",
            "--per-size", "2")
    assert r.returncode == 0, r.stderr
    subs = sorted(tmp_path.glob("submap_n4_*.json"))
    subs = [p for p in subs if not p.name.endswith(".truth.json")]
    assert len(subs) == 2
    m = run("match", "--map", str(tmp_path / "map.json"), "--submap", str(subs[0]), "--json")
    assert m.returncode == 0, m.stderr
    truth = json.loads(subs[0].with_suffix(".truth.json").read_text())
    assert set(truth) >= {"matches", "transform"}
    out = json.loads(m.stdout)
    for x in out["matches"]:  # whatever is returned for an accepted submap is right
        if out["accepted"]:
            assert truth["matches"][x["submap_object"]] == x["map_object"] or x[
                "map_object"] in truth.get("equivalent", {}).get(x["submap_object"], [])
    bad = run("scenario", "underwater", str(tmp_path), "--run", "7")
    assert bad.returncode == 2 and "run" in bad.stderr


def test_uncertainty_train_and_eval(tmp_path: Path) -> None:
    weights = tmp_path / "head.npz"
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"hidden_sizes": [32], "epochs": 8}))
    r = run("uncertainty", "train", str(weights), "--samples", "3000", "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    spearman = float(r.stdout.split("Spearman ")[1].split(",")[0])
    assert spearman > 0.6  # measured ~0.9: the head sees the degradation in the embedding
    e = run("uncertainty", "eval", str(weights), "--samples", "1000", "--seed", "0")
    assert e.returncode == 0, e.stderr
    assert json.loads(e.stdout)["spearman"] > 0.6
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    bad = run("uncertainty", "eval", str(tmp_path / "junk.npz"))
    assert bad.returncode == 2 and bad.stderr.startswith("error:")
    assert "Traceback" not in bad.stderr


def test_link_sim_table() -> None:
    r = run("link", "sim", "--rate", "5", "--snr-db", "6.0", "--duration-s", "600")
    assert r.returncode == 0, r.stderr
    assert "rate" in r.stdout and "6.00" in r.stdout
    bad = run("link", "sim", "--rate", "2")
    assert bad.returncode == 2


def test_demo_quick_runs_to_completion(quick_demo: dict) -> None:
    """The README's main job in its quick form: processes start, factors are accepted, the
    frames end up aligned, every process is stopped; --listen picks the endpoint."""
    tmp_path, endpoint = quick_demo["out"], quick_demo["endpoint"]
    r = types.SimpleNamespace(stdout=quick_demo["stdout"])
    # --listen: the service on that endpoint, and the line that attaches a live view to it
    assert (f"mergesvc view --connect {endpoint} --fleet demo0 --projection "
            f"{tmp_path / 'projection.npz'}") in r.stdout
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ok"] and summary["factors_accepted"] > 0
    assert summary["precision"] >= 0.8
    for a in summary["alignment"].values():
        if a["after_m"] is not None:
            assert a["after_m"] < a["before_m"] or a["after_m"] < 2.0
    assert (tmp_path / "merged_map.png").read_bytes()[:4] == b"\x89PNG"
    # each robot's keyframe trajectory against the truth: odometry alone for every robot,
    # merged (the service's keyframe poses) for the anchor and every robot aligned with it
    traj = summary["trajectory"]["robots"]
    assert set(traj) == {"auv1", "auv2", "auv3"}
    assert math.isfinite(summary["trajectory"]["fleet_ate_merged_m"])
    assert sum(line.strip().startswith("fleet ATE") for line in r.stdout.splitlines()) == 1
    # each robot's odometry noise as the service calibrated it (its status), one line each
    noise = summary["odometry_noise"]
    assert set(noise) == {"auv1", "auv2", "auv3"}
    for robot, n in noise.items():
        assert len(n["sigma_scale"]) == 6 and all(0.05 <= x <= 20 for x in n["sigma_scale"])
        line = next(x for x in r.stdout.splitlines()
                    if x.strip().startswith(f"{robot}:") and "|" in x)
        assert f"{n['sigma_scale'][0]:.2f}" in line and "+-" in line, line
    anchor_robot = summary["anchor"].split("/")[0]
    aligned = {rb for rb, a in summary["alignment"].items() if a["after_m"] is not None}
    for robot, t in traj.items():
        assert math.isfinite(t["ate_odometry_m"]) and 0.0 <= t["ate_odometry_m"] < 5.0, robot
        assert (tmp_path / "trajectories" / f"{robot}_odometry.tum").is_file()
        for key in ("ate_merged_m", "final_rot_err_deg"):
            if robot == anchor_robot or robot in aligned:
                assert t[key] is not None and math.isfinite(t[key]), (robot, key, t)
            else:
                assert t[key] is None or math.isfinite(t[key]), (robot, key, t)
        if t["ate_merged_m"] is not None:
            assert (tmp_path / "trajectories" / f"{robot}_merged.tum").is_file()
            assert 0.0 <= t["final_rot_err_deg"] <= 180.0
            # merged and odometry on the same keyframes, their ratio said in the output
            assert t["merged_over_odometry"] == t["ate_merged_m"] / t["ate_odometry_m"]
            worse = t["merged_over_odometry"] > WORSE_ABOVE  # (1.00 as printed is not worse)
            assert t["merged_over_odometry"] <= 1.10, (robot, t)  # merging harms no robot
            line = next(x for x in r.stdout.splitlines() if x.strip().startswith(f"{robot}:"))
            assert ("WORSE than its own odometry" in line) == worse, line
    assert sum("keyframe ATE" in line for line in r.stdout.splitlines()) == len(traj)
    # which robots merging made worse, in the summary and said in one line; where the files are
    worse = [rb for rb, t in traj.items() if (t["merged_over_odometry"] or 0.0) > WORSE_ABOVE]
    assert summary["robots_worse"] == worse
    verdict = [x.strip() for x in r.stdout.splitlines() if x.strip().startswith("merging made")]
    assert len(verdict) == 1 and ("no robot" in verdict[0]) == (not worse), verdict
    assert all(rb in verdict[0] for rb in worse), verdict
    assert f"summary {tmp_path / 'summary.json'}" in r.stdout
    for t in traj.values():  # the last keyframe from odometry alone, beside the merged
        assert 0.0 <= t["final_pos_err_odometry_m"] < 5.0, t
        if t["ate_merged_m"] is not None:  # and the odometry as the service received it
            assert 0.0 < t["ate_odometry_received_m"] < 5.0, t
            assert t["merged_over_received"] == t["ate_merged_m"] / t["ate_odometry_received_m"]
    # the stopped service's store exported (mergesvc export): the g2o graph loads in gtsam with
    # every node the export names, and a merged TUM file for every robot aligned with the anchor
    exports = [Path(p) for p in summary["exports"]]
    assert exports and all(p.is_file() and (tmp_path / "export") in p.parents for p in exports)
    g2o = tmp_path / "export" / "graph.g2o"
    assert g2o in exports
    assert {tmp_path / "export" / n for n in ("factors.json", "map.json", "export.json",
                                              "graph_nodes.json")} <= set(exports)
    printed = next(x for x in r.stdout.splitlines() if x.startswith("exported "))
    assert printed.startswith(f"exported {len(exports)} files") and "factors.json" in printed
    lat = next(x for x in r.stdout.splitlines() if x.startswith("service latency"))
    assert "." not in lat.split(";")[0], lat  # whole milliseconds
    graph, initial = gtsam.readG2o(str(g2o), True)
    nodes = json.loads((tmp_path / "export" / "graph_nodes.json").read_text())
    assert initial.size() == len(nodes) > 0 and graph.size() >= len(nodes) - len(traj)
    for robot in {anchor_robot, *aligned}:
        assert tmp_path / "export" / "trajectories" / f"{robot}_s0_merged.tum" in exports
    # evo on the export agrees with the summary (it once lost keyframe 0): the same keyframes;
    # the merged poses the same, the odometry compact-coded (within a centimetre)
    from evo.core import sync
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape
    from evo.tools import file_interface

    for robot, t in traj.items():
        truth = file_interface.read_tum_trajectory_file(
            str(tmp_path / "trajectories" / f"{robot}_truth.tum"))
        for kind, n in (("odometry", t["keyframes"]), ("merged", t["keyframes_merged"])):
            path = tmp_path / "export" / "trajectories" / f"{robot}_s0_{kind}.tum"
            if t[f"ate_{kind}_m"] is None or not path.is_file():
                continue
            ref, est = sync.associate_trajectories(
                truth, file_interface.read_tum_trajectory_file(str(path)))
            assert est.num_poses == n, (robot, kind)
            got = ape(ref, est, PoseRelation.translation_part, align=True).stats["rmse"]
            assert got == pytest.approx(t[f"ate_{kind}_m"], abs=0.01), (robot, kind)
    out = subprocess.run(["pgrep", "-f", str(tmp_path)], capture_output=True, text=True)
    assert out.stdout.strip() == ""  # nothing left running


def test_codec_encode_decode_feeds_match(files: Path, tmp_path: Path) -> None:
    """A compact-coded submap decodes to a file `mergesvc match` reads, with an answer as good."""
    binf, back, proj = tmp_path / "sub.bin", tmp_path / "sub.json", tmp_path / "fleet.npz"
    made = run("projection", "make", str(proj), "--from", str(files / "map.json"))
    assert made.returncode == 0, made.stderr
    r = run("codec", "encode", "--profile", "compact", "--projection", str(proj),
            str(files / "submap.json"), str(binf))
    assert r.returncode == 0, r.stderr
    assert "bytes/object" in r.stdout
    per_object = float(r.stdout.split(" bytes/object")[0].rsplit(" ", 1)[1])
    assert per_object <= 64 + 40  # a 5-object submap carries its envelope on few objects
    d = run("codec", "decode", "--projection", str(proj), str(binf), str(back))
    assert d.returncode == 0, d.stderr
    a = run("match", "--map", str(files / "map.json"), "--submap", str(back), "--json")
    b = run("match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"),
            "--json")
    pairs = lambda out: {(m["submap_object"], m["map_object"]) for m in json.loads(out)["matches"]}  # noqa: E731
    # coded on a projection of the map (not of the submap itself, as encode once did): the
    # decoded submap finds at least the same true pairs
    truth = json.loads((files / "truth.json").read_text())["matches"]
    assert pairs(b.stdout) <= pairs(a.stdout) <= set(truth.items())
    (tmp_path / "bad.bin").write_bytes(b"\x93garbage")
    bad = run("codec", "decode", str(tmp_path / "bad.bin"), str(tmp_path / "x.json"))
    assert bad.returncode == 2 and bad.stderr.startswith("error:") and "Traceback" not in bad.stderr


def test_settings_file_env_and_flags_on_match(files: Path, tmp_path: Path) -> None:
    """--settings, MERGESVC_* and the flags, last one winning; the old `--config` still works,
    with a one-line warning."""
    args = ["match", "--map", str(files / "map.json"), "--submap", str(files / "submap.json"),
            "--json"]
    bare = tmp_path / "bare.json"  # a MatchConfig object, as `--config` always read
    bare.write_text(json.dumps({"mode": "paper"}))
    tree = tmp_path / "tree.json"
    tree.write_text(json.dumps({"match": {"mode": "paper"}}))
    plain = json.loads(run(*args).stdout)
    assert plain["reason"] == "verified"
    for f in (bare, tree):
        r = run(*args, "--settings", str(f))
        assert r.returncode == 0 and r.stderr == "", r.stderr
        assert json.loads(r.stdout)["reason"] == "not_verified"  # paper mode
        assert json.loads(run(*args, "--settings", str(f), "--mode", "verified").stdout)[
            "reason"] == "verified"
        r = run(*args, "--settings", str(f), env={"MERGESVC_MATCH__MODE": "verified"})
        assert json.loads(r.stdout)["reason"] == "verified"
    old = run(*args, "--config", str(bare))
    assert old.returncode == 0 and json.loads(old.stdout)["reason"] == "not_verified"
    assert len(old.stderr.strip().splitlines()) == 1 and "deprecated" in old.stderr
    assert run(*args, "--config", str(bare), "--settings", str(tree)).returncode == 2
    r = run(*args, env={"MERGESVC_CANDIDATES__TOPK": "3"})  # a typo is an error, not ignored
    assert r.returncode == 1 and "MERGESVC_CANDIDATES__TOPK" in r.stderr and r.stdout == ""
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"candidates": {"top_k": 0}}))
    r = run(*args, "--settings", str(bad))
    assert r.returncode == 1 and r.stderr.startswith(  # where it goes in the tree, and the file
        "error: invalid settings: match.candidates.top_k"), r.stderr
    assert f"(set by settings file {bad})" in r.stderr, r.stderr


def test_config_dump_prints_the_resolved_tree(tmp_path: Path) -> None:
    r = run("config", "--dump")
    assert r.returncode == 0, r.stderr
    tree = json.loads(r.stdout)
    assert {"match", "service", "agent", "codec", "link", "workload", "uncertainty"} == set(tree)
    assert tree["service"]["match"]["verify"]["min_matches"] == 4
    r = run("config", "--dump", "--section", "match.solver",
            env={"MERGESVC_MATCH__SOLVER__NAME": "sm"})
    assert json.loads(r.stdout)["name"] == "sm"
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"service": {"fleet": "f9"}}))
    assert json.loads(run("config", "--dump", "--settings", str(f), "--section",
                          "service.fleet").stdout) == "f9"
    assert run("config", "--dump", "--section", "nope").returncode == 2
    assert run("config").returncode == 2


def test_zenoh_config_and_settings_are_two_flags() -> None:
    """--config is the Zenoh file wherever a session is opened; --settings the settings tree."""
    wide = {"COLUMNS": "240"}  # one option per line in the help
    for cmd in (["serve"], ["agent"], ["link", "bridge"]):
        text = run(*cmd, "--help", env=wide).stdout
        assert "--config" in text and "zenoh JSON5 config file" in text
    for cmd in (["serve"], ["agent"], ["demo"], ["match"], ["bench", "match"], ["config"],
                ["link", "sim"], ["codec", "encode"], ["uncertainty", "train"]):
        assert "--settings" in run(*cmd, "--help", env=wide).stdout, cmd
    assert "--config" not in run("match", "--help", env=wide).stdout  # the alias is hidden


def _tilted_files(out: Path) -> tuple[Path, Path]:
    """A map and a submap of the same 8 objects, both declaring up = +z, the submap turned
    90 degrees about x: the fit would turn the vertical over (`tilted`, rejected)."""
    import numpy as np

    from mergesvc.core.model import ObjectMap, ObjectNode, Submap

    rng = np.random.default_rng(1)
    emb = rng.normal(size=(8, 64))
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    pos = rng.uniform(-10, 10, (8, 3))
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

    def objs(p: np.ndarray, prefix: str) -> list[ObjectNode]:
        return [ObjectNode(id=f"{prefix}{i}", position=tuple(float(x) for x in q),
                           embedding=[float(x) for x in e], variance=0.01, n_obs=3)
                for i, (q, e) in enumerate(zip(p, emb, strict=True))]

    m, s = out / "tilted_map.json", out / "tilted_submap.json"
    m.write_text(ObjectMap(robot_id="m", session_id="s", objects=objs(pos, "m"),
                           up=(0, 0, 1)).model_dump_json())
    s.write_text(Submap(robot_id="r", session_id="s", seq=0, objects=objs(pos @ R.T, "s"),
                        up=(0, 0, 1)).model_dump_json())
    return m, s


def test_a_rejected_match_prints_no_transform(tmp_path: Path) -> None:
    """README: `transform ... or null`: a rejected match (here `tilted`, whose fit exists
    but turns the vertical over) prints null transform and covariance, the same keys."""
    m, s = _tilted_files(tmp_path)
    r = run("match", "--map", str(m), "--submap", str(s), "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert set(out) == {"accepted", "reason", "matches", "transform", "covariance", "timings_ms"}
    assert (out["accepted"], out["reason"]) == (False, "tilted")
    assert out["transform"] is None and out["covariance"] is None
    assert len(out["matches"]) == 8  # what was matched is still said
    text = run("match", "--map", str(m), "--submap", str(s))
    assert text.returncode == 0 and "rejected (tilted)" in text.stdout
    assert "T_map_submap" not in text.stdout
    assert "declare `up` in both files" in text.stdout.splitlines()[1]  # what to do about it


def test_a_fit_chance_explains_is_refused_with_its_count(tmp_path: Path) -> None:
    # a KITTI-like submap against the map without its own objects: chance fits 3 objects
    from mergesvc.bench.generalize import lacking_pairs
    from mergesvc.sim import Family, make_scenario

    (mp, sub), = lacking_pairs([make_scenario(Family.KITTI, 6)])
    m, s = tmp_path / "map.json", tmp_path / "submap.json"
    m.write_text(mp.model_dump_json())
    s.write_text(sub.model_dump_json())
    r = run("match", "--map", str(m), "--submap", str(s))
    assert r.returncode == 0 and "rejected (too_few_matches)" in r.stdout, r.stdout
    assert "is the vehicle on this map?" in r.stdout.splitlines()[1]
    free = tmp_path / "free.json"
    free.write_text(json.dumps({"match": {"verify": {"max_chance_log10": None}}}))
    r = run("match", "--map", str(m), "--submap", str(s), "--settings", str(free), "--json")
    assert json.loads(r.stdout)["accepted"]  # what the count refused


def test_every_rejection_reason_has_a_hint() -> None:
    from mergesvc.cli.files import _REJECTION_HINTS
    from mergesvc.core.model import RejectReason

    answers = {RejectReason.VERIFIED, RejectReason.NOT_VERIFIED}
    assert set(_REJECTION_HINTS) == {r.value for r in RejectReason} - {r.value for r in answers}


def test_factors_are_coded_full_or_compact_only() -> None:
    """docs/wire.md §2: no f16 or int8 factor; the service's setting refuses them."""
    env = {"MERGESVC_SERVICE__FACTOR_PROFILE": "int8"}
    r = run("config", "--dump", "--section", "service.factor_profile", env=env)
    assert r.returncode == 1 and "full or compact" in r.stderr
    r = run("config", "--dump", "--section", "service.factor_profile",
            env={"MERGESVC_SERVICE__FACTOR_PROFILE": "full"})
    assert r.returncode == 0 and json.loads(r.stdout) == "full"


def test_demo_refuses_a_listen_value_that_is_no_endpoint(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from mergesvc.cli import app

    r = CliRunner().invoke(app, ["demo", "--out", str(tmp_path), "--listen", "127.0.0.1:7447"])
    assert r.exit_code == 2 and "not a Zenoh endpoint" in r.output
    assert not (tmp_path / "settings.json").exists()  # refused before anything started


def test_progress_lines_say_what_changed_and_never_stop_the_work(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A line per period when the text changed, after the elapsed time; a line that fails is
    skipped; 0 prints nothing. Ticks are waited for, not timed: the test asserts no clock."""
    import threading

    from mergesvc.cli.options import progress_lines

    said: list[int] = []
    ticks = threading.Semaphore(0)

    def line() -> str:
        said.append(len(said))
        ticks.release()
        if len(said) == 2:
            raise RuntimeError("the status query failed")
        return f"count {min(len(said), 4)}"  # 1, (fails), 3, 4, 4, ...

    with progress_lines(0.01, line):
        for _ in range(7):
            assert ticks.acquire(timeout=30)
    err = capsys.readouterr().err.splitlines()
    assert [e.split("] ", 1)[1] for e in err] == ["count 1", "count 3", "count 4"]
    assert all(re.fullmatch(r"\[ +\d+ s\] count \d", e) for e in err)
    with progress_lines(0, line):
        pass
    assert capsys.readouterr().err == ""


def test_progress_line_texts() -> None:
    """The service's line reads the status reply it answers queries with; the agent's its
    counts."""
    from mergesvc.fleet.agent import AgentStats
    from mergesvc.fleet.config import ServiceConfig
    from mergesvc.fleet.replies import status_line
    from mergesvc.fleet.service import MergeService
    from mergesvc.fleet.transport import InProcessTransport

    with MergeService(ServiceConfig(store=":memory:"), InProcessTransport()) as svc:
        status = svc.status(False, False)
    status["results"]["refused"] = {"bad_submap": 2, "busy": 1}
    status["robots_alive"] = ["auv1", "auv2"]
    assert status_line(status) == (
        "submaps 0 received, 0 merged, 0 without a match, 3 refused, 0 queued; factors 0 in "
        "force, 0 retracted; robots alive: auv1, auv2")
    status["solve"] = {**status["solve"], "ok": False, "error": "indeterminant system"}
    assert status_line(status).endswith("; pose graph failing: indeterminant system")
    stats = AgentStats(frames=40, submaps_sent=2, bytes_sent=900, factors_received=1,
                       results={"processed": 1, "no_match": 1})
    assert stats.line() == ("40 frames, 2 submaps sent (900 bytes), answers: 1 no match, "
                            "1 processed, factors in: 1")


def test_view_save_path_that_cannot_be_written_is_said_before_connecting(tmp_path: Path) -> None:
    """A missing folder, a folder, a file as a folder: one line, exit 2, before the session
    (a dead endpoint would say exit 3) and before Rerun (whose refusal adds a log line)."""
    (tmp_path / "f").write_text("")
    for save, why in ((tmp_path / "no" / "x.rrd", "No such file or directory"),
                      (tmp_path, "Is a directory"), (tmp_path / "f" / "x.rrd", "Not a directory")):
        r = run("view", "--save", str(save), "--connect", "tcp/127.0.0.1:1",
                "--connect-timeout", "1", "--duration", "1")
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip().splitlines() == [f"error: cannot use {save}: {why}"], r.stderr
