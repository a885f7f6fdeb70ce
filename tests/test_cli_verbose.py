"""`-v` is the command tree's flag; `mergesvc main()` accepts it after the command too."""

from __future__ import annotations

import subprocess
import sys

from typer.testing import CliRunner

from mergesvc.cli import app, hoist_verbose


def test_verbose_flags_move_to_the_front_and_nothing_else_moves() -> None:
    assert hoist_verbose(["serve", "-v", "--fleet", "f"]) == ["-v", "serve", "--fleet", "f"]
    assert hoist_verbose(["agent", "--robot", "a", "-vv", "--verbose"]) == [
        "-vv", "--verbose", "agent", "--robot", "a"]
    # after "--" everything is an argument; "-vx" and "-V" are not the flag
    assert hoist_verbose(["match", "--", "-v"]) == ["match", "--", "-v"]
    assert hoist_verbose(["x", "-vx", "-V"]) == ["x", "-vx", "-V"]
    assert hoist_verbose([]) == []


def test_a_verbose_flag_after_the_command_is_accepted() -> None:
    runner = CliRunner()
    assert runner.invoke(app, ["config", "--dump", "-v"]).exit_code == 2  # typer alone
    r = runner.invoke(app, hoist_verbose(["config", "--dump", "-v"]))
    assert r.exit_code == 0, r.output


def test_the_installed_entry_point_hoists(tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "config", "--dump", "-vv"],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert '"match"' in r.stdout
