"""Shared fixtures: seeded scenarios (generated, never downloaded), and an environment without
a developer's MERGESVC_* settings for every test."""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import typer.main
import typer.testing
from hypothesis import settings

from mergesvc.sim import Family, Scenario, make_scenario

# CI runs the property tests on a fixed set of examples (reproducible, never flaky); developers
# get fresh random examples on every run.
settings.register_profile("ci", derandomize=True, deadline=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

# typer's CliRunner builds the click command from the whole app (every command's signature) on
# each invoke: ~0.1 s of CPU, most of an in-process command's cost. The apps are not changed
# after import, so the command is built once per app and test process; each invoke still
# parses its arguments and makes its context afresh.
typer.testing._get_command = functools.cache(typer.main.get_command)

# `make test` runs `--dist loadgroup --no-loadscope-reorder`: each group runs on one worker, in
# the order below. A file is a group (its module fixtures built once), files that share an
# expensive session fixture are one group (built once, not once per worker), and the files
# whose tests share nothing costly go test by test, last, to even out the workers' ends. The
# heaviest groups start first (longest first, as measured with --durations=0). The groups are
# made by the scheduler below, not by xdist_group marks (pytest 9 ignores the node id suffix
# xdist 3.8 gives a marked test, so the marks group nothing).
SHARED_GROUPS = {
    "test_cli.py": "quick_demo", "test_view.py": "quick_demo",  # `demo --quick`, ~20 s
    "test_service_graph.py": "cost_stream", "test_service_memory.py": "cost_stream",
}
HEAVY_FIRST = ("quick_demo", "cost_stream", "test_bench_merge.py", "test_generalize.py",
               "test_cost_bench.py", "test_held.py", "test_service_limits.py", "test_vertical.py",
               "test_fuzz.py", "test_consistency.py", "test_service.py", "test_ngm.py",
               "test_burst.py", "test_soak.py")
TEST_BY_TEST = ("test_settings.py", "test_exact.py", "test_exact_qaplib.py")


def xdist_group_of(nodeid: str) -> str | None:
    """The group of a test (its file's, or the shared one); None: a group of its own."""
    name = nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
    return None if name in TEST_BY_TEST else SHARED_GROUPS.get(name, name)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        g = xdist_group_of(item.nodeid)
        if g is None:
            return len(HEAVY_FIRST) + 1
        return HEAVY_FIRST.index(g) if g in HEAVY_FIRST else len(HEAVY_FIRST)

    items.sort(key=rank)  # stable: collection order within a rank


@pytest.hookimpl(optionalhook=True)  # a hook of xdist's: none without it
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """--dist loadgroup: xdist's scope scheduling over the groups above (other modes: xdist's)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group_of(nodeid) or nodeid

    return GroupScheduling(config, log)


SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

SETTINGS_PREFIX = "MERGESVC_"


def strip_settings_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Remove every MERGESVC_* variable from os.environ (undone by `monkeypatch`). Processes a
    test starts inherit os.environ, so they run without them too."""
    for key in [k for k in os.environ if k.startswith(SETTINGS_PREFIX)]:
        monkeypatch.delenv(key)


@pytest.fixture(scope="session", autouse=True)
def _no_developer_settings_in_the_session() -> Iterator[None]:
    """Before any fixture: module- and session-scoped fixtures that start processes (a service
    under test) start them without a developer's MERGESVC_* variables."""
    with pytest.MonkeyPatch.context() as mp:
        strip_settings_env(mp)
        yield


@pytest.fixture(autouse=True)
def _no_developer_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    """A developer's MERGESVC_* variables reach no test (nor what a test starts); a variable
    one test sets (outside monkeypatch) does not reach the next."""
    strip_settings_env(monkeypatch)


@pytest.fixture(scope="session")
def kitti_scenario() -> Scenario:
    return make_scenario(Family.KITTI, seed=0)


@pytest.fixture(scope="session")
def small_kitti_scenario() -> Scenario:
    """Small enough for paper mode's dense K in a test (20 vs 60 objects)."""
    return make_scenario(Family.KITTI, seed=1, n_map=60, n_sub=12, n_outliers=0)


@pytest.fixture(scope="session")
def underwater_scenario() -> Scenario:
    return make_scenario(Family.UNDERWATER, seed=4, n_map=30, n_sub=5, n_outliers=1)


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """`mergesvc demo --quick --listen EP --view-save FILE.rrd`, run once for the session (the
    README's main job; its output, summary and recording are checked by tests/test_cli.py and
    tests/test_view.py): {"out", "stdout", "endpoint", "rrd"}."""
    from helpers import free_port, run_cli

    out = tmp_path_factory.mktemp("demo")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rrd = out / "demo.rrd"
    r = run_cli("demo", "--quick", "--out", str(out), "--listen", endpoint, "--view-save",
                str(rrd))
    assert r.returncode == 0, r.stdout + r.stderr
    return {"out": out, "stdout": r.stdout, "endpoint": endpoint, "rrd": rrd}


