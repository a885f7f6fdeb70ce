"""One BLAS thread for small problems: inside a match the BLAS runs one thread, and its own
setting is back afterwards; large problems keep it."""

from __future__ import annotations

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
