"""The live view (mergesvc/view, `mergesvc view`): a seeded fleet merged by a real MergeService,
recorded to .rrd and read back (entities and counts against the service's own state), the
same over real Zenoh sessions on 127.0.0.1 with the command as a process, and the web viewer's
page in headless Chromium (Debian's `chromium`; skipped where it is not installed)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from helpers import Inbox, free_port, wait_for, zenoh_config

from mergesvc.core.model import Factor, FactorStatus, Submap
from mergesvc.errors import ConfigError
from mergesvc.fleet.agent import AgentConfig, build_submaps
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.sim import fleet_world
from mergesvc.view import PALETTE, FleetScene, LiveView, ViewSink, require_rerun
from mergesvc.wire import Profile, encode_message, keys

rr = pytest.importorskip("rerun", reason="the view extra (rerun-sdk) is not installed")
from rerun.chunk import RrdReader  # noqa: E402  (after the skip)

ROBOTS = ("auv1", "auv2", "auv3")
FLEET = "view"
ROOT = keys.fleet_root(FLEET)
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def submaps() -> list[Submap]:
    """The demo's pool, one lap, three vehicles that know gravity: submaps in time order."""
    world = fleet_world(0, ROBOTS, laps=1)
    subs: list[Submap] = []
    for r in ROBOTS:
        subs += build_submaps(AgentConfig(robot=r, up=(0.0, 0.0, 1.0)), world.frames(r))[1]
    return sorted(subs, key=lambda s: (s.stamp or 0.0, s.robot_id))


def read_rrd(path: Path) -> tuple[dict[str, dict[str, Any]], Counter]:
    """entity path -> {component: value} of the last row logged to it (by row id, which rerun
    makes increasing), and how many rows each entity got."""
    last: dict[str, tuple[bytes, dict[str, Any]]] = {}
    rows: Counter = Counter()
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        data = [n for n in batch.schema.names if ":" in n]
        ids = batch.column("rerun.controls.RowId").to_pylist()
        for i, row_id in enumerate(ids):
            rows[chunk.entity_path] += 1
            if chunk.entity_path not in last or row_id > last[chunk.entity_path][0]:
                last[chunk.entity_path] = (row_id, {n: batch.column(n)[i].as_py() for n in data})
    return {e: v for e, (_, v) in last.items()}, rows


def assert_empty_recording(path: Path) -> None:
    """A valid recording of a view that saw no vehicle: rerun's own properties, no robot and no
    up axis (nothing is assumed until a vehicle declares its gravity: KITTI's y points down)."""
    last, _ = read_rrd(path)
    assert "/__properties" in last, last
    assert not any(e.startswith("/world") for e in last), last


def events(path: Path) -> list[str]:
    out = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == "/events":
            out += chunk.to_record_batch().column("TextLog:text").to_pylist()
    return [t for batch in out for t in batch]


def check_against_service(path: Path, svc: MergeService) -> dict[str, dict[str, Any]]:
    """The recording's last state is the service's: per session the objects, keyframes and
    merged keyframe poses; the factors in force and retracted; their correspondences."""
    last, _ = read_rrd(path)
    merged = svc.keyframe_poses()
    assert set(merged) == {f"{r}/s0" for r in ROBOTS}  # every vehicle aligned: a real merge
    for name, st in svc.sessions.items():
        base = f"/world/robots/{name}"
        assert len(last[f"{base}/objects"]["Points3D:positions"]) == len(st.objects)
        assert len(last[f"{base}/odometry"]["LineStrips3D:strips"][0]) == len(st.keyframes)
        strip = np.asarray(last[f"{base}/merged"]["LineStrips3D:strips"][0])
        want = np.stack([merged[name][k][:3, 3] for k in sorted(merged[name])])
        np.testing.assert_allclose(strip, want, atol=1e-4)  # float32 on the wire
    retracted = [f for f in svc.store.factors() if f.status == FactorStatus.RETRACTED]
    assert retracted, "the scenario must exercise retraction"
    assert len(last["/world/factors/accepted"]["LineStrips3D:strips"]) == len(svc.factors)
    assert len(last["/world/factors/retracted"]["LineStrips3D:strips"]) == len(retracted)
    pairs = last["/world/correspondences"]["LineStrips3D:strips"]
    assert len(pairs) == sum(len(f.correspondences) for f in svc.factors.values())
    # objects of different robots that the factors say are one object lie close in the merged
    # map (metres; they are seconds of drift apart in the vehicles' own frames)
    lengths = [np.linalg.norm(np.subtract(*seg)) for seg in pairs]
    assert np.median(lengths) < 1.0
    return last


def test_missing_rerun_says_how_to_install_it(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    with pytest.raises(ConfigError, match=r"pip install mergesvc\[view\]"):
        require_rerun()


def test_scene_keeps_one_copy_of_each_factor_and_its_latest_status(submaps) -> None:
    """The service sends a factor once per robot and again when GNC retracts it."""
    svc = MergeService(ServiceConfig(store=":memory:"), session=None)
    try:
        for s in submaps:
            svc.ingest(s)
        stored = svc.store.factors()
    finally:
        svc.close()
    scene = FleetScene()
    for s in submaps:
        scene.add_submap(s, arrived_s=0.0)
    first = [Factor.model_validate_json(f.payload) for f in stored]
    for f in first + first:  # both robots' copies
        scene.add_factor(f.model_copy(update={"status": None}), arrived_s=1.0)
    assert len(scene.active_factors()) == len(stored)
    gone = [f for f, row in zip(first, stored) if row.status == FactorStatus.RETRACTED]
    for f in gone:
        assert scene.add_factor(f.model_copy(update={"status": FactorStatus.RETRACTED}),
                                arrived_s=2.0) is None
    assert len(scene.retracted_factors()) == len(gone) > 0
    assert len(scene.factor_segments(retracted=True)) == len(gone)


def test_in_process_recording_reads_back(submaps, tmp_path) -> None:
    """A MergeService in this process fed submap by submap, the view catching up after each:
    the .rrd holds each robot's trajectories and objects, the factors and correspondences."""
    out = tmp_path / "inproc.rrd"
    svc = MergeService(ServiceConfig(store=":memory:"), session=None)
    try:
        with LiveView.open(ViewSink(save=out)) as view:
            for s in submaps:
                svc.ingest(s)
                view.update_from_service(svc)
        check_against_service(out, svc)
        _, rows = read_rrd(out)
        assert rows["/latency/service_ms"] == svc.stats.submaps_processed == len(submaps)
        assert rows["/world/fused_objects"] > 0
        texts = events(out)
        n_retracted = sum(f.status == FactorStatus.RETRACTED for f in svc.store.factors())
        assert sum(t.endswith("retracted") or " retracted " in t for t in texts) == n_retracted
        assert sum(t.startswith("submap ") for t in texts) == len(submaps)
    finally:
        svc.close()


def view_command() -> list[str]:
    """`mergesvc view` as a process."""
    return [sys.executable, "-m", "mergesvc.cli", "view"]


def _stop(p: subprocess.Popen, sig: int) -> int:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(p.pid, sig)
    try:
        return p.wait(timeout=30)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=10)
        raise


def test_view_command_records_a_fleet_over_zenoh(submaps, tmp_path) -> None:
    """`mergesvc view --save x.rrd` joins a fleet on loopback (a router, the service, vehicles
    publishing as agents do) and records what the network carries: the .rrd ends with the
    service's state."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    out, log = tmp_path / "zenoh.rrd", tmp_path / "view.out"
    with zenoh.open(zenoh_config("router", listen=ep)) as _router, \
            zenoh.open(zenoh_config("client", connect=ep)) as svc_s, \
            zenoh.open(zenoh_config("client", connect=ep)) as pub_s:
        from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

        svc = MergeService(ServiceConfig(fleet=FLEET, store=str(tmp_path / "svc.db")),
                           svc_s).start()
        inbox = Inbox()
        sub = pub_s.declare_subscriber(keys.all_factors(ROOT), inbox.handler)
        pubs: dict[str, Any] = {}
        with log.open("w") as fh:
            proc = subprocess.Popen(
                [*view_command(), "--fleet", FLEET, "--connect", ep, "--save", str(out),
                 "--duration", "120", "--status-period", "0.3"],
                stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            assert wait_for(lambda: "viewing fleet" in log.read_text(), 60.0), log.read_text()
            for r in ROBOTS:
                pubs[r] = declare_advanced_publisher(  # as an agent's (fleet/agent.py)
                    pub_s, keys.submap_key(ROOT, r, "s0"), cache=CacheConfig(max_samples=1000),
                    sample_miss_detection=MissDetectionConfig(heartbeat=0.5),
                    publisher_detection=True)
            for s in submaps:
                pubs[s.robot_id].put(encode_message(s, Profile.INT8, s.robot_id, s.seq))

            def sent() -> int:  # each factor goes to both its robots, and again if retracted
                return 2 * (svc.stats.factors_accepted + svc.stats.factors_retracted)

            def settled() -> bool:
                return (svc.stats.submaps_processed == len(submaps)
                        and len(inbox.keys) == sent())

            # the service solves its graph after a batch (retractions come then): settled
            # twice, a second apart; then the view has had the same factors through the router
            assert wait_for(settled, 60.0)
            time.sleep(1.0)
            assert wait_for(settled, 30.0)
            assert _stop(proc, signal.SIGINT) == 0, log.read_text()
            counts = json.loads(log.read_text().strip().splitlines()[-1])
            assert counts["submaps"] == len(submaps) and counts["undecodable"] == 0
            assert counts["factors"] == sent() and counts["statuses"] > 0
            check_against_service(out, svc)
        finally:
            if proc.poll() is None:
                _stop(proc, signal.SIGKILL)
            sub.undeclare()
            for p in pubs.values():
                p.undeclare()
            svc.close()


def test_view_duration_bounds_it_without_a_service(tmp_path) -> None:
    """No service, no vehicles: `--duration` ends the view, the file is a valid recording."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "empty.rrd"
    with zenoh.open(zenoh_config("router", listen=ep)):
        res = subprocess.run([*view_command(), "--fleet", FLEET, "--connect", ep, "--save",
                              str(out), "--duration", "1", "--status-period", "0.5"],
                             capture_output=True, text=True, timeout=90)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1])["submaps"] == 0
    assert f"warning: nothing of fleet {FLEET} came" in res.stderr, res.stderr  # said, once
    assert res.stderr.count("warning: nothing of fleet") == 1
    assert_empty_recording(out)


# ---------------------------------------------------------------------- the web viewer

SERVE = """
import sys, time
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.view import LiveView, ViewSink
from mergesvc.wire import decode_message
subs = [decode_message(bytes.fromhex(line))[1] for line in sys.stdin.readline().split()]
svc = MergeService(ServiceConfig(store=":memory:"), session=None)
view = LiveView.open(ViewSink(web=True, bind_ip="127.0.0.1", web_port=int(sys.argv[1]),
                              grpc_port=int(sys.argv[2])))
for s in subs:
    svc.ingest(s)
    view.update_from_service(svc)
print(view.url, flush=True)
sys.stdin.readline()  # until the test closes stdin
"""


def _window() -> str:
    """The page's size: the documentation's figure (VIEW_SCREENSHOT) at 1600 x 1000, else a
    smaller page, as software WebGL draws every pixel on the CPU."""
    return "1600,1000" if os.environ.get("VIEW_SCREENSHOT") else "800,500"


async def _screenshot(url: str, out: Path, drawn: Callable[[Path], bool],
                      timeout_s: float = 90.0) -> dict[str, Any]:
    """Open `url` in headless Chromium and drive it over the DevTools protocol (aiohttp, which
    pygmtools brings): wait until the viewer's canvas replaced the loading screen, then save a
    PNG every second until `drawn(PNG)` (or the time is up: the last one stays). Returns the
    page state it saw last."""
    import aiohttp

    port = free_port()
    profile = tempfile.mkdtemp(prefix="chromium-")
    chrome = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", f"--remote-debugging-port={port}",
         f"--user-data-dir={profile}", f"--window-size={_window()}", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + timeout_s
    try:
        async with aiohttp.ClientSession() as http:
            ws_url = None
            while ws_url is None and time.monotonic() < deadline:
                with contextlib.suppress(aiohttp.ClientError):
                    async with http.get(f"http://127.0.0.1:{port}/json/list") as r:
                        pages = [t for t in await r.json() if t["type"] == "page"]
                        ws_url = pages[0]["webSocketDebuggerUrl"] if pages else None
                await asyncio.sleep(0.2)
            assert ws_url, "chromium's DevTools endpoint did not come up"
            async with http.ws_connect(ws_url, max_msg_size=0) as ws:
                ids = iter(range(1, 10**6))

                async def call(method: str, **params: Any) -> dict[str, Any]:
                    mid = next(ids)
                    await ws.send_json({"id": mid, "method": method, "params": params})
                    while True:  # events of the page come in between: skip them
                        msg = await asyncio.wait_for(ws.receive_json(),
                                                     max(deadline - time.monotonic(), 1.0))
                        if msg.get("id") == mid:
                            return msg.get("result", {})

                await call("Page.enable")
                await call("Page.navigate", url=url)
                probe = ("JSON.stringify({canvas: !!document.querySelector('canvas'), "
                         "text: document.body ? document.body.innerText.trim() : 'loading'})")
                state: dict[str, Any] = {}
                while time.monotonic() < deadline:
                    res = await call("Runtime.evaluate", expression=probe, returnByValue=True)
                    value = res.get("result", {}).get("value")
                    state = json.loads(value) if value else {}
                    if state.get("canvas") and not state.get("text"):
                        break
                    await asyncio.sleep(0.5)
                while True:  # the wasm viewer streams and draws the recording: until it shows
                    await asyncio.sleep(1.0)
                    shot = await call("Page.captureScreenshot", format="png")
                    out.write_bytes(base64.b64decode(shot["data"]))
                    if drawn(out) or time.monotonic() > deadline - 5.0:
                        return state
    finally:
        chrome.terminate()
        try:
            chrome.wait(timeout=15)
        except subprocess.TimeoutExpired:
            chrome.kill()
            chrome.wait(timeout=5)
        shutil.rmtree(profile, ignore_errors=True)


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH: `apt-get install chromium` "
                    "(Debian's package) for this test")
def test_web_viewer_shows_the_merged_map_in_headless_chromium(submaps, tmp_path) -> None:
    """`--serve-web`'s sink: the page loads in headless Chromium (software WebGL), the viewer
    replaces its loading screen with its canvas, and the 3-D view draws every robot's colour.
    VIEW_SCREENSHOT=FILE keeps the screenshot (docs/figures/view.png)."""
    web, grpc = free_port(), free_port()
    server = subprocess.Popen([sys.executable, "-c", SERVE, str(web), str(grpc)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              start_new_session=True)
    shot = tmp_path / "view.png"
    try:
        server.stdin.write(" ".join(encode_message(s, Profile.FULL, s.robot_id, s.seq).hex()
                                    for s in submaps) + "\n")
        server.stdin.flush()
        url = server.stdout.readline().strip()  # after every submap was merged and logged
        assert url.startswith(f"http://127.0.0.1:{web}/?url="), url
        state = asyncio.run(_screenshot(url, shot, lambda png: all(
            n >= 20 for n in _robot_pixels(png).values())))
    finally:
        with contextlib.suppress(OSError):
            server.stdin.close()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            _stop(server, signal.SIGKILL)
    if os.environ.get("VIEW_SCREENSHOT"):
        shutil.copy(shot, os.environ["VIEW_SCREENSHOT"])
    assert state.get("canvas") and not state.get("text"), state  # loaded, no error page
    near = _robot_pixels(shot)
    assert all(n >= 20 for n in near.values()), near  # each robot's trajectory and objects


def _robot_pixels(png: Path) -> dict[tuple[int, int, int], int]:
    """Per robot's colour, the pixels of the screenshot within 12 levels of it."""
    from matplotlib.image import imread

    rgb = (imread(png)[..., :3] * 255).round().astype(int)
    near: dict[tuple[int, int, int], int] = defaultdict(int)
    for color in PALETTE[: len(ROBOTS)]:
        near[color] = int((np.abs(rgb - np.asarray(color)).max(axis=-1) <= 12).sum())
    return near


def test_demo_observer_attaches_to_a_session_and_closes_the_view(tmp_path) -> None:
    """The hook `mergesvc demo --view-save` hands run_demo: attach, then detach closes the
    recording (a valid file, no robots and no up axis: nothing was sent)."""
    from mergesvc.view import observer

    ep = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "demo.rrd"
    with zenoh.open(zenoh_config("router", listen=ep)) as session:
        view = LiveView.open(ViewSink(save=out))
        detach = observer(view, status_period_s=0.2)(session, FLEET, None)
        detach()
    assert_empty_recording(out)


def test_a_view_that_joins_late_gets_each_cached_submap_once(submaps, tmp_path) -> None:
    """Vehicles publish before the view joins: it gets what their publication caches hold,
    each submap once, though both zenoh-ext's history and the sweep of each publisher's cache
    bring it (the service's recovering subscription)."""
    from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

    from mergesvc.view.feed import ZenohFeed

    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=ep)) as _router, \
            zenoh.open(zenoh_config("client", connect=ep)) as pub_s, \
            zenoh.open(zenoh_config("client", connect=ep)) as view_s:
        pubs = {r: declare_advanced_publisher(  # as an agent's (fleet/agent.py)
            pub_s, keys.submap_key(ROOT, r, "s0"), cache=CacheConfig(max_samples=1000),
            sample_miss_detection=MissDetectionConfig(heartbeat=0.5),
            publisher_detection=True) for r in ROBOTS}
        for s in submaps:
            pubs[s.robot_id].put(encode_message(s, Profile.INT8, s.robot_id, s.seq))
        view = LiveView.open(ViewSink(save=tmp_path / "late.rrd"))
        feed = ZenohFeed(view, view_s, FLEET, status_period_s=30.0, status_timeout_s=0.2)
        try:
            feed.start()
            assert wait_for(lambda: feed.stats.submaps >= len(submaps), 30.0)
            time.sleep(1.5)  # a second copy of any would have come by now
            assert feed.stats.submaps == len(submaps) and feed.stats.undecodable == 0
        finally:
            feed.close()
            view.close()
            for p in pubs.values():
                p.undeclare()


def test_demo_view_save_records_the_demo(quick_demo: dict) -> None:
    """`mergesvc demo --quick --view-save FILE.rrd` (the session's demo, conftest.py): the demo
    runs as without it (tests/test_cli.py checks its output), and the recording holds every
    vehicle's session (objects, odometry, merged trajectory) and the factors it reports."""
    rrd = quick_demo["rrd"]
    summary = json.loads((quick_demo["out"] / "summary.json").read_text())
    last, _ = read_rrd(rrd)
    for robot in ("auv1", "auv2", "auv3"):
        base = f"/world/robots/{robot}/s0"
        assert last[f"{base}/objects"]["Points3D:positions"], robot
        assert last[f"{base}/odometry"]["LineStrips3D:strips"][0], robot
        assert f"{base}/merged" in last, robot
    accepted = last["/world/factors/accepted"]["LineStrips3D:strips"]
    retracted = last.get("/world/factors/retracted", {}).get("LineStrips3D:strips", [])
    assert len(accepted) + len(retracted) == summary["factors_accepted"]


@pytest.mark.parametrize(("up", "axes"), [((0.0, -1.0, 0.0), "RIGHT_HAND_Y_DOWN"),
                                          ((0.0, 0.0, 1.0), "RIGHT_HAND_Z_UP"),
                                          ((0.97, 0.1, 0.2), "RIGHT_HAND_X_UP")])
def test_the_view_takes_up_from_the_vehicles_not_from_a_convention(tmp_path, up, axes) -> None:
    """KITTI's camera axes (y down), the pool (z up), anything: the world's up axis is the one
    nearest the first session's declared gravity; before any, none is declared."""
    from mergesvc.core.model import ObjectNode

    objs = [ObjectNode(id=f"o{i}", position=(float(i), 0.0, 1.0), embedding=[1.0, float(i)],
                       variance=0.1) for i in range(3)]
    path = tmp_path / "up.rrd"
    view = LiveView.open(ViewSink(save=path))
    view.on_submap(Submap(robot_id="car1", session_id="s0", seq=0, keyframe=0, objects=objs))
    view.on_submap(Submap(robot_id="car1", session_id="s0", seq=1, keyframe=0, up=up,
                          objects=objs))
    view.close()
    last, rows = read_rrd(path)
    want = getattr(rr.ViewCoordinates, axes).as_arrow_array().to_pylist()
    assert last["/world"]["ViewCoordinates:xyz"] == want
    assert rows["/world"] == 1  # declared once
