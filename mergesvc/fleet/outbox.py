"""What the service sends: factors to both their robots, each submap's result, refusals (the
coded error message and the refused result), each with the encoding of what is sent. A send
that fails is logged and counted, never raised: what was committed stays committed (a
restart's replay publishes it again).
"""

from __future__ import annotations

import logging
import threading

from mergesvc.core.model import ErrorMessage, Factor
from mergesvc.errors import MergeError, one_line
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.queries import ServiceStats
from mergesvc.fleet.replies import Outcome, RefusalCode, SubmapResult
from mergesvc.fleet.transport import Transport
from mergesvc.wire import Profile, encode_message, keys

log = logging.getLogger(__name__)


class Outbox:
    """Messages out through a transport (None: offline, nothing is sent)."""

    def __init__(self, config: ServiceConfig, transport: Transport | None,
                 stats: ServiceStats) -> None:
        self.config = config
        self.transport = transport
        self.stats = stats
        self.root = keys.fleet_root(config.fleet)
        self._seq = 0
        self._lock = threading.Lock()

    def _put(self, key: str, payload: bytes, json_doc: bool) -> None:
        if self.transport is not None:
            self.transport.put(key, payload, keys.JSON_ENCODING if json_doc
                               else keys.MSGPACK_ENCODING)

    def _next_seq(self) -> int:
        with self._lock:
            self._seq += 1
            return self._seq

    def factor(self, factor: Factor) -> None:
        """A factor to both its robots."""
        try:
            payload = encode_message(factor, self.config.factor_profile, "mergesvc",
                                     self._next_seq())
            for robot in sorted({factor.robot_a, factor.robot_b}):
                self._put(keys.factor_key(self.root, robot, factor.factor_id), payload,
                          json_doc=False)
        except (MergeError, ValueError) as exc:
            log.warning("could not publish factor %s: %s", factor.factor_id, exc)

    def result(self, res: SubmapResult) -> None:
        """A submap's result on result/{robot} (JSON), counted."""
        self.stats.result(res)
        try:
            self._put(keys.result_key(self.root, res.robot), res.model_dump_json().encode(),
                      json_doc=True)
        except (MergeError, ValueError) as exc:
            log.warning("could not publish a result to %s: %s", res.robot, exc)

    def refusal(self, robot: str, code: RefusalCode, detail: str, seq: int | None,
                session: str | None = None) -> None:
        """A refused submap: the error message on error/{robot} and the refused result."""
        self.stats.error(code.value)
        try:
            res = SubmapResult(robot=robot, session=session, seq=seq, outcome=Outcome.REFUSED,
                               code=code, detail=detail[:1000])
        except ValueError as exc:  # a name from the key no reply can carry
            log.warning("no result for a refused submap of %r: %s", robot[:80], one_line(exc))
        else:
            self.result(res)
        try:
            msg = encode_message(ErrorMessage(code=code.value, detail=detail[:1000],
                                              about_seq=seq),
                                 Profile.FULL, "mergesvc", self._next_seq())
            self._put(keys.error_key(self.root, robot), msg, json_doc=False)
        except (MergeError, ValueError) as exc:
            log.warning("could not publish an error to %s: %s", robot, exc)


__all__ = ["Outbox"]
