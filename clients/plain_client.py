"""An independent vehicle client of the merge service: plain eclipse-zenoh + msgpack + json +
numpy, written from docs/wire.md alone (no import of mergesvc).

It publishes one submap (a JSON file in the `mergesvc match` format), coded by itself with the
`full` profile (docs/wire.md §2-§4), and waits for what the service answers: the submap's result
on result/{robot} (JSON), the factors it names on factor/{robot}/{id} (msgpack; decoded here when
the service codes factors `full`: `mergesvc serve --factor-profile full`); then it queries
status and relocalize (JSON replies). It prints one JSON object:

    {"result": {...}, "factors": [{...}], "status": {...}, "relocalize": {...},
     "encodings": {"result": "application/json", "factor": "application/msgpack", ...}}

    python clients/plain_client.py --connect tcp/127.0.0.1:7447 --fleet fleet0 \\
        --robot auv2 --session s0 --seq 0 --submap submap.json

Exit code 0 when the result came (whatever it says), 1 when it did not within --timeout, 2 when
the session or the file failed (one line on stderr). A factor coded `compact` (the service's
default) is listed as {"factor_id", "undecoded": why}.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 1
CODEC_VERSION = 1
TYPE_SUBMAP, TYPE_FACTOR, TYPE_ERROR = 1, 3, 4
PROFILE_FULL, PROFILE_COMPACT = 0, 3
MSGPACK = "application/msgpack"  # docs/wire.md §11: the encoding of coded messages
ROOT = "mergesvc/v1"


# ------------------------------------------------------------------ the submap, full profile


def bits_for(v: int) -> int:
    """§1: the number of bits of the unsigned integer v."""
    return int(v).bit_length()


class BitWriter:
    """§3: unsigned fields, most significant bit first; byte sections after zero padding."""

    def __init__(self) -> None:
        self.out = bytearray()
        self.acc = 0
        self.n_bits = 0

    def field(self, value: int, width: int) -> None:
        if width == 0:
            return
        if not 0 <= value < (1 << width):
            raise ValueError(f"{value} does not fit {width} bits")
        self.acc = (self.acc << width) | value
        self.n_bits += width
        while self.n_bits >= 8:
            self.n_bits -= 8
            self.out.append((self.acc >> self.n_bits) & 0xFF)
        self.acc &= (1 << self.n_bits) - 1

    def pad(self) -> None:
        if self.n_bits:
            self.field(0, 8 - self.n_bits)

    def raw(self, data: bytes) -> None:
        self.pad()
        self.out += data

    def finish(self) -> bytes:
        self.pad()
        return bytes(self.out)


def encode_submap(doc: Mapping[str, Any], robot: str, seq: int) -> bytes:
    """A submap document (the `match` JSON format) as one message: envelope (§2) around a
    `full` payload (§4): ids as strings (kind 0), float64 positions, float32 variances and
    embeddings, `up` (§4.7) and the pose (§4.8) when the document has them."""
    objects = doc["objects"]
    n = len(objects)
    d = len(objects[0]["embedding"])
    ids = [str(o["id"]) for o in objects]
    labels = [o.get("label") for o in objects]
    n_obs = [int(o.get("n_obs", 1)) for o in objects]
    iso = [not isinstance(o["variance"], list) for o in objects]
    var_mode = 0 if all(iso) else 1 if not any(iso) else 2

    blob = BitWriter()
    table: list[str | None] | None = None
    if any(label is not None for label in labels):  # §4.2: a label table and a code per object
        named = sorted({label for label in labels if label is not None})
        table = ([None] if None in labels else []) + named
        width = bits_for(len(table) - 1)
        for label in labels:
            blob.field(table.index(label), width)
    nobs_bits = bits_for(max(n_obs) - 1)  # §4.3
    for k in n_obs:
        blob.field(k - 1, nobs_bits)
    if var_mode == 2:  # §4.5: a flag per object, 1 = isotropic
        for flag in iso:
            blob.field(int(flag), 1)
    positions = np.asarray([o["position"] for o in objects], dtype="<f8")  # §4.4 full
    blob.raw(positions.tobytes())
    iso_var = [o["variance"] for o, f in zip(objects, iso, strict=True) if f]
    dim_var = [o["variance"] for o, f in zip(objects, iso, strict=True) if not f]
    blob.raw(np.asarray(iso_var, dtype="<f4").tobytes())
    blob.raw(np.asarray(dim_var, dtype="<f4").reshape(-1).tobytes())
    emb = np.asarray([o["embedding"] for o in objects], dtype="<f4")  # §4.6 full
    blob.raw(emb.tobytes())

    payload: list[Any] = [
        robot, doc["session_id"], seq, doc.get("stamp"), n, d, [0, ids], table, nobs_bits,
        var_mode, None, None, None, blob.finish(),
    ]
    up = doc.get("up")
    if doc.get("keyframe") is not None:  # §4.8
        pose: list[Any] = [int(doc["keyframe"])]
        odo = doc.get("odometry")
        if odo is not None:
            T = odo["T_from_to"]
            floats = [*T["translation"], *T["quaternion_wxyz"],
                      *np.asarray(odo["covariance"], dtype=float).reshape(-1)]
            pose += [int(doc["keyframe"]) - int(odo["from_keyframe"]),
                     struct.pack("<43d", *floats)]
        payload += [_up_codes(up) if up is not None else None, pose]
    elif up is not None:
        payload.append(_up_codes(up))
    envelope = [SCHEMA_VERSION, CODEC_VERSION, TYPE_SUBMAP, robot, seq, PROFILE_FULL, payload]
    return msgpack.packb(envelope, use_bin_type=True)


def _up_codes(up: Any) -> list[int]:
    """§4.7: c = rint(127 u / max |u_k|)."""
    u = np.asarray(up, dtype=float)
    return [int(c) for c in np.rint(127.0 * u / np.abs(u).max())]


# ------------------------------------------------------------------ what the service sends


def decode_factor(data: bytes) -> dict[str, Any]:
    """A factor message (§2, §6.1): the factor document of a `full` factor. A compact factor
    (§6.2) is not decoded here: ask the service for full factors (--factor-profile full)."""
    env = msgpack.unpackb(data, raw=False, strict_map_key=True)
    if not (isinstance(env, list) and len(env) == 7 and env[0] == SCHEMA_VERSION
            and env[1] == CODEC_VERSION and env[2] == TYPE_FACTOR):
        raise ValueError("not a factor message of schema and codec version 1")
    if env[5] == PROFILE_COMPACT:
        raise ValueError("a compact factor: start the service with --factor-profile full")
    if env[5] != PROFILE_FULL or not isinstance(env[6], dict):
        raise ValueError(f"factor profile {env[5]} is neither full nor compact")
    return env[6]


def strict_json(data: bytes) -> Any:
    """JSON as the standard says: NaN and Infinity refused."""

    def refuse(name: str) -> None:
        raise ValueError(f"not JSON: {name}")

    return json.loads(data, parse_constant=refuse)


class Inbox:
    """Samples of one subscription: (key, payload, encoding), with a bounded wait."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, str]] = []
        self.cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes(),
                               str(sample.encoding)))
            self.cond.notify_all()

    def wait(self, pick: Any, timeout_s: float) -> Any:
        """The first item `pick` maps to something other than None, or None at the timeout."""

        def found() -> Any:
            for item in self.items:
                got = pick(item)
                if got is not None:
                    return got
            return None

        with self.cond:
            self.cond.wait_for(lambda: found() is not None, timeout_s)
            return found()


def query_json(session: zenoh.Session, key: str, payload: bytes | None,
               timeout_s: float) -> tuple[Any, str]:
    """One JSON reply of a queryable (an error reply is an ErrorMessage document, §7)."""
    for reply in session.get(key, payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            return strict_json(reply.ok.payload.to_bytes()), str(reply.ok.encoding)
        return {"error": strict_json(reply.err.payload.to_bytes())}, str(reply.err.encoding)
    raise TimeoutError(f"no reply from {key} within {timeout_s} s")


def run(args: argparse.Namespace) -> dict[str, Any]:
    root = f"{ROOT}/{args.fleet}"
    doc = json.loads(Path(args.submap).read_text())
    doc["session_id"] = args.session
    message = encode_submap(doc, args.robot, args.seq)

    conf = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.mode))
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.no_multicast_scouting:
        conf.insert_json5("scouting/multicast/enabled", "false")
    results, factors = Inbox(), Inbox()
    with zenoh.open(conf) as session:
        session.declare_subscriber(f"{root}/result/{args.robot}", results)
        session.declare_subscriber(f"{root}/factor/{args.robot}/**", factors)
        # the subscriptions travel before the put on the same link: nothing to wait for
        session.put(f"{root}/submap/{args.robot}/{args.session}", message,
                    encoding=zenoh.Encoding(MSGPACK),
                    congestion_control=zenoh.CongestionControl.BLOCK)

        def mine(item: tuple[str, bytes, str]) -> Any:
            res = strict_json(item[1])
            ours = res.get("session") == args.session and res.get("seq") == args.seq
            return (res, item[2]) if ours else None

        got = results.wait(mine, args.timeout)
        if got is None:
            raise TimeoutError(f"no result for {args.robot}/{args.session} seq {args.seq}")
        result, result_encoding = got
        out_factors, factor_encoding = [], None
        for fid in result.get("factors", []):  # sent before the result: already here
            key = f"{root}/factor/{args.robot}/{fid}"
            item = factors.wait(lambda it, key=key: it if it[0] == key else None, args.timeout)
            if item is None:
                raise TimeoutError(f"factor {fid} named by the result did not come")
            try:
                out_factors.append(decode_factor(item[1]))
            except ValueError as exc:  # a compact factor (the service's default): said, kept
                out_factors.append({"factor_id": fid, "undecoded": str(exc)})
            factor_encoding = item[2]
        status, status_encoding = query_json(session, f"{root}/status", None, args.timeout)
        reloc, reloc_encoding = query_json(session, f"{root}/relocalize", message, args.timeout)
        junk, junk_encoding = query_json(session, f"{root}/relocalize", b"junk", args.timeout)
    return {
        "result": result,
        "factors": out_factors,
        "status": status,
        "relocalize": reloc,
        "relocalize_error": junk,
        "encodings": {"result": result_encoding, "factor": factor_encoding,
                      "status": status_encoding, "relocalize": reloc_encoding,
                      "relocalize_error": junk_encoding},
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--submap", required=True, help="submap JSON file (the match format)")
    p.add_argument("--robot", required=True)
    p.add_argument("--session", default="s0")
    p.add_argument("--seq", type=int, default=0)
    p.add_argument("--fleet", default="fleet0")
    p.add_argument("--mode", default="client", choices=["client", "peer"])
    p.add_argument("--connect", "-e", action="append", default=[], help="zenoh endpoint(s)")
    p.add_argument("--config", "-c", help="zenoh JSON5 config file")
    p.add_argument("--no-multicast-scouting", action="store_true")
    p.add_argument("--timeout", type=float, default=20.0, help="seconds to wait for each answer")
    args = p.parse_args(argv)
    try:
        out = run(args)
    except TimeoutError as exc:
        print(f"plain_client: {exc}", file=sys.stderr)
        return 1
    except (zenoh.ZError, OSError, ValueError) as exc:  # no router there, a bad file or flag
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0].split("  at ")[0]
        print(f"plain_client: {first} (check --connect and that the service runs there, and "
              f"the --submap file)", file=sys.stderr)
        return 2
    print(json.dumps(out, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
