"""One service per store file (store/lock.py): a second holder is refused in one line naming
the first's pid; the lock is free again once released; a store path that cannot take a store
says why. One fleet per store (Store.claim_fleet)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mergesvc.errors import ConfigError, StoreError
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


def test_a_store_belongs_to_the_fleet_whose_submaps_it_took(tmp_path: Path) -> None:
    """Another fleet's service on it is refused before it reads anything (its sessions and
    frame are not that fleet's); the same fleet, restarted, is served. A service that stored
    nothing (a typo in --fleet, a --seconds 0 start) leaves no mark."""
    from mergesvc.core.model import ObjectNode, Submap
    from mergesvc.fleet.config import ServiceConfig
    from mergesvc.fleet.service import MergeService

    store = tmp_path / "merge.db"
    with MergeService(ServiceConfig(fleet="typo", store=str(store)), None) as svc:
        assert svc.store.meta("fleet") is None
    objects = [ObjectNode(id=f"o{i}", position=(float(i), 0.0, 0.0), embedding=[1.0, 0.0],
                          variance=0.1) for i in range(3)]
    with MergeService(ServiceConfig(fleet="reef", store=str(store)), None) as svc:
        svc.ingest(Submap(robot_id="auv1", session_id="s0", seq=0, objects=objects))
        assert svc.store.meta("fleet") == "reef"
    told = (f"store {store} holds fleet reef's submaps, not wreck's: serve --fleet reef, or "
            "pick another --store for wreck")
    with pytest.raises(ConfigError, match=re.escape(told)):
        MergeService(ServiceConfig(fleet="wreck", store=str(store)), None).start()
    with MergeService(ServiceConfig(fleet="reef", store=str(store)), None) as svc:
        assert svc.store.meta("fleet") == "reef"
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MERGESVC_")}
    r = subprocess.run([sys.executable, "-m", "mergesvc.cli", "serve", "--store", str(store),
                        "--fleet", "wreck", "--listen", "tcp/127.0.0.1:0", "--seconds", "5"],
                       capture_output=True, text=True, timeout=120, env=clean)
    assert r.returncode == 1 and r.stderr.strip().splitlines() == [f"error: {told}"], r.stderr
