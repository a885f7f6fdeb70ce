"""The first match in a fresh process, as a user of `mergesvc match --json` gets it.

Each scenario's map and submap are written as JSON files, and `python -m mergesvc.cli match
--json` runs on them in a new process, with the BLAS's default threads (those variables
removed) and again with OPENBLAS_NUM_THREADS (and OMP_, MKL_) set to 1. Measured: the
match's own total from the JSON's `timings_ms` (what follows the files' loading) and the
process's wall time (start-up, imports and loading included). Every answer is checked
against the in-process one: the same acceptance and the same pairs, or the row says how many
differ.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mergesvc.bench.scoring import _spread, check_count
from mergesvc.core.config import MatchConfig, match_config
from mergesvc.core.pipeline import MatchOutcome
from mergesvc.errors import MergeError
from mergesvc.sim import Scenario

_ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_TIMEOUT_S = 300.0


def _pairs(matches: Sequence[Any]) -> list[tuple[str, str]]:
    return sorted((m["submap_object"], m["map_object"]) if isinstance(m, dict)
                  else (m.submap_object, m.map_object) for m in matches)


def run_cli_match(folder: Path, options: Sequence[str], one_thread: bool
                  ) -> tuple[dict[str, Any], float]:
    """One `mergesvc match --json` process (with `options`) on folder/map.json and
    folder/submap.json: (its JSON, wall ms). MergeError with the command's own error line
    when it fails."""
    command = [sys.executable, "-m", "mergesvc.cli", "match", "--map", str(folder / "map.json"),
               "--submap", str(folder / "submap.json"), *options, "--json"]
    start = time.perf_counter()
    try:
        done = subprocess.run(command, capture_output=True, text=True, env=child_env(one_thread),
                              timeout=_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise MergeError(f"`mergesvc match` on {folder} took over {_TIMEOUT_S:.0f} s") from None
    except OSError as exc:
        raise MergeError(f"cannot start `mergesvc match`: {exc}") from exc
    wall = (time.perf_counter() - start) * 1e3
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise MergeError(f"`mergesvc match` failed on {folder}: {last}")
    try:
        answer = json.loads(done.stdout)
        float(answer["timings_ms"]["total"])
    except (ValueError, KeyError, TypeError) as exc:
        raise MergeError(f"`mergesvc match` on {folder} printed no answer: "
                         f"{done.stdout.strip()[:200]!r}") from exc
    return answer, wall


def child_env(one_thread: bool) -> dict[str, str]:
    """The environment of a fresh process: this one's without MERGESVC_* (the settings go as
    flags or a file) and without the BLAS's thread variables (the library's own default), or
    with them at 1 (`one_thread`)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("MERGESVC_") and k not in _ONE_THREAD}
    if one_thread:
        env.update(_ONE_THREAD)
    return env


def run_fresh(
    cases: Sequence[tuple[Scenario, MatchOutcome]], config: MatchConfig, runs: int = 1
) -> dict[str, Any]:
    """`runs` fresh processes per case and thread setting (interleaved); `cases` pairs each
    scenario with its in-process outcome under `config`. Returns the spreads of the JSON's
    total and of the wall time per thread setting, and how many answers equal the
    in-process ones."""
    check_count("fresh process runs", runs)
    out: dict[str, Any] = {"runs": 0, "same_answers": 0}
    times: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="mergesvc-fresh-") as tmp:
        # the defaults but the affinity: a flag, as a user would type it (a settings file
        # loads the whole settings tree, ~1 s more of wall time)
        options = ["--affinity", config.affinity.kind]
        if config != match_config(affinity={"kind": config.affinity.kind}):
            settings = Path(tmp) / "match.json"
            settings.write_text(config.model_dump_json())
            options = ["--settings", str(settings)]
        for k, (sc, outcome) in enumerate(cases):
            folder = Path(tmp) / f"case{k}"
            folder.mkdir()
            (folder / "map.json").write_text(sc.map.model_dump_json())
            (folder / "submap.json").write_text(sc.submap.model_dump_json())
            want = (bool(outcome.result.accepted), _pairs(outcome.result.matches))
            for _ in range(runs):
                for label, one in (("default", False), ("1 thread", True)):
                    got, wall = run_cli_match(folder, options, one)
                    times.setdefault(f"{label} match", []).append(
                        float(got["timings_ms"]["total"]))
                    times.setdefault(f"{label} wall", []).append(wall)
                    out["runs"] += 1
                    out["same_answers"] += (bool(got["accepted"]), _pairs(got["matches"])) \
                        == want
    out["ms"] = {k: _spread(v) for k, v in times.items()}
    return out


def markdown_fresh(fresh: dict[str, dict[str, Any]]) -> str:
    """The fresh-process rows, one per family / affinity: p50 [min-max] ms."""
    lines = ["| first match in a fresh process | same answers | match ms, default threads "
             "| match ms, 1 thread | process wall ms, default | wall ms, 1 thread |",
             "|---|---|---|---|---|---|"]
    for key, r in fresh.items():
        cells = [f"{s['median']:.1f} [{s['min']:.1f}-{s['max']:.1f}]" for s in (
            r["ms"][k] for k in ("default match", "1 thread match", "default wall",
                                 "1 thread wall"))]
        lines.append(f"| {key} | {r['same_answers']}/{r['runs']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


__all__ = ["child_env", "markdown_fresh", "run_cli_match", "run_fresh"]
