"""One BLAS thread for small problems: inside a match the BLAS runs one thread, and its own
setting is back afterwards; large problems keep it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from threadpoolctl import threadpool_limits

import mergesvc.core.pipeline as pipeline
from mergesvc.core.threads import PIN_BELOW_PAIRS, blas_thread_counts, blas_threads


def test_small_problems_pin_the_blas_and_restore_it() -> None:
    with threadpool_limits(2, user_api="blas"):
        assert set(blas_thread_counts()) == {2}
        with blas_threads(20 * 900):
            assert set(blas_thread_counts()) == {1}
        assert set(blas_thread_counts()) == {2}
        with blas_threads(PIN_BELOW_PAIRS):
            assert set(blas_thread_counts()) == {2}


def test_a_blas_loaded_after_the_first_pin_is_pinned_too() -> None:
    import faiss  # noqa: F401  (brings its own BLAS: loaded here, after earlier pins)

    with threadpool_limits(2, user_api="blas"), blas_threads(100):
        assert set(blas_thread_counts()) == {1}


def test_the_narrow_listing_finds_every_blas_threadpoolctl_finds() -> None:
    import faiss  # noqa: F401  (a third BLAS, with a name of its own)
    from threadpoolctl import ThreadpoolController

    from mergesvc.core.threads import _BlasController

    def blas(controller: ThreadpoolController) -> set[str]:
        return {lib.filepath for lib in controller.lib_controllers if lib.user_api == "blas"}

    full, narrow = blas(ThreadpoolController()), blas(_BlasController())
    assert len(full) >= 2 and narrow == full


def test_a_narrow_listing_that_finds_no_blas_gives_way_to_the_full_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import mergesvc.core.threads as threads

    monkeypatch.setattr(threads, "_BLAS_NAMES", ("no such library",))
    assert not threads._BlasController().lib_controllers
    assert any(lib.user_api == "blas" for lib in threads._listing().lib_controllers)

    class Broken(threads._BlasController):  # a threadpoolctl whose hook the override breaks
        def _make_controller_from_path(self, *args, **kwargs) -> None:
            raise TypeError("unexpected")

    monkeypatch.setattr(threads, "_BLAS_NAMES", ("blas",))
    monkeypatch.setattr(threads, "_BlasController", Broken)
    assert any(lib.user_api == "blas" for lib in threads._listing().lib_controllers)


def test_the_match_command_lists_the_blas_before_it_times_the_match(
        monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    """`mergesvc match` lists the BLAS with its set-up: the match it times only switches it."""
    from helpers import run_cli

    import mergesvc.core.threads as threads

    listed: list[str] = []
    inner_listing, inner_match = threads._listing, pipeline.match

    def listing():
        listed.append("list")
        return inner_listing()

    def match(*args, **kwargs):
        listed.append("match")
        return inner_match(*args, **kwargs)

    monkeypatch.setattr(threads, "_controller", None)
    monkeypatch.setattr(threads, "_listing", listing)
    monkeypatch.setattr(pipeline, "match", match)
    assert run_cli("example", str(tmp_path), "--family", "underwater").returncode == 0
    r = run_cli("match", "--map", str(tmp_path / "map.json"), "--submap",
                str(tmp_path / "submap.json"), "--json")
    assert r.returncode == 0, r.stderr
    assert listed == ["list", "match"]
    threads.list_blas()  # nothing imported since: the list stands
    assert listed == ["list", "match"]


def test_match_runs_on_one_thread(monkeypatch: pytest.MonkeyPatch, small_kitti_scenario) -> None:
    seen: list[list[int]] = []
    inner = pipeline._match_verified

    def spy(*args, **kwargs):
        seen.append(blas_thread_counts())
        return inner(*args, **kwargs)

    monkeypatch.setattr(pipeline, "_match_verified", spy)
    with threadpool_limits(2, user_api="blas"):
        pipeline.match(small_kitti_scenario.map, small_kitti_scenario.submap)
        assert set(blas_thread_counts()) == {2}
    assert seen and set(seen[0]) == {1}


def test_the_command_line_starts_without_the_numeric_stack() -> None:
    code = ("import sys, mergesvc.cli; heavy = [m for m in ('numpy', 'scipy', 'gtsam', "
            "'pydantic', 'faiss', 'zenoh') if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == ""


_SPIN_PROBE = """
import os, time
import mergesvc  # first, as the CLI and the service do
import numpy as np
from mergesvc.core.threads import blas_threads
main = str(os.getpid())
def ticks():
    out = {}
    for tid in os.listdir("/proc/self/task"):
        st = open(f"/proc/self/task/{tid}/stat").read().split()
        out[tid] = int(st[13]) + int(st[14])
    return out
q, e = np.ones((2200, 384), dtype=np.float32), np.ones((900, 384), dtype=np.float32)
b, c = np.ones((64, 64)), np.ones((300, 40))
before = ticks()
for _ in range(10):
    q @ e.T  # a product on two BLAS threads (a whole-map search)
    end = time.perf_counter() + 0.05
    while time.perf_counter() < end:  # then small matches, each pinned to one thread
        with blas_threads(20 * 900):
            b @ b, c.T @ c
after = ticks()
print(sum(after[t] - before.get(t, 0) for t in after if t != main))
"""


@pytest.mark.skipif(os.cpu_count() == 1 or not os.path.exists("/proc/self/task"),
                    reason="needs two cores and Linux /proc")
def test_blas_threads_do_not_spin_through_the_small_work_after_a_product() -> None:
    """OpenBLAS's workers spin for 2^28 cycles after each threaded call, taking a core from
    the pinned small matches that follow (measured: 58 clock ticks of the run's 118 without
    the setting, 7 with); mergesvc shortens that when it loads first, unless told otherwise."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    env["OPENBLAS_NUM_THREADS"] = "2"
    out = subprocess.run([sys.executable, "-c", _SPIN_PROBE], env=env, capture_output=True,
                         text=True, timeout=120, check=True)
    assert int(out.stdout.split()[-1]) <= 20, out.stdout  # of ~50 ticks of small work
