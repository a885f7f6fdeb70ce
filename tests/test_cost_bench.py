"""`mergesvc bench cost` quick variant (about 150 factors, one run): a real MergeService (store
in a temporary folder, real GTSAM; `ingest` needs no Zenoh session) built as the CLI builds it,
the pool fleet's local maps from fleet/agent.py. Structural truths only, never wall-clock: the
factor target reached, both modes fed the same submaps and accepted the same factors,
per_submap solved after every submap that changed the graph, batched only at batch ends."""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pytest

from mergesvc.bench.cost import MODES, CostBenchPlan, plot_cost, run_cost_bench
from mergesvc.core.model import Submap
from mergesvc.core.tracking import Frame
from mergesvc.errors import InputError
from mergesvc.fleet.agent import build_submaps
from mergesvc.fleet.service import MergeService
from mergesvc.settings import Settings

TREE = Settings()


def make_service(store: str) -> MergeService:
    """The CLI's factory: the service section with its store in the benchmark's folder."""
    return MergeService(TREE.service.model_copy(update={"store": store}), session=None)


def build(robot: str, session: str, frames: Iterable[Frame]) -> list[Submap]:
    """The CLI's vehicles: the agent section, z up (the pool's vehicles have an AHRS)."""
    cfg = TREE.agent_config(robot).model_copy(update={"session": session})
    if cfg.up is None:
        cfg = cfg.model_copy(update={"up": (0.0, 0.0, 1.0)})
    return build_submaps(cfg, frames)[1]


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """`bench cost --quick --out --figure`, run once for the module: its JSON, the progress
    it reported (recorded on the way to the CLI's bar) and where the figure went."""
    from typer.testing import CliRunner

    import mergesvc.bench.cost as cost
    from mergesvc.cli import app

    out = tmp_path_factory.mktemp("cost") / "cost.json"
    calls: list[float] = []

    def recorded(*args: Any, progress: Any, **kw: Any) -> dict:
        def tick(msg: str, done: float) -> None:
            calls.append(done)
            progress(msg, done)
        return run_cost_bench(*args, progress=tick, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cost, "run_cost_bench", recorded)
        r = CliRunner().invoke(app, ["bench", "cost", "--quick", "--out", str(out), "--figure",
                                     str(out.with_suffix(".png"))])
    assert r.exit_code == 0, r.output
    rep = json.loads(out.read_text())
    rep["progress_calls"] = calls
    rep["figure"] = str(out.with_suffix(".png"))
    return rep


def test_the_factor_target_is_reached_within_the_bound(report: dict) -> None:
    plan = CostBenchPlan.quick()
    (run,) = report["runs"]
    bat, per = run["batched"], run["per_submap"]
    B = report["batch"]
    # batched: whole batches, stopped at the first batch end with the target reached
    assert bat["factors_accepted"] >= plan.target_factors
    assert bat["submaps"] <= plan.max_submaps and bat["submaps"] % B == 0
    assert bat["rows"][-B]["factors_before"] < plan.target_factors
    # per_submap: stopped at the first submap that reached it
    rows = per["rows"]
    assert per["factors_accepted"] >= plan.target_factors
    assert rows[-1]["factors_before"] < plan.target_factors
    assert rows[-1]["factors_before"] + rows[-1]["factors_added"] >= plan.target_factors
    # most submaps of revisiting vehicles yield factors
    assert sum(r["factors_added"] > 0 for r in rows) > len(rows) / 2
    assert all(v["target_factors_reached"] for v in report["verdict"].values())


def test_both_modes_ran_the_same_submaps_and_accepted_the_same_factors(report: dict) -> None:
    """per_submap fed the batched stream's first submaps (up to the target) and matched the
    same factors from each: when the graph is solved changes the cost, not the matches. Which
    of them the consistency sets trust at once may differ: each solve recalibrates the odometry
    noise their test uses (docs/uncertainty.md); the totals stay close."""
    (run,) = report["runs"]
    bat, per = run["batched"], run["per_submap"]
    n = per["submaps"]
    assert bat["submaps"] - report["batch"] < n <= bat["submaps"]
    key = [(r["robot"], r["session"], r["seq"]) for r in bat["rows"]]
    assert len(set(key)) == len(key)
    assert [(r["robot"], r["session"], r["seq"]) for r in per["rows"]] == key[:n]
    assert [r["factors_matched"] for r in per["rows"]] == [r["factors_matched"]
                                                           for r in bat["rows"][:n]]
    sent_bat = sum(r["factors_added"] for r in bat["rows"][:n])
    assert per["factors_accepted"] == sum(r["factors_added"] for r in per["rows"])
    assert abs(per["factors_accepted"] - sent_bat) <= 0.05 * sent_bat, (per["factors_accepted"],
                                                                       sent_bat)


def test_per_submap_solves_after_every_submap_batched_once_per_batch(report: dict) -> None:
    (run,) = report["runs"]
    B = report["batch"]
    assert B == CostBenchPlan.quick().batch_size() == 10  # 5 Hz x 2 s
    per, bat = run["per_submap"], run["batched"]
    n = per["submaps"]
    # per_submap: every submap that added a factor was followed by its own solve
    assert all(r["solved"] for r in per["rows"] if r["factors_added"] > 0)
    assert per["solves"] == sum(r["solved"] for r in per["rows"])
    assert sum(r["factors_added"] > 0 for r in per["rows"]) <= per["solves"] <= n
    # batched: solves only at the end of a batch (or of the stream), at most one per batch
    assert all(i % B == B - 1 or i == n - 1 for i, r in enumerate(bat["rows"]) if r["solved"])
    assert bat["solves"] == sum(r["solved"] for r in bat["rows"]) <= math.ceil(n / B)
    assert bat["solves"] < per["solves"]


def test_costs_add_up_and_buckets_cover_every_submap(report: dict) -> None:
    (run,) = report["runs"]
    plan = CostBenchPlan.quick()
    for mode in MODES:
        res = run[mode]
        rows = res["rows"]
        total = sum(r["process_ms"] + r["solve_ms"] for r in rows)
        assert math.isclose(sum(r["amortized_ms"] for r in rows), total, rel_tol=1e-9)
        assert all(r["solve_ms"] == 0.0 for r in rows if not r["solved"])
        assert [b["bucket"] for b in res["buckets"]] == ["0-50", "50-100", "100+"]
        assert sum(b["n"] for b in res["buckets"]) == res["submaps"]
        assert all(b["n"] > 0 and b["p90_ms"] >= b["median_ms"] for b in res["buckets"])
        assert math.isfinite(res["ratio_last_first"])
        assert res["peak_rss_mb"] > 0
    assert set(report["summary"]) == set(MODES)
    assert "| 100+ |" in report["markdown"]
    assert "B = 10" in report["markdown"]
    # progress: rising, within the plan's 2 x runs mode-runs
    calls = report["progress_calls"]
    assert calls and calls == sorted(calls) and calls[-1] <= 2 * plan.runs


def test_figure(report: dict, tmp_path: Path) -> None:
    path = plot_cost(report, tmp_path / "cost.png", window=11)
    assert path.stat().st_size > 10_000


@pytest.mark.parametrize("change", [{"runs": 0}, {"robots": 1}, {"target_factors": 0},
                                    {"buckets": (0, 200, 100)}, {"buckets": (10, 100)},
                                    {"batch": 0}])
def test_bad_plans_are_input_errors(change: dict) -> None:
    plan = CostBenchPlan.quick()
    for k, v in change.items():
        setattr(plan, k, v)
    with pytest.raises(InputError):
        run_cost_bench(make_service, build, plan, echo=lambda _m: None)


def test_the_cli_writes_the_cost_figure(report: dict) -> None:
    """`bench cost --quick --figure`: the cost figure (and nothing of another bench's)."""
    assert Path(report["figure"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
