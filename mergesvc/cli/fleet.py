"""Commands that run the fleet: `serve` (the merge service), `agent` (a vehicle), `demo`
(both, as processes on loopback), `export` (a service's store as g2o and TUM files), `link
sim|bridge` (the acoustic link).

Settings (mergesvc/settings.py): `serve` and `export` read the `service` section, `agent` the
`agent` section, `demo` hands its resolved tree to the processes it starts, `link sim` reads `link`
and `workload`; `link bridge` builds its link from its flags."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections.abc import Iterable, Iterator
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from mergesvc.cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, exit_on_error, fail
from mergesvc.cli.options import (
    DEFAULT_ENDPOINT,
    Connect,
    ConnectTimeout,
    FleetName,
    LinkKind,
    Listen,
    Mode,
    Progress,
    SettingsCommand,
    ZenohConfigFile,
    ZenohMode,
    bare_match_for,
    command_group,
    given,
    key_names,
    progress_lines,
    resolve_settings,
    settings_env,
    settings_file,
    stop_on_signals,
    write_settings_beside,
    zenoh_config,
    zenoh_connect,
    zenoh_mode,
)
from mergesvc.errors import ConfigError, MergeError
from mergesvc.wire.names import Profile

if TYPE_CHECKING:
    from mergesvc.core.tracking import Frame

link_app = command_group("the acoustic link simulator")


class FactorProfile(str, Enum):
    """The profiles a factor can be coded in (docs/wire.md §6)."""

    FULL = "full"
    COMPACT = "compact"


# the Zenoh flags with the help texts these commands have always shown
ConnectTo = zenoh_connect("zenoh endpoint(s) to connect")
AgentMode = zenoh_mode("zenoh mode")
BridgeMode = zenoh_mode("zenoh mode: router, peer or client")
# --settings of each command here: what it reads
ServeSettings = settings_file("`service`", bare="MatchConfig (its service.match)")
AgentSettingsFile = settings_file("`agent` (without robot: that is --robot)")
DemoSettings = settings_file(
    "`service` and `agent` (written to OUT/settings.json for the processes it starts)"
)
LinkSimSettings = settings_file("`link` and `workload`")
ExportSettings = settings_file("`service` (its `graph` solves, its `store` is the default "
                               "--store)", bare="MatchConfig (its service.match)")
# --ros2 and its options, the same on serve and agent (docs/ros2.md)
Ros2 = Annotated[bool, typer.Option("--ros2", help="also publish ROS 2 topics for rmw_zenoh "
                                                   "(docs/ros2.md; needs mergesvc[ros2])")]
Ros2Domain = Annotated[int, typer.Option(help="ROS_DOMAIN_ID of the ROS 2 topics")]
Ros2Namespace = Annotated[str, typer.Option(help="ROS 2 namespace of the topics (a vehicle's "
                                                 "get /<robot> below it)")]


@contextlib.contextmanager
def _ros2_bridge(on: bool, session: Any, fleet: str, domain_id: int, namespace: str,
                 service: Any = None, robot: str | None = None,
                 root: str | None = None) -> Iterator[None]:
    """With --ros2: a Ros2Bridge for the block (the service's outputs, or one vehicle's)."""
    if not on:
        yield
        return
    from mergesvc.ros2 import Ros2Bridge
    from mergesvc.ros2.names import join_topic, name_token

    if robot is not None:
        namespace, node = join_topic(namespace, name_token(robot)), "agent"
    else:
        node = "merge_service"
    with Ros2Bridge(session, fleet=fleet, service=service, root=root,
                    robots=None if robot is None else [robot], domain_id=domain_id,
                    namespace=namespace, node_name=node):
        yield


def serve(
    ctx: typer.Context,
    fleet: FleetName = "fleet0",
    store: Annotated[Path, typer.Option(help="SQLite file (WAL mode)")] = Path("mergesvc.db"),
    mode: Mode = ZenohMode.ROUTER,
    listen: Listen = None,
    connect: ConnectTo = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    projection: Annotated[
        list[Path] | None, typer.Option(help="fleet projection(s) for compact submaps")
    ] = None,
    settings: ServeSettings = None,
    seconds: Annotated[float | None, typer.Option(min=0.0, help="stop after this long")] = None,
    progress: Progress = 10.0,
    ros2: Ros2 = False,
    ros2_domain: Ros2Domain = 0,
    ros2_namespace: Ros2Namespace = "/mergesvc",
    factor_profile: Annotated[
        FactorProfile, typer.Option(help="how factors are coded: compact (a bit stream) or full "
                                         "(a msgpack map, for clients that do not decode "
                                         "compact) [default: the setting service.factor_profile]",
                                    show_default=False)
    ] = FactorProfile.COMPACT,
) -> None:
    """The merge service: embedded Zenoh router on tcp/127.0.0.1:7447 by default.

    Settings: the `service` section (a bare MatchConfig file is its `service.match`)."""
    from mergesvc.fleet.replies import status_line
    from mergesvc.fleet.service import MergeService
    from mergesvc.store.lock import held_store
    from mergesvc.wire import Projection
    from mergesvc.wire.session import open_session

    if mode is ZenohMode.ROUTER and not listen and not config:
        listen = [DEFAULT_ENDPOINT]
    stop = stop_on_signals()
    with exit_on_error(ValueError, OSError):
        flags = given(ctx, fleet=fleet, store=str(store), factor_profile=factor_profile)
        cfg = resolve_settings(settings, {"service": flags},
                               bare_match=bare_match_for(SettingsCommand.SERVE))
        cfg = cfg.service
        zconf = zenoh_config(mode, connect, listen, config, connect_timeout=connect_timeout)
        projections = [Projection.load(p) for p in projection or []]
        with held_store(cfg.store), open_session(zconf) as session, \
                MergeService(cfg, session, projections) as svc, \
                _ros2_bridge(ros2, session, cfg.fleet, ros2_domain, ros2_namespace, service=svc):
            typer.echo(f"merge service for fleet {cfg.fleet} on {listen or connect}, "
                       f"store {cfg.store}")
            start = time.monotonic()
            fresh = cfg.status_refresh_s <= 0  # else the figures' thread's last read
            with progress_lines(progress, lambda: status_line(svc.status(False, fresh))):
                while not stop.is_set() and (seconds is None
                                             or time.monotonic() - start < seconds):
                    stop.wait(0.2)
            typer.echo(json.dumps(svc.status()["submaps"]))


def export(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option(help="folder for graph.g2o, graph_nodes.json, "
                                            "export.json, factors.json, map.json and the TUM "
                                            "trajectories")],
    store: Annotated[
        Path | None, typer.Option(help="the service's SQLite file [default: the setting "
                                       "service.store]")
    ] = None,
    projection: Annotated[
        list[Path] | None, typer.Option(help="fleet projection(s): needed when the store "
                                             "holds compact submaps (serve's --projection)")
    ] = None,
    settings: ExportSettings = None,
) -> None:
    """Export a service's store: the pose graph (g2o) and each session's trajectory (TUM). The
    service is rebuilt from a copy of the store as a restart rebuilds it (the processed submaps,
    the factors in force): the store is never changed, a running service may keep writing.

    Settings: the `service` section, as serve reads it.

    Writes graph.g2o, graph_nodes.json (node ids), export.json, factors.json, map.json and TUMs.

    Prints one line per file written."""
    from mergesvc.fleet.export import export_store
    from mergesvc.wire import Projection

    with exit_on_error(ValueError, OSError):
        flags = given(ctx, store=str(store))
        cfg = resolve_settings(settings, {"service": flags},
                               bare_match=bare_match_for(SettingsCommand.SERVE)).service
        projections = [Projection.load(p) for p in projection or []]
        res = export_store(cfg.store, out, config=cfg, projections=projections)
    for f in res.files:
        typer.echo(str(f))


def _agent_frames(robot: str, session: str, seed: int, laps: int, objects: int,
                  log_file: Path | None) -> Iterable[Frame]:
    """The vehicle's frames: a recorded observation log, or its pass through the seeded fleet
    world (session `s<N>` re-enters on pass N)."""
    from mergesvc.sim import fleet_world, read_observation_log

    if log_file is not None:
        return read_observation_log(log_file)
    n = int(session[1:]) if session[:1] == "s" and session[1:].isdigit() else 0
    return fleet_world(seed, laps=laps, n_objects=objects).frames(robot, n)


def agent(
    ctx: typer.Context,
    robot: Annotated[str, typer.Option(help="this vehicle's name")],
    fleet: FleetName = "fleet0",
    session_id: Annotated[str, typer.Option("--session", help="this session's name")] = "s0",
    seed: Annotated[int, typer.Option(help="fleet world seed (scenario input)")] = 0,
    laps: Annotated[int, typer.Option(help="laps of the robot's pattern")] = 2,
    objects: Annotated[int, typer.Option(help="objects in the pool")] = 24,
    log_file: Annotated[
        Path | None, typer.Option("--log", help="replay a recorded observation log instead")
    ] = None,
    profile: Annotated[Profile, typer.Option(help="codec: full, f16, int8 or compact")] = (
        Profile.INT8
    ),
    projection: Annotated[Path | None, typer.Option(help="fleet projection (compact)")] = None,
    time_scale: Annotated[
        float, typer.Option(min=0.0, help="wall s per simulated s; 0: no pacing")] = 0.0,
    acoustic: Annotated[bool, typer.Option(help="publish on the acoustic vehicle side")] = False,
    mode: AgentMode = ZenohMode.CLIENT,
    connect: Connect = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    linger: Annotated[
        float, typer.Option(min=0.0, help="s to stay up after the run (factors)")] = 2.0,
    progress: Progress = 10.0,
    settings: AgentSettingsFile = None,
    ros2: Ros2 = False,
    ros2_domain: Ros2Domain = 0,
    ros2_namespace: Ros2Namespace = "/mergesvc",
) -> None:
    """A vehicle: local map (tracker + ISAM2), submaps out, factors in.

    Settings: the `agent` section."""
    from mergesvc.fleet.agent import AgentRun, AgentStats, run_agent

    if profile is Profile.COMPACT and projection is None:
        raise typer.BadParameter("--profile compact needs --projection")
    with exit_on_error():
        flags = given(ctx, fleet=fleet, session_id=session_id)
        if "session_id" in flags:
            flags["session"] = flags.pop("session_id")
        tree = resolve_settings(settings, {"agent": flags})
    try:
        acfg = tree.agent_config(robot)
    except ConfigError as exc:  # --robot is a flag: bad input
        fail(exc, EXIT_BAD_INPUT)
    run = AgentRun(
        robot=robot, fleet=acfg.fleet, session=acfg.session, profile=profile,
        projection=projection, time_scale=time_scale, acoustic=acoustic, linger_s=linger,
        config=acfg,
    )
    with exit_on_error(ValueError, OSError):
        frames = _agent_frames(robot, acfg.session, seed, laps, objects, log_file)
        zconf = zenoh_config(mode, connect, None, config, default_connect=(DEFAULT_ENDPOINT,),
                             connect_timeout=connect_timeout)
        with contextlib.ExitStack() as ros:
            if ros2:  # a session of its own beside the vehicle's (run_agent opens that one)
                from mergesvc.wire import keys
                from mergesvc.wire.session import open_session

                root = keys.uw_root(acfg.fleet) if acoustic else keys.fleet_root(acfg.fleet)
                ros_session = ros.enter_context(open_session(zconf))
                ros.enter_context(_ros2_bridge(True, ros_session, acfg.fleet, ros2_domain,
                                               ros2_namespace, robot=robot, root=root))
            stop = stop_on_signals()  # then say what was done
            stats = AgentStats()
            with progress_lines(progress, stats.line):
                run_agent(run, zconf, frames, stop, stats)
    typer.echo(json.dumps({"robot": robot, "frames": stats.frames,
                           "submaps_sent": stats.submaps_sent,
                           "bytes_sent": stats.bytes_sent,
                           "submaps_resent": stats.submaps_resent,
                           "submaps_given_up": stats.submaps_given_up,
                           "submaps_refused": stats.submaps_refused,
                           "results": stats.results,
                           "factors_received": stats.factors_received,
                           "stopped": stop.is_set()}))
    if stats.submaps_sent and not stats.results and not acoustic and not stop.is_set():
        typer.echo(f"warning: none of the {stats.submaps_sent} submaps sent got an answer from "
                   f"a service within --linger {linger:g} s: is one running on fleet "
                   f"{acfg.fleet}?", err=True)
    if stats.all_refused():
        fail(MergeError(f"the service held none of the {stats.submaps_sent} submaps sent; "
                        f"it said: {stats.last_refusal or 'busy until given up'}"), EXIT_FAILED)


def demo(
    out: Annotated[Path, typer.Option(help="folder for logs, summary and the figure")] = Path(
        "results/demo"
    ),
    quick: Annotated[bool, typer.Option(help="a smaller mission (under 30 s)")] = False,
    link: Annotated[LinkKind, typer.Option(help="zenoh, or acoustic (simulated modem)")] = (
        LinkKind.ZENOH
    ),
    seed: Annotated[int, typer.Option(help="mission seed")] = 0,
    profile: Annotated[Profile, typer.Option(help="codec profile of the submaps")] = (
        Profile.COMPACT
    ),
    settings: DemoSettings = None,
    view: Annotated[bool, typer.Option(help="show the merged map live in Rerun (the view "
                                            "extra)")] = False,
    view_save: Annotated[Path | None, typer.Option(help="record the live view into this "
                                                        ".rrd file")] = None,
    listen: Annotated[str | None, typer.Option(
        help="the service's Zenoh endpoint, e.g. tcp/127.0.0.1:7447 [default: a free port on "
             "127.0.0.1]; the demo prints the `mergesvc view --connect` line for it")] = None,
) -> None:
    """Service + 3 vehicles as processes on loopback; summary against the ground truth.

    Settings: the `service` and `agent` sections, written to OUT/settings.json.

    Every process the demo starts reads OUT/settings.json."""
    from mergesvc.fleet.demo import ROBOTS, SESSION, STORE_FILE, DemoPlan, run_demo
    from mergesvc.wire.session import make_zenoh_config, open_session

    if listen is not None:  # the service will listen there: a bad or busy endpoint fails now
        with exit_on_error():
            open_session(make_zenoh_config(mode="router", listen=[listen], scouting=False)).close()
    plan = (DemoPlan.quick if quick else DemoPlan)(seed=seed, link=link.value, profile=profile,
                                                   listen=listen)
    with exit_on_error():
        # the demo's processes are started with these flags: record what they really use
        tree = resolve_settings(settings, {
            "service": {"fleet": plan.fleet, "store": str(out / STORE_FILE)},
            "agent": {"fleet": plan.fleet, "session": SESSION},
        })
        if tree.agent.up is None:  # the demo's vehicles know gravity: the pool is z up
            tree = tree.merged({"agent": {"up": [0.0, 0.0, 1.0]}})
    # the export solves with the service's settings; the score rebuilds the vehicles' maps with
    # theirs
    plan = dataclasses.replace(plan, service=tree.service,
                               agents={r: tree.agent_config(r) for r in ROBOTS})
    with exit_on_error(OSError):
        written = write_settings_beside(tree, out, folder=True)
    attach = None
    if view or view_save is not None:
        from mergesvc.view import LiveView, ViewSink, observer

        with exit_on_error():
            attach = observer(LiveView.open(ViewSink(save=view_save)))
    with exit_on_error(), settings_env(written):
        res = run_demo(plan, out, echo=typer.echo, attach=attach)
    s = res.summary
    if s:
        typer.echo(f"submaps sent {s['submaps_sent']} ({s['bytes_on_wire']} bytes, "
                   f"{s['bytes_per_submap']:.0f} per submap); processed {s['submaps_processed']}")
        typer.echo(f"factors accepted {s['factors_accepted']} ({s['factors_retracted']} of "
                   f"them retracted since); correspondences right {s['correspondences_right']},"
                   f" wrong {s['correspondences_wrong']} (precision "
                   f"{s['precision'] if s['precision'] is None else round(s['precision'], 3)})")
        for r, a in s["alignment"].items():
            after = ("not placed" if a["after_m"] is None else
                     f"{a['after_m']:.2f} m / {a['after_deg']:.1f} deg")
            typer.echo(f"  {r}'s start frame placed in {s['anchor']}'s by the merge: {after} "
                       f"off the truth (the two taken as one frame: {a['before_m']:.2f} m / "
                       f"{a['before_deg']:.1f} deg off; no alignment, unlike the ATEs)")
        lat = ", ".join(f"{k} {v:.0f}" for k, v in (s["latency_ms"] or {}).items()
                        if isinstance(v, (int, float)))
        typer.echo(f"service latency per submap (ms): {lat or '-'}; demo took "
                   f"{s['elapsed_s']:.0f} s")
        typer.echo(f"figure {s['figure']}; summary {out / 'summary.json'} (docs/demo.md); "
                   f"trajectories as TUM files in {out / 'trajectories'}; logs in {out}")
    if s.get("exports"):
        files = [Path(p) for p in s["exports"]]
        top = files[0].parent
        names = sorted(str(p.relative_to(top)) if top in p.parents else str(p) for p in files)
        typer.echo(f"exported {len(files)} files into {top}: {', '.join(names)}")
    for f in res.failures:
        typer.echo(f"FAILED: {f}", err=True)
    if not res.ok:
        raise typer.Exit(EXIT_FAILED)


@link_app.command("sim")
def link_sim(
    ctx: typer.Context,
    rate: Annotated[list[int] | None, typer.Option(help="modem rate 1, 3 or 5 (repeat)")] = None,
    snr_db: Annotated[list[float] | None, typer.Option(help="SNR in dB (repeat)")] = None,
    bytes_per_submap: Annotated[int, typer.Option(help="uplink message size")] = 1024,
    period_s: Annotated[float, typer.Option(help="one submap per vehicle every ...")] = 60.0,
    duration_s: Annotated[float, typer.Option(help="simulated mission time")] = 1800.0,
    seed: Annotated[int, typer.Option(help="channel seed")] = 0,
    settings: LinkSimSettings = None,
) -> None:
    """Simulate 3 vehicles and a topside on a TDMA acoustic link (no network, no waiting).

    Settings: the `link` section (each rate and SNR set on it) and the `workload` section."""
    from mergesvc.link import ModemRate, format_sweep_table, sweep_link

    with exit_on_error(ValueError):
        rates = tuple(ModemRate(r) for r in (rate or [1, 3, 5]))
    flags = given(ctx, bytes_per_submap=bytes_per_submap, period_s=period_s,
                  duration_s=duration_s)
    if "bytes_per_submap" in flags:
        flags["uplink_bytes"] = flags.pop("bytes_per_submap")
    with exit_on_error():
        tree = resolve_settings(settings, {"workload": flags})
        rows = sweep_link(rates, snr_db or None, workload=tree.workload,
                          base_config=tree.link, seed=seed)
    typer.echo(format_sweep_table(rows))


@link_app.command("bridge")
def link_bridge(
    fleet: FleetName = "fleet0",
    rate: Annotated[int, typer.Option(help="modem rate 1, 3 or 5")] = 5,
    snr_db: Annotated[float, typer.Option(help="mean SNR in dB")] = 6.0,
    time_scale: Annotated[float, typer.Option(help="simulated s per wall s, inverted")] = 1.0,
    vehicles: Annotated[list[str] | None, typer.Option(
        help="vehicle names (repeat)", callback=key_names("robot"))] = None,
    mode: BridgeMode = ZenohMode.CLIENT,
    connect: Connect = None,
    listen: Listen = None,
    config: ZenohConfigFile = None,
    connect_timeout: ConnectTimeout = None,
    seconds: Annotated[float | None, typer.Option(min=0.0, help="stop after this long")] = None,
) -> None:
    """Bridge the vehicle side of the key space to the topside through the simulated modem."""
    from mergesvc.link import (
        AcousticBridge,
        ArqConfig,
        ChannelConfig,
        LinkConfig,
        ModemRate,
        SnrModel,
        TdmaConfig,
    )
    from mergesvc.wire.keys import all_under, fleet_root, uw_root

    names = vehicles or ["auv1", "auv2", "auv3"]
    with exit_on_error(ValueError):
        cfg = LinkConfig(
            channel=ChannelConfig(rate=ModemRate(rate), snr=SnrModel(mean_db=snr_db)),
            tdma=TdmaConfig(slot_order=["topside", *names]),
            # the topside sends every factor to both robots: room for a burst of them
            arq=ArqConfig(max_queue_messages=64),
        )
        # scouting stays on here even with a --config file (unlike serve and agent)
        zconf = zenoh_config(mode, connect, listen, config,
                             default_connect=(DEFAULT_ENDPOINT,), scouting=True,
                             connect_timeout=connect_timeout)
        with AcousticBridge(cfg, uw_prefix=uw_root(fleet), top_prefix=fleet_root(fleet),
                            zenoh_config=zconf, time_scale=time_scale) as bridge:
            typer.echo(f"bridging {all_under(uw_root(fleet))} <-> {all_under(fleet_root(fleet))} "
                       f"(rate {rate}, {snr_db} dB, time scale {time_scale})")
            start = time.monotonic()
            try:
                while seconds is None or time.monotonic() - start < seconds:
                    time.sleep(0.2)
            except KeyboardInterrupt:
                pass
            typer.echo(json.dumps(dataclasses.asdict(bridge.stats()), default=str))
