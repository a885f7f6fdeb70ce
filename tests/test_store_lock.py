"""One service per store file (store/lock.py): a second holder is refused in one line naming
the first's pid; the lock is free again once released; a store path that cannot take a store
says why."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mergesvc.errors import StoreError
from mergesvc.store.lock import held_store


def test_a_second_holder_is_refused_until_the_first_lets_go(tmp_path: Path) -> None:
    store = tmp_path / "merge.db"
    taken = rf"in use by another service \(pid {os.getpid()}\)"
    with held_store(store), pytest.raises(StoreError, match=taken), held_store(store):
        pass
    assert not (tmp_path / "merge.db.lock").exists()  # removed as it was let go
    with held_store(store):  # free again
        assert (tmp_path / "merge.db.lock").read_text() == f"{os.getpid()}\n"
    (tmp_path / "killed.db.lock").write_text("999999\n")  # left by a holder killed -9
    with held_store(tmp_path / "killed.db"):  # its lock died with it: taken over
        pass
    with held_store(":memory:"), held_store(":memory:"):  # nothing to share
        pass


@pytest.mark.parametrize(("where", "text"), [
    ("missing/merge.db", "no folder"), ("a_folder", "is a folder")])
def test_a_store_path_that_cannot_take_a_store_says_why(tmp_path: Path, where, text) -> None:
    (tmp_path / "a_folder").mkdir()
    with pytest.raises(StoreError, match=text), held_store(tmp_path / where):
        pass


def test_serve_on_a_store_another_service_holds_fails_in_one_line(tmp_path: Path) -> None:
    store = tmp_path / "merge.db"
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    with held_store(store):
        r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "serve", "--store", str(store),
                            "--listen", "tcp/127.0.0.1:0", "--seconds", "5"],
                           capture_output=True, text=True, timeout=120, env=clean)
    assert r.returncode == 1 and r.stderr.strip().splitlines() == [
        f"error: store {store} is in use by another service (pid {os.getpid()}): stop it or "
        "pick another --store"]
