"""`bench scale` on a tiny plan: a child process per map, both thread modes, accuracy and
recall reported (never a wall-clock assertion)."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from mergesvc.bench.scale import THREAD_MODES, ScalePlan, markdown_table, run_scale
from mergesvc.bench.scoring import peak_rss_mb
from mergesvc.cli import app


def test_a_tiny_scale_run_reports_every_cell(tmp_path: Path) -> None:
    plan = ScalePlan({400: (3, 60)}, cases=2, large_cases=1, repeats=1, dim=32)
    work = tmp_path / "not" / "made"  # made by the run (a user's --work-dir need not exist)
    report = run_scale(plan, echo=lambda _: None, work_dir=work)
    res = report["maps"]["400"]
    assert set(res["cells"]) == {"3", "60"}
    for cell in res["cells"].values():
        assert set(cell["latency_ms"]) == set(THREAD_MODES)
        assert cell["latency_ms"]["default"]["runs"] == cell["latency_ms"]["1"]["runs"]
        assert cell["peak_rss_mb"] > 0 and cell["cpu_ms_p50"] > 0
    # the 60-object submap goes through windows and comes out right
    assert res["cells"]["60"]["node_accuracy"] >= 0.9
    assert res["cells"]["60"]["recall"]["recall_at_k"] == 1.0  # exact search: exact top-k
    assert "| 400 | 2-5 |" in markdown_table(report)
    assert 0 < res["rss_end_shared_mb"] < res["rss_end_mb"]  # the libraries at least
    assert not list(work.iterdir())  # the worlds' files are gone


def test_the_command_refuses_map_sizes_outside_its_plan() -> None:
    res = CliRunner().invoke(app, ["bench", "scale", "--quick", "--map-size", "7"])
    assert res.exit_code == 2 and "not in the plan" in res.output


def test_a_spawned_child_reports_its_own_peak_memory_not_its_parents() -> None:
    """The children of `bench scale` are spawned by a parent that has just built a world:
    their peak must be theirs (ru_maxrss kept the parent's across the exec)."""
    held = np.ones(400 * 2**20 // 8)  # 400 MB resident in the parent
    parent = peak_rss_mb()
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        child = pool.apply(peak_rss_mb)
    assert held.sum() > 0 and parent > 400 and child < parent - 300, (parent, child)
