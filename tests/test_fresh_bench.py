"""`bench match`'s fresh processes (bench/fresh.py): real `mergesvc match` processes whose
answers are checked against the in-process ones; a settings file when the settings are not
the defaults; one line when the command fails."""

from __future__ import annotations

from pathlib import Path

import pytest

from mergesvc.bench.fresh import child_env, run_cli_match, run_fresh
from mergesvc.core.config import match_config
from mergesvc.core.pipeline import match
from mergesvc.errors import MergeError


def test_settings_other_than_the_defaults_reach_the_process(underwater_scenario) -> None:
    sc = underwater_scenario
    # a setting that changes the answer: more matches needed than the submap holds
    cfg = match_config(verify={"min_matches": 10, "min_matches_vertical": 10})
    default = match(sc.map, sc.submap, match_config())
    strict = match(sc.map, sc.submap, cfg)
    assert default.result.accepted and not strict.result.accepted
    # the processes answer as `strict` did, not as the defaults would have
    got = run_fresh([(sc, strict)], cfg, runs=1)
    assert got["runs"] == 2 and got["same_answers"] == 2
    # and a process on the defaults (flags, no file) is counted as answering otherwise
    assert run_fresh([(sc, strict)], match_config(), runs=1)["same_answers"] == 0


def test_a_failed_command_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(MergeError, match=r"`mergesvc match` failed on .*: error: cannot read"):
        run_cli_match(tmp_path, ["--affinity", "ucos"], one_thread=True)


def test_the_default_threads_are_the_librarys(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    monkeypatch.setenv("MERGESVC_MATCH__SEED", "3")
    default, one = child_env(False), child_env(True)
    assert "OPENBLAS_NUM_THREADS" not in default and "MERGESVC_MATCH__SEED" not in default
    assert one["OPENBLAS_NUM_THREADS"] == one["OMP_NUM_THREADS"] == "1"
    assert "MERGESVC_MATCH__SEED" not in one and default["PATH"] == one["PATH"]
