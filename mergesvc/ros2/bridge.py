"""The service's outputs to ROS 2 without touching the service: factors from its own Zenoh keys,
the merged map and trajectories polled from it (or from its status queryable).

`serve --ros2` runs one beside the MergeService (service given: map, paths, relocalization
answers too); `agent --ros2` runs one for a vehicle (robots=[robot], no service: its factors,
and the paths the service's status reports).
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mergesvc.core.model import Factor, ObjectMap, Submap
from mergesvc.errors import MergeError, one_line
from mergesvc.ros2.publisher import Ros2Publisher
from mergesvc.wire import decode_message, keys

if TYPE_CHECKING:
    from mergesvc.fleet.replies import RelocalizeReply
    from mergesvc.fleet.service import MergeService

log = logging.getLogger(__name__)

_SEEN_MAX = 100_000  # factor (id, status) pairs remembered, to publish each once


class Ros2Bridge:
    """Republishes a fleet's outputs through a `Ros2Publisher`.

    - factors: subscribes to `all_factors(root)` (or `robot_factors` of `robots`); each
      (factor id, status) is published once, although the service sends a factor to both its
      robots;
    - map and paths: every `period_s`, from `service` when given (global_map, status), else from
      the status queryable; published when they changed. A session no factor joins to the
      anchor yet has its path in its own frame with `service` (its keyframes composed by
      odometry from its keyframe 0); without it (the status holds no poses for such a session)
      it has none, and the bridge logs why, once per session;
    - relocalization answers (with `service`): `service.relocalize` is wrapped on this
      instance while the bridge runs, so each answer the queryable gives is published too.

    `start()` declares, `close()` undeclares (and closes the publisher if the bridge made it).
    """

    def __init__(
        self,
        session: Any,
        fleet: str = "fleet0",
        publisher: Ros2Publisher | None = None,
        service: MergeService | None = None,
        robots: list[str] | None = None,
        period_s: float = 1.0,
        query_timeout_s: float = 2.0,
        root: str | None = None,
        **publisher_options: Any,
    ) -> None:
        self.session = session
        self.root = root if root is not None else keys.fleet_root(fleet)
        self._own_publisher = publisher is None
        self.publisher = publisher or Ros2Publisher(session, **publisher_options)
        self.service = service
        self.robots = list(robots or [])
        self.period_s = period_s
        self.query_timeout_s = query_timeout_s
        self.factors_published = 0
        self._seen: OrderedDict[tuple[str, str], None] = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._subs: list[Any] = []
        self._map_fingerprint: int | None = None
        self._paths_fingerprint: int | None = None
        self._unpublished: set[str] = set()  # sessions whose missing path was logged
        self._wrapped: Callable[[Submap], RelocalizeReply] | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> Ros2Bridge:
        exprs = ([keys.robot_factors(self.root, r) for r in self.robots] if self.robots
                 else [keys.all_factors(self.root)])
        self._subs = [self.session.declare_subscriber(e, self._on_factor) for e in exprs]
        if self.service is not None:
            self._wrap_relocalize(self.service)
        self._thread = threading.Thread(target=self._run, name="mergesvc-ros2", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop polling, undeclare the subscribers, unwrap the service (idempotent)."""
        import zenoh

        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        for sub in self._subs:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        self._subs = []
        if self.service is not None and self._wrapped is not None:
            with contextlib.suppress(AttributeError):
                del self.service.relocalize  # the class's method again
            self._wrapped = None
        if self._own_publisher:
            self.publisher.close()

    def __enter__(self) -> Ros2Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ factors

    def _on_factor(self, sample: Any) -> None:
        try:
            _, factor = decode_message(sample.payload.to_bytes())
            if not isinstance(factor, Factor):
                raise MergeError(f"not a factor: {type(factor).__name__}")
            self.publish_factor(factor)
        except MergeError as exc:
            log.warning("ros2: ignoring a message on %s: %s", sample.key_expr, one_line(exc))
        # last resort of a Zenoh callback: log with the traceback, keep bridging
        except Exception:
            log.exception("ros2: could not republish a factor")

    def publish_factor(self, factor: Factor) -> bool:
        """Publish a factor unless this (id, status) was published already; True if it was."""
        status = factor.status.value if factor.status is not None else "accepted"
        with self._lock:
            if (factor.factor_id, status) in self._seen:
                return False
            self._seen[factor.factor_id, status] = None
            while len(self._seen) > _SEEN_MAX:
                self._seen.popitem(last=False)
            self.factors_published += 1
        self.publisher.publish_factor(factor)
        return True

    # ------------------------------------------------------------------ relocalization

    def _wrap_relocalize(self, service: MergeService) -> None:
        original = service.relocalize

        def relocalize(sub: Submap) -> RelocalizeReply:
            reply = original(sub)
            try:
                self.publisher.publish_relocalization(reply)
            except Exception:  # the querier gets its answer whatever happens here
                log.exception("ros2: could not publish a relocalization answer")
            return reply

        self._wrapped = relocalize
        service.relocalize = relocalize  # an instance attribute: close() deletes it

    # ------------------------------------------------------------------ map and paths

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.refresh()
            except MergeError as exc:
                log.warning("ros2: refresh failed: %s", one_line(exc))
            # last resort of the polling thread: log with the traceback, try again next period
            except Exception:
                log.exception("ros2: refresh failed")
            self._stop.wait(self.period_s)

    def refresh(self) -> list[str]:
        """Publish the map and the paths if they changed since the last refresh; returns the
        topics published on."""
        out: list[str] = []
        gmap: ObjectMap | None = None
        if self.service is not None:
            gmap, _ = self.service.global_map()
            status = self.service.status()
        else:
            status = self._query_status()
        if gmap is not None:
            fp = hash(tuple((o.id, o.position, o.label) for o in gmap.objects))
            if fp != self._map_fingerprint:
                out += self.publisher.publish_map(gmap)
                self._map_fingerprint = fp
        if status is None:
            return out
        joined = status.get("keyframe_poses") or {}
        own = self._own_frame_poses(set(joined)) if self.service is not None else {}
        if self.service is None:
            self._note_unpublished(set(status.get("frames") or {}) - set(joined))
        fp = hash(json.dumps([joined, {n: {str(k): T.tolist() for k, T in kf.items()}
                                       for n, kf in own.items()}], sort_keys=True))
        if fp != self._paths_fingerprint and (joined or own):
            if joined and status.get("anchor"):
                poses = {name: {int(k): np.asarray(T, dtype=np.float64) for k, T in kf.items()}
                         for name, kf in joined.items()}
                out += self.publisher.publish_paths(poses, status["anchor"])
            out += self.publisher.publish_session_paths(own)
            self._paths_fingerprint = fp
        return out

    def _own_frame_poses(self, joined: set[str]) -> dict[str, dict[int, np.ndarray]]:
        """The sessions outside the anchor's component (none solved with it yet): their
        keyframes in their own frame, composed by odometry from keyframe 0 as the export's
        odometry trajectory is."""
        import gtsam

        out: dict[str, dict[int, np.ndarray]] = {}
        if self.service is None:
            return out
        try:
            for name, st in list(self.service.sessions.items()):
                if name not in joined:
                    placed = st.propagate({0: gtsam.Pose3()})
                    out[name] = {k: np.asarray(T.matrix()) for k, T in sorted(placed.items())}
        except RuntimeError:  # the worker added a session or edge meanwhile: next period
            return {}
        return out

    def _note_unpublished(self, names: set[str]) -> None:
        """Say once per session why it has no path (vehicle side: no poses in the status)."""
        for name in sorted(names - self._unpublished):
            log.warning("ros2: session %s is not joined to the anchor yet (no factor ties it): "
                        "no path for it until one does (the service's status has poses only "
                        "for the anchor's sessions; serve --ros2 publishes it in its own frame)",
                        name)
        self._unpublished |= names

    def _query_status(self) -> dict[str, Any] | None:
        """The service's status over Zenoh (None when no service answers in time)."""
        for reply in self.session.get(keys.status_key(self.root),
                                      timeout=self.query_timeout_s):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None


__all__ = ["Ros2Bridge"]
