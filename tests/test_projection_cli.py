"""`mergesvc projection make|show|check` (cli/projection.py) and `codec encode --profile
compact`, which needs the projection they make: real files, the commands in-process."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mergesvc.cli import app
from mergesvc.fleet.demo import fleet_projection
from mergesvc.sim import Family, make_scenario
from mergesvc.wire import Projection, decode_message

runner = CliRunner()


def cli(*args: str):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("proj")
    sc = make_scenario(Family.UNDERWATER, 4)
    (out / "map.json").write_text(sc.map.model_dump_json())
    (out / "submap.json").write_text(sc.submap.model_dump_json())
    other = make_scenario(Family.UNDERWATER, 5).map.arrays().embeddings_nd
    np.save(out / "survey.npy", other)
    return out


def test_make_from_files_show_and_check(files: Path, tmp_path: Path) -> None:
    p = tmp_path / "fleet.npz"
    r = cli("projection", "make", p, "--from", files / "survey.npy", "--from",
            files / "map.json", "--k", "16", "--seed", "3")
    assert r.exit_code == 0, r.output
    proj = Projection.load(p)
    assert proj.k == 16 and proj.dim == 384 and proj.id in r.output
    assert f"serve --projection {p}" in r.output and f"agent --projection {p}" in r.output
    # the same inputs and seed: the same file; another subsample: another projection
    again = tmp_path / "again.npz"
    assert cli("projection", "make", again, "--from", files / "survey.npy", "--from",
               files / "map.json", "--k", "16", "--seed", "3").exit_code == 0
    assert Projection.load(again).id == proj.id
    sub = tmp_path / "sub.npz"
    assert cli("projection", "make", sub, "--from", files / "survey.npy", "--k", "16",
               "--max-samples", "20", "--seed", "1").exit_code == 0
    assert Projection.load(sub).id != proj.id

    shown = cli("projection", "show", p, "--json")
    assert shown.exit_code == 0, shown.output
    info = json.loads(shown.output)
    kept = float(np.sum(proj.scale_k.astype(np.float64) ** 2) / proj.fit_variance)
    assert info["id"] == proj.id and (info["dim"], info["k"]) == (384, 16)
    assert info["variance_kept"] == pytest.approx(kept, abs=1e-4) and 0 < kept < 1
    assert info["components_with_bits"] == 16 and info["budget_bits"] == 400
    assert "variance kept" in cli("projection", "show", p).output

    ok = cli("projection", "check", p, files / "submap.json", files / "map.json")
    assert ok.exit_code == 0, ok.output
    assert ok.output.count(": ok: ") == 2
    strict = cli("projection", "check", p, files / "submap.json", "--min-cosine", "0.999")
    assert strict.exit_code == 1 and ": NO: " in strict.output


def test_check_refuses_another_dimension_and_another_projections_message(
    files: Path, tmp_path: Path
) -> None:
    p, q = tmp_path / "p.npz", tmp_path / "q.npz"
    assert cli("projection", "make", p, "--from", files / "survey.npy", "--k", "8").exit_code == 0
    assert cli("projection", "make", q, "--from", files / "map.json", "--k", "8").exit_code == 0
    small = tmp_path / "small.npy"
    np.save(small, np.random.default_rng(0).normal(size=(5, 16)))
    r = cli("projection", "check", p, small)
    assert r.exit_code == 1 and "16-d embeddings, the projection is 384-d" in r.output
    coded = tmp_path / "sub.bin"
    enc = cli("codec", "encode", "--projection", q, files / "submap.json", coded)
    assert enc.exit_code == 0, enc.output
    r = cli("projection", "check", p, coded)
    assert r.exit_code == 1 and f"coded with projection {Projection.load(q).id}" in r.output
    assert cli("projection", "check", q, coded).exit_code == 0


def test_codec_encode_compact_needs_the_fleets_projection(files: Path, tmp_path: Path) -> None:
    """Without --projection: one line, exit 2, nothing written (it used to fit a one-off
    projection on the file, one the service does not have)."""
    out = tmp_path / "sub.bin"
    r = runner.invoke(app, ["codec", "encode", "--profile", "compact", str(files / "submap.json"),
                            str(out)])
    assert r.exit_code == 2
    assert r.output.count("\n") == 1 and "projection make" in r.output
    assert not out.exists() and not list(tmp_path.glob("projection-*"))
    # the other profiles need none; a factor coded compact needs none either
    assert cli("codec", "encode", "--profile", "int8", files / "submap.json", out).exit_code == 0
    assert decode_message(out.read_bytes())[0].profile.value == "int8"


def test_the_simulated_survey_is_the_demos_projection(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--survey underwater --seed S` fits on what the demo of seed S fits on (the same
    survey_embeddings; smaller here, the demo's is 4000 views)."""
    import mergesvc.fleet.demo as demo
    import mergesvc.sim

    p = tmp_path / "survey.npz"
    r = cli("projection", "make", p, "--survey", "underwater", "--seed", "2", "--samples", "60")
    assert r.exit_code == 0, r.output
    assert Projection.load(p).k == 59  # n - 1 components from 60 views
    monkeypatch.setattr(demo, "survey_embeddings",
                        lambda seed: mergesvc.sim.survey_embeddings(seed, samples=60))
    assert fleet_projection(2, tmp_path / "demo.npz").id == Projection.load(p).id
    assert cli("projection", "make", p, "--survey", "mars").exit_code == 2
    assert cli("projection", "make", p).exit_code == 2  # neither --from nor --survey
