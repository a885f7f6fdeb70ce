"""The vehicle agent on Zenoh: a `LocalMap` (fleet/local_map.py) fed frame by frame, its submaps
published (msgpack, `application/msgpack`, through an advanced publisher that keeps them for a
late or restarted service), factors received in either profile the service codes them (full or
compact) and added to the local graph, and the service's result of each submap (JSON on
result/{robot}) counted; refusals that say "not now" are sent again after a backoff.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from mergesvc.core.model import Factor, Submap
from mergesvc.core.tracking import Frame
from mergesvc.errors import ConfigError, MergeError
from mergesvc.fleet.local_map import AgentConfig, LocalMap, build_submaps, odometry_covariance
from mergesvc.fleet.replies import Outcome, RefusalCode, SubmapResult
from mergesvc.wire import Profile, Projection, decode_message, encode_message, keys

log = logging.getLogger(__name__)


@dataclass
class AgentStats:
    frames: int = 0
    submaps_sent: int = 0
    bytes_sent: int = 0
    factors_received: int = 0
    bad_messages: int = 0
    results: dict[str, int] = field(default_factory=dict)  # the service's results per outcome
    submaps_resent: int = 0  # sent again after a "not now" refusal
    submaps_given_up: int = 0  # refused "not now" after every retry
    submaps_refused: int = 0  # refused for good or failed at the service: not sent again
    last_refusal: str = ""  # the last of those: "code: detail"

    def line(self) -> str:
        """What was done so far, as one progress line (read while the agent runs: the answers
        are copied first, a single step another thread's insert cannot interleave with)."""
        answers = ", ".join(f"{n} {k.replace('_', ' ')}"
                            for k, n in sorted(self.results.copy().items()))
        return (f"{self.frames} frames, {self.submaps_sent} submaps sent ({self.bytes_sent} "
                f"bytes), answers: {answers or 'none yet'}, factors in: {self.factors_received}")

    def all_refused(self) -> bool:
        """Every submap sent was refused for good, failed or given up, and none was
        processed or found no match."""
        answered = self.results.get("processed", 0) + self.results.get("no_match", 0)
        return (not answered and self.submaps_sent > 0
                and self.submaps_refused + self.submaps_given_up >= self.submaps_sent)


def decode_factor(data: bytes) -> Factor:
    """A factor message as the service sends it, coded full or compact (docs/wire.md §6);
    MergeError for anything else."""
    _, f = decode_message(data)
    if not isinstance(f, Factor):
        raise MergeError(f"expected a factor, got a {type(f).__name__}")
    return f


#: Refusals that say "not now", not "never": the agent sends the submap again after a backoff.
#: Every other code is final: `conflict` (other bytes under a stored seq) above all, since
#: sending the same bytes again gets the same answer (docs/wire.md §7).
RETRY_CODES = frozenset({RefusalCode.BUSY, RefusalCode.RATE_LIMITED, RefusalCode.STORE})
RETRY_BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)  # then the submap is given up


class Agent:
    """A vehicle on Zenoh: liveliness token, advanced publisher of submaps (cache, so a service
    that joins late or restarts recovers them), subscriber of its factors and of its submaps'
    results. A submap refused with a "not now" code (RETRY_CODES: busy, rate_limited, store:
    after a long outage the cache's replay can exceed the service's per-robot burst) is sent
    again after RETRY_BACKOFF_S[attempt] seconds, up to len(RETRY_BACKOFF_S) times; the last
    `cache_samples` payloads are kept for that. A submap the service will never hold (refused
    for good, failed, given up) is marked lost in the local map: the next submap's odometry
    starts before it, so the service's chain of this robot stays joined."""

    def __init__(
        self,
        config: AgentConfig,
        session: object,
        encode: Callable[[Submap, int], bytes],
        decode_factor: Callable[[bytes], Factor],
        submap_key: str,
        factor_key: str,
        alive_key: str,
        cache_samples: int = 10_000,
        result_key: str | None = None,
        stats: AgentStats | None = None,
    ) -> None:
        import zenoh
        from zenoh.ext import CacheConfig, MissDetectionConfig, declare_advanced_publisher

        self.config = config
        self.local = LocalMap(config)
        self.stats = AgentStats() if stats is None else stats
        self._encode, self._decode = encode, decode_factor
        self._lock = threading.Lock()
        self._session = session
        self._token = session.liveliness().declare_token(alive_key)
        self._pub = declare_advanced_publisher(
            session, submap_key, cache=CacheConfig(max_samples=cache_samples),
            sample_miss_detection=MissDetectionConfig(heartbeat=0.5), publisher_detection=True,
            congestion_control=zenoh.CongestionControl.BLOCK,
            encoding=zenoh.Encoding(keys.MSGPACK_ENCODING),
        )
        self._sub = session.declare_subscriber(factor_key, self._on_factor)
        # (session, seq) -> the payload sent and the submap's keyframe
        self._sent: OrderedDict[tuple[str, int], tuple[bytes, int | None]] = OrderedDict()
        self._keep = cache_samples
        self._attempts: dict[tuple[str, int], int] = {}
        self._refused: set[tuple[str, int | None]] = set()  # refused for good or failed
        self._warned: set[str] = set()  # the refusal codes said at warning level
        self._timers: set[threading.Timer] = set()
        self._closed = False
        self._results = (None if result_key is None
                         else session.declare_subscriber(result_key, self._on_result))

    def _on_result(self, sample: object) -> None:
        """The service's answer about one of this vehicle's submaps: counted, logged."""
        try:
            res = SubmapResult.model_validate_json(sample.payload.to_bytes())
        except ValueError as exc:  # pydantic's ValidationError: not a result document
            self.stats.bad_messages += 1
            log.warning("%s: ignoring a bad result message: %s", self.config.robot, exc)
            return
        if res.session is not None and res.session != self.config.session:
            # another session of this robot's name (another vehicle, or an earlier run)
            log.debug("%s: a result for session %s, not mine", self.config.robot, res.session)
            return
        with self._lock:
            self.stats.results[res.outcome.value] = self.stats.results.get(
                res.outcome.value, 0) + 1
        why = {Outcome.PROCESSED: f"factors {', '.join(res.factors)}",
               Outcome.NO_MATCH: f"no match ({getattr(res.reason, 'value', res.reason)})"}.get(
            res.outcome, f"{res.outcome.value} ({res.code.value if res.code else ''}: "
                         f"{res.detail})")
        which = f"submap {res.session}/{res.seq}" if res.seq is not None else "a submap"
        key = (res.session or self.config.session, res.seq)
        if res.outcome is Outcome.REFUSED and res.code in RETRY_CODES and res.seq is not None:
            log.info("%s: %s: %s", self.config.robot, which, why)
            self._retry(key)
        elif res.outcome in (Outcome.REFUSED, Outcome.FAILED):
            code = res.code.value if res.code else res.outcome.value
            with self._lock:
                if res.seq is None or key not in self._refused:  # a submap counts once
                    self._refused.add(key)
                    self.stats.submaps_refused += 1
                first = code not in self._warned
                self._warned.add(code)
                self.stats.last_refusal = f"{code}: {res.detail}"
            # the first of each code is said by default: the operator must act
            (log.warning if first else log.info)(
                "%s: %s %s, not sent again; the service said: %s: %s", self.config.robot,
                which, "refused for good" if res.outcome is Outcome.REFUSED else
                "failed at the service", code, res.detail)
            self._lost(key)
        else:
            log.info("%s: %s: %s", self.config.robot, which, why)

    def _lost(self, key: tuple[str, int | None]) -> None:
        """A submap the service will never hold: the next submap's odometry bridges it."""
        with self._lock:
            sent = self._sent.get(key)  # type: ignore[arg-type]
            if sent is not None and sent[1] is not None and key[0] == self.config.session:
                self.local.lost.add(sent[1])

    def _retry(self, key: tuple[str, int]) -> None:
        """Send a refused submap again after the next backoff (or give it up)."""
        with self._lock:
            payload = self._sent[key][0] if key in self._sent else None
            attempt = self._attempts.get(key, 0)
            if payload is None or self._closed:
                return
            if attempt >= len(RETRY_BACKOFF_S):
                self.stats.submaps_given_up += 1
                log.warning("%s: submap %s/%s refused %d times: given up", self.config.robot,
                            key[0], key[1], attempt)
                self._lost(key)
                return
            self._attempts[key] = attempt + 1
            timer = threading.Timer(RETRY_BACKOFF_S[attempt], self._resend, (key, payload))
            timer.daemon = True
            self._timers.add(timer)
        timer.start()

    def _resend(self, key: tuple[str, int], payload: bytes) -> None:
        import zenoh

        with self._lock:
            self._timers = {t for t in self._timers if t.is_alive()}
            if self._closed:
                return
        try:
            self._pub.put(payload)
            self.stats.submaps_resent += 1
            log.info("%s: submap %s/%s sent again", self.config.robot, key[0], key[1])
        except zenoh.ZError as exc:  # the session is closing
            log.warning("%s: could not send submap %s/%s again: %s", self.config.robot,
                        key[0], key[1], exc)

    def _on_factor(self, sample: object) -> None:
        try:
            factor = self._decode(sample.payload.to_bytes())
            with self._lock:
                line = self.local.add_inter_robot(factor)
                self.stats.factors_received += 1
            log.info("%s: %s", self.config.robot, line)
        except MergeError as exc:  # not a factor, or not one this map can use
            self.stats.bad_messages += 1
            log.warning("%s: ignoring a bad factor message: %s", self.config.robot, exc)
        # Last resort of the factor callback on a running vehicle: a factor the local graph
        # cannot take (GTSAM refuses it), or a bug, is logged with its traceback and skipped;
        # the vehicle goes on mapping.
        except Exception:
            self.stats.bad_messages += 1
            log.exception("%s: ignoring a factor the local map could not take", self.config.robot)

    def run(self, frames: Iterable[Frame], time_scale: float = 0.0,
            stop: threading.Event | None = None) -> AgentStats:
        """Process frames; time_scale > 0 paces them (wall s per simulated s)."""
        start = time.monotonic()
        for fr in frames:
            if stop is not None and stop.is_set():
                break
            if time_scale > 0:
                delay = start + fr.stamp_s * time_scale - time.monotonic()
                if delay > 0 and (stop.wait(delay) if stop is not None else time.sleep(delay)):
                    break  # stopped while waiting for the frame's time
            with self._lock:
                cut = self.local.add_frame(fr)
                sub = self.local.cut_submap(self.stats.submaps_sent, fr.stamp_s) if cut else None
                try:  # a factor the local graph cannot take is dropped, as on arrival
                    held = self.local.add_held()
                except Exception:
                    log.exception("%s: dropping a held factor the local map could not take",
                                  self.config.robot)
                    held = []
            for line in held:
                log.info("%s: %s", self.config.robot, line)
            self.stats.frames += 1
            if sub is not None:
                self.publish(sub)
        return self.stats

    def publish(self, sub: Submap) -> None:
        """Encode and send one submap (kept for a retry: see the class docstring)."""
        payload = self._encode(sub, self.stats.submaps_sent)
        with self._lock:
            self._sent[(sub.session_id, sub.seq)] = (payload, sub.keyframe)
            while len(self._sent) > self._keep:
                self._sent.popitem(last=False)
        self._pub.put(payload)
        self.stats.submaps_sent += 1
        self.stats.bytes_sent += len(payload)
        log.info("%s: submap %d (%d objects, %d bytes)", self.config.robot, sub.seq,
                 len(sub.objects), len(payload))

    def close(self) -> None:
        import zenoh

        with self._lock:
            self._closed = True
            timers, self._timers = self._timers, set()
        for t in timers:
            t.cancel()
        for ent in (self._results, self._sub, self._pub, self._token):
            if ent is None:
                continue
            with contextlib.suppress(zenoh.ZError):  # already gone with the session
                ent.undeclare()

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class AgentRun:
    """One vehicle run as `mergesvc agent` starts it: who the vehicle is, how its submaps are
    coded and which side of the key space it publishes on. Where its frames come from (a
    recorded log, a simulated world) is the caller's business: run_agent takes them."""

    robot: str
    fleet: str = "fleet0"
    session: str = "s0"
    profile: Profile = Profile.INT8
    projection: Path | None = None  # fleet projection (.npz); the compact profile needs it
    time_scale: float = 0.0  # wall s per simulated s; 0: no pacing
    acoustic: bool = False  # publish on the acoustic vehicle side (through the bridge)
    linger_s: float = 2.0  # stay up this long after the run, for late factors
    config: AgentConfig | None = None  # the agent settings; None: defaults for this robot


def run_agent(run: AgentRun, zenoh_config: Any, frames: Iterable[Frame],
              stop: threading.Event | None = None, stats: AgentStats | None = None
              ) -> AgentStats:
    """Build the vehicle (codec, keys), open a Zenoh session with `zenoh_config`, run `frames`
    through an `Agent`, linger for factors, close; `stop` set ends the run and the lingering
    early (what was done is counted, in `stats` when given: a caller may read it meanwhile).
    Raises MergeError (ConfigError for the
    compact profile without a projection, TransportError when the session cannot open),
    ValueError/OSError for unreadable input."""
    from mergesvc.wire.session import open_session

    proj = Projection.load(run.projection) if run.projection is not None else None
    if run.profile is Profile.COMPACT and proj is None:
        raise ConfigError("the compact profile needs a fleet projection")
    try:
        acfg = run.config or AgentConfig(robot=run.robot, session=run.session, fleet=run.fleet)
    except ValidationError as exc:  # a name no key can hold
        err = exc.errors()[0]
        raise ConfigError(f"invalid agent settings: {'.'.join(map(str, err['loc']))}: "
                          f"{err['msg'].removeprefix('Value error, ')}") from exc
    if (acfg.robot, acfg.session, acfg.fleet) != (run.robot, run.session, run.fleet):
        raise ConfigError(
            f"agent settings are for {acfg.robot}/{acfg.session} in fleet {acfg.fleet}, the run "
            f"is {run.robot}/{run.session} in fleet {run.fleet}"
        )
    root = keys.uw_root(run.fleet) if run.acoustic else keys.fleet_root(run.fleet)

    def encode(sub: Submap, seq: int) -> bytes:
        return encode_message(sub, run.profile, run.robot, seq, projection=proj)

    with open_session(zenoh_config) as session, Agent(
        acfg, session, encode, decode_factor,
        submap_key=keys.submap_key(root, run.robot, run.session),
        factor_key=keys.robot_factors(root, run.robot), alive_key=keys.alive_key(root, run.robot),
        result_key=keys.result_key(root, run.robot), stats=stats,
    ) as ag:
        stats = ag.run(frames, time_scale=run.time_scale, stop=stop)
        (stop or threading.Event()).wait(run.linger_s)
    return stats


__all__ = ["Agent", "AgentConfig", "AgentRun", "AgentStats", "LocalMap", "build_submaps",
           "decode_factor", "odometry_covariance", "run_agent"]
