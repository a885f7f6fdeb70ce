"""The live view: a FleetScene drawn into a Rerun recording (native viewer, web viewer or an
.rrd file) as submaps, factors and the service's status come in. Rerun is an optional extra
(`pip install mergesvc[view]`), imported only here, when a view is opened.

Entities: `world` (right-handed, z up) with each session's odometry, merged poses, keyframes and
objects under `world/robots/{robot}/{session}/`, the fused map, the correspondences and the
factors (accepted, retracted); `latency/...` and `counts/...` scalars; an `events` text log.
Timelines: `submap` (how many submaps the view has seen) and `time` (seconds since the view
opened, from its clock). Every entity path: docs/view.md.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import gtsam
import numpy as np

from mergesvc.core.model import Factor, FactorStatus, Submap
from mergesvc.errors import ConfigError, MergeError
from mergesvc.fleet.sessions import session_up
from mergesvc.view.scene import RETRACTED_RGB, FleetScene, Segments

if TYPE_CHECKING:
    from mergesvc.fleet.service import MergeService

log = logging.getLogger(__name__)

APPLICATION_ID = "mergesvc"
INSTALL_HINT = "pip install mergesvc[view]"
CORRESPONDENCE_RGB = (200, 200, 200)
FACTOR_RGB = (255, 255, 255)
FUSED_RGB = (150, 150, 150)
BACKGROUND_RGB = (18, 22, 28)


def require_rerun() -> Any:
    """The rerun module, or ConfigError saying how to install it."""
    try:
        import rerun
    except ImportError as exc:
        raise ConfigError(f"the live view needs rerun-sdk: {INSTALL_HINT}") from exc
    return rerun


@dataclass(frozen=True)
class ViewSink:
    """Where a view goes: an .rrd file (`save`), a web viewer (`web`: a gRPC server on
    `bind_ip`:`grpc_port` and the web viewer's page on `web_port`, which rerun serves on every
    interface), or else a native viewer spawned on `grpc_port`. `save` and `web` may go
    together."""

    save: Path | None = None
    web: bool = False
    bind_ip: str = "0.0.0.0"
    web_port: int = 9090
    grpc_port: int = 9876
    open_browser: bool = False


def blueprint(rr: Any) -> Any:
    """The default layout: the 3-D map on a dark background, beside it latency, counts and
    events; the time panel follows the `submap` timeline as data comes in."""
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="merged map", background=BACKGROUND_RGB),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="latency", name="latency (ms)"),
                rrb.TimeSeriesView(origin="counts", name="submaps and factors"),
                rrb.TextLogView(origin="events", name="events"),
            ),
            column_shares=[3, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="submap", play_state="following", state="collapsed"),
    )


def _check_port_free(ip: str, port: int) -> None:
    """rerun's gRPC server only logs a port in use and goes on without a server: refuse it
    here instead (ConfigError)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((ip, port))
        except OSError as exc:
            raise ConfigError(f"cannot serve the rerun view on port {port}: {exc}") from exc


def open_recording(sink: ViewSink, recording_id: str | None = None) -> tuple[Any, str | None]:
    """A Rerun recording stream sending to `sink`; returns it and the web viewer's URL (None
    unless `sink.web`)."""
    rr = require_rerun()
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    bp = blueprint(rr)
    url = None
    try:
        if sink.web:
            _check_port_free(sink.bind_ip, sink.grpc_port)
            server = rr.GrpcServerSink(bind_ip=sink.bind_ip, port=sink.grpc_port)
            sinks = [server] if sink.save is None else [server, rr.FileSink(str(sink.save))]
            rec.set_sinks(*sinks, default_blueprint=bp)
            rr.serve_web_viewer(web_port=sink.web_port, open_browser=sink.open_browser,
                                connect_to=server.uri)
            here = server.uri.replace("//0.0.0.0:", "//127.0.0.1:")  # what a browser here opens
            url = f"http://127.0.0.1:{sink.web_port}/?url={quote(here, safe=':/')}"
        elif sink.save is not None:
            rec.save(str(sink.save), default_blueprint=bp)
        else:
            rec.spawn(port=sink.grpc_port, default_blueprint=bp)
    except (OSError, RuntimeError, ValueError) as exc:  # rerun's own, mapped at the boundary
        raise ConfigError(f"cannot open the rerun view: {exc}") from exc
    return rec, url


class LiveView:
    """Draws a FleetScene into a Rerun recording as it changes.

    Feed it with `on_submap`, `on_factor` and `on_status` (the network: view/feed.py), or with
    `update_from_service(service)` (a MergeService in this process). Thread-safe."""

    def __init__(self, recording: Any, clock: Callable[[], float] = time.monotonic,
                 scene: FleetScene | None = None) -> None:
        self.rr = require_rerun()
        self.rec = recording
        self.clock = clock
        self.scene = scene or FleetScene()
        self._t0 = clock()
        self._lock = threading.RLock()
        self._service_rows: set[int] = set()
        self._service_latency = 0  # latencies of MergeService.stats already drawn
        self.url: str | None = None  # the web viewer's, when open() served one
        # which way is up in the world (the anchor's frame) is learned from the vehicles'
        # declared gravity (`_declare_up`); nothing is assumed before (KITTI's camera axes
        # have y down)
        self._up_axis: str | None = None

    @classmethod
    def open(cls, sink: ViewSink, clock: Callable[[], float] = time.monotonic,
             recording_id: str | None = None) -> LiveView:
        rec, url = open_recording(sink, recording_id)
        view = cls(rec, clock)
        view.url = url
        return view

    # ------------------------------------------------------------------ input

    def on_submap(self, sub: Submap, *, timed: bool = True) -> None:
        """A submap as a vehicle sent it. `timed`: it is arriving now (its factors' delay is
        measured from now: latency/submap_to_factor_ms)."""
        with self._lock:
            name = self.scene.add_submap(sub, self.clock() if timed else None)
            self._tick()
            self._event(f"submap {name} seq {sub.seq} keyframe {sub.keyframe}: "
                        f"{len(sub.objects)} objects", "DEBUG")
            self._draw_session(name)
            self._draw_links()
            self._count("submaps", self.scene.submaps_seen)
            self._declare_up()

    def _declare_up(self) -> None:
        """Once the world's session (the first seen: the anchor's, drawn in its own frame)
        has a keyframe that declared `up`, tell the viewer the axis nearest to it."""
        if self._up_axis is not None or not self.scene.sessions:
            return
        st = next(iter(self.scene.sessions.values()))
        up = session_up(st, st.propagate({0: gtsam.Pose3()}))
        if up is None:
            return
        i = int(np.argmax(np.abs(up)))
        self._up_axis = f"RIGHT_HAND_{'XYZ'[i]}_{'UP' if up[i] > 0 else 'DOWN'}"
        self.rec.log("world", getattr(self.rr.ViewCoordinates, self._up_axis), static=True)

    def on_factor(self, factor: Factor, *, timed: bool = True) -> None:
        """A factor message as the service sent it (accepted, or retracted); `timed`: it is
        arriving now."""
        with self._lock:
            before = self.scene.factors.get(factor.factor_id)
            delay_s = self.scene.add_factor(factor, self.clock() if timed else None)
            if self.scene.factors[factor.factor_id] is before:
                return  # the copy sent to the other robot
            self._tick()
            retracted = factor.status is FactorStatus.RETRACTED
            self._event(f"factor {factor.factor_id} {'retracted' if retracted else 'accepted'}"
                        f" ({len(factor.correspondences)} correspondences)",
                        "WARN" if retracted else "INFO")
            if delay_s is not None:
                self.rec.log(["latency", "submap_to_factor_ms", factor.robot_b],
                             self.rr.Scalars(delay_s * 1e3))
            self._draw_links()
            self._count_factors()

    def on_status(self, status: Mapping[str, Any]) -> None:
        """The service's status (its JSON): merged keyframe poses, anchor, latency."""
        with self._lock:
            self.scene.set_merged(status.get("keyframe_poses") or {}, status.get("anchor"))
            self._tick()
            for name in list(self.scene.sessions):
                self._draw_session(name)
            self._draw_links()
            for q, v in (status.get("latency_ms") or {}).items():
                if isinstance(v, (int, float)) and np.isfinite(v):
                    self.rec.log(["latency", f"{q}_ms"], self.rr.Scalars(float(v)))

    def update_from_service(self, service: MergeService) -> None:
        """Catch up with a MergeService in this process: the submaps it has processed since
        the last call, its factors (with their status), its merged keyframe poses, the
        latency of each submap it processed, its fused global map."""
        from mergesvc.wire import decode_message

        with self._lock:
            for row in service.store.submaps():
                if row.row_id in self._service_rows or not row.processed:
                    continue
                self._service_rows.add(row.row_id)
                try:
                    _, sub = decode_message(row.payload, list(service.projections.values()))
                except MergeError as exc:  # the service stored it: it decoded it once
                    log.warning("view: stored submap %d undecodable: %s", row.row_id, exc)
                    continue
                if isinstance(sub, Submap):
                    self.on_submap(sub, timed=False)  # drawn after it was processed
            for stored in service.store.factors():
                factor = Factor.model_validate_json(stored.payload)
                status = FactorStatus(stored.status)
                self.on_factor(factor.model_copy(update={"status": status}), timed=False)
            self.on_status(service.status())
            lat = service.stats.latency_ms
            new = service.stats.submaps_processed - self._service_latency
            for ms in lat[len(lat) - min(new, len(lat)):]:
                self.rec.log("latency/service_ms", self.rr.Scalars(float(ms)))
            self._service_latency = service.stats.submaps_processed
            gmap, _ = service.global_map()
            if gmap is not None:
                self.rec.log("world/fused_objects", self.rr.Points3D(
                    np.asarray([o.position for o in gmap.objects], dtype=np.float64),
                    colors=FUSED_RGB, radii=0.12))

    def close(self) -> None:
        """Flush what was logged (a file sink is complete after this)."""
        with self._lock:
            self.rec.flush()
            self.rec.disconnect()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ drawing

    def _tick(self) -> None:
        self.rec.set_time("submap", sequence=self.scene.submaps_seen)
        self.rec.set_time("time", duration=self.clock() - self._t0)

    def _event(self, text: str, level: str) -> None:
        self.rec.log("events", self.rr.TextLog(text, level=level))

    def _count(self, what: str, n: int) -> None:
        self.rec.log(["counts", what], self.rr.Scalars(float(n)))

    def _count_factors(self) -> None:
        active, retracted = self.scene.active_factors(), self.scene.retracted_factors()
        self._count("factors_active", len(active))
        self._count("factors_retracted", len(retracted))
        self._count("factors_accepted", len(active) + len(retracted))

    def _draw_session(self, name: str) -> None:
        rr, sc = self.rr, self.scene
        st = sc.sessions[name]
        robot, session = st.frame.robot, st.frame.session
        base = ["world", "robots", robot, session]
        rgb = sc.color(robot)
        placed = sc.placed_poses(name)
        odo = sc.path_xyz_m(sc.odometry_poses(name))
        self.rec.log([*base, "odometry"], rr.LineStrips3D([odo], colors=rgb, radii=0.02))
        merged = sc.path_xyz_m(sc.merged_poses(name))
        if len(merged):
            self.rec.log([*base, "merged"], rr.LineStrips3D([merged], colors=rgb, radii=0.06))
        self.rec.log([*base, "keyframes"], rr.Points3D(
            sc.path_xyz_m(placed), colors=rgb, radii=0.08,
            labels=[str(k) for k in sorted(placed)], show_labels=False))
        objs = sc.objects(name, placed)
        self.rec.log([*base, "objects"], rr.Points3D(
            objs.position_xyz_m, colors=rgb, radii=0.2, labels=objs.ids, show_labels=False))

    def _lines(self, path: str, seg: Segments, rgb: tuple[int, int, int], radius: float) -> None:
        strips = [np.stack([a, b]) for a, b in zip(seg.start_xyz_m, seg.end_xyz_m)]
        self.rec.log(path, self.rr.LineStrips3D(strips, colors=rgb, radii=radius,
                                                labels=seg.labels or None, show_labels=False))

    def _draw_links(self) -> None:
        sc = self.scene
        self._lines("world/correspondences", sc.correspondences(), CORRESPONDENCE_RGB, 0.02)
        self._lines("world/factors/accepted", sc.factor_segments(False), FACTOR_RGB, 0.025)
        self._lines("world/factors/retracted", sc.factor_segments(True), RETRACTED_RGB, 0.05)


__all__ = [
    "APPLICATION_ID",
    "INSTALL_HINT",
    "LiveView",
    "ViewSink",
    "blueprint",
    "open_recording",
    "require_rerun",
]
