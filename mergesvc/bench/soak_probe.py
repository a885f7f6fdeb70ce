"""The soak's status probe: a process of its own that asks the service's status (`?poses=false`)
every PERIOD seconds and prints one JSON line per answer, {"t": wall time, "ms": round trip}, or
{"t": ..., "ms": null} without one within 2 s. Run by bench/soak.py as `python -m
mergesvc.bench.soak_probe ENDPOINT FLEET PERIOD`: the round trip a client that does nothing
else sees, apart from the soak driver's own threads (its robots and callbacks).
"""

from __future__ import annotations

import json
import sys
import time

from mergesvc.wire import keys
from mergesvc.wire.session import make_zenoh_config


def main() -> None:
    import zenoh

    endpoint, fleet, period = sys.argv[1], sys.argv[2], float(sys.argv[3])
    selector = keys.status_key(keys.fleet_root(fleet)) + "?poses=false"
    while True:  # the service may not listen yet (or be restarting): the driver kills us
        try:
            session = zenoh.open(make_zenoh_config(mode="client", connect=[endpoint],
                                                   scouting=False))
            break
        except zenoh.ZError:
            time.sleep(period)
    with session as s:
        while True:
            t, t0 = time.time(), time.monotonic()
            ms = None
            for reply in s.get(selector, timeout=2.0):
                if reply.ok is not None:
                    ms = (time.monotonic() - t0) * 1e3
            print(json.dumps({"t": t, "ms": ms}), flush=True)
            time.sleep(max(0.0, period - (time.monotonic() - t0)))


if __name__ == "__main__":
    main()


__all__ = ["main"]
