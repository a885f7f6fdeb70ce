"""`mergesvc match` and `codec encode` keep their promise on hostile JSON files: one line on
stderr and exit code 2, never a traceback (issue 14, item 6)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import run_cli

from mergesvc.core.model import ObjectMap, Submap
from mergesvc.errors import DecodeError, SchemaError
from mergesvc.sim import Family, make_scenario
from mergesvc.wire.files import load_model

CLI = [sys.executable, "-m", "mergesvc.cli"]
DEPTH = 100_000


def run(*args: str) -> subprocess.CompletedProcess:
    return run_cli(*args)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("boundary")
    sc = make_scenario(Family.UNDERWATER, seed=4)
    good_map, good_sub = out / "map.json", out / "submap.json"
    good_map.write_text(sc.map.model_dump_json())
    good_sub.write_text(sc.submap.model_dump_json())
    deep = out / "deep.json"
    deep.write_text("[" * DEPTH + "]" * DEPTH)
    deep_field = out / "deep_field.json"
    deep_field.write_text('{"robot_id": ' + "[" * DEPTH + "]" * DEPTH + "}")
    long_int = out / "long_int.json"
    long_int.write_text('{"schema_version": ' + "7" * 5000 + "}")
    sub = json.loads(sc.submap.model_dump_json())
    sub["objects"][0]["n_obs"] = 10**100  # the model takes it, an int64 array cannot
    huge_n_obs = out / "huge_n_obs.json"
    huge_n_obs.write_text(json.dumps(sub))
    return {"map": good_map, "submap": good_sub, "deep": deep, "deep_field": deep_field,
            "long_int": long_int, "huge_n_obs": huge_n_obs}


def _one_line_exit_2(r: subprocess.CompletedProcess) -> str:
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    return lines[0]


@pytest.mark.parametrize("bad", ["deep", "long_int"])
def test_match_refuses_hostile_json_in_one_line(files: dict[str, Path], bad: str) -> None:
    line = _one_line_exit_2(run("match", "--map", str(files[bad]), "--submap",
                                str(files["submap"])))
    assert str(files[bad]) in line
    line = _one_line_exit_2(run("match", "--map", str(files["map"]), "--submap",
                                str(files[bad]), "--json"))
    assert str(files[bad]) in line


def test_match_refuses_a_number_too_large_for_its_array(files: dict[str, Path]) -> None:
    line = _one_line_exit_2(run("match", "--map", str(files["map"]), "--submap",
                                str(files["huge_n_obs"])))
    assert "huge_n_obs.json" in line


def test_codec_encode_refuses_hostile_json_in_one_line(files: dict[str, Path],
                                                       tmp_path: Path) -> None:
    for bad in ("deep_field", "long_int"):
        _one_line_exit_2(run("codec", "encode", str(files[bad]), str(tmp_path / "out.bin")))


@pytest.mark.parametrize("bad", ["deep", "deep_field", "long_int"])
def test_load_model_maps_parser_limits_to_decode_errors(files: dict[str, Path], bad: str) -> None:
    for model in (ObjectMap, Submap):
        with pytest.raises(DecodeError, match="not usable JSON"):
            load_model(model, files[bad])


def test_load_model_still_reads_good_files_and_refuses_bad_ones(files: dict[str, Path]) -> None:
    assert len(load_model(Submap, files["submap"]).objects) > 0
    with pytest.raises(SchemaError, match="too large"):
        load_model(Submap, files["huge_n_obs"])
