"""Shared fixtures: seeded scenarios (generated, never downloaded)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

from mergesvc.sim import Family, Scenario, make_scenario

# CI runs the property tests on a fixed set of examples (reproducible, never flaky); developers
# get fresh random examples on every run.
settings.register_profile("ci", derandomize=True, deadline=None)
if os.environ.get("CI"):
    settings.load_profile("ci")

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


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
