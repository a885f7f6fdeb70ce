"""`bench fuzz`: seeded mutation fuzzing of every decoder of outside input: each input is either
decoded or refused with one of the errors the command line turns into one line and exit 2;
anything else (RecursionError, KeyError, OverflowError, a hang, ...) is a finding.

Targets (`DECODERS`): `wire` (decode_message, peek_projection_id), `link` (the ARQ framing and
the bridge's per-sample framing), `match` (the loader of `mergesvc match`, then the pipeline on
what it accepts) and `other` (codec JSON input, TUM, observation logs, projection files). Every
finding is counted, grouped by where it was raised, and its first inputs saved. Every draw comes
from one seeded `random.Random`: a run is reproducible. Each decoder, and why a mutation fuzzer
and not hypothesis: docs/benchmarks/fuzz.md.
"""

from __future__ import annotations

import io
import json
import math
import os
import random
import signal
import subprocess
import tempfile
import threading
import time
import traceback
import warnings
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.bench.fuzz_mutators import (
    MAX_DEPTH,
    RAW_TOKEN,
    mutate_bytes,
    mutate_json,
    mutate_msgpack,
    mutator,
)
from mergesvc.errors import InputError, MergeError, one_line

DEFAULT_INPUTS = 100_000
MAX_REPRODUCERS = 5  # reproducer files saved per decoder
INPUT_TIMEOUT_S = 10.0  # an input that takes longer is a finding (a hang)


class FuzzTarget(str, Enum):
    WIRE = "wire"
    LINK = "link"
    MATCH = "match"
    OTHER = "other"
    ALL = "all"


class HangError(BaseException):  # BaseException: decoders that catch Exception let it by
    """Raised by the interval timer in the decoder running too long (never caught by it)."""


@dataclass
class Decoder:
    """One decoder under test: `run(data)` decodes; `refused` are the errors its command maps to
    one line and exit 2; `mutate(rng)` gives the next input."""

    name: str
    target: FuzzTarget
    run: Callable[[bytes], Any]
    mutate: Callable[[random.Random], bytes]
    refused: tuple[type[BaseException], ...] = (MergeError,)
    suffix: str = ".bin"
    weight: float = 1.0  # share of the target's inputs


@dataclass
class DecoderStats:
    name: str
    inputs: int = 0
    accepted: int = 0
    refused: Counter = field(default_factory=Counter)
    refused_exit_1: Counter = field(default_factory=Counter)  # MergeError but not InputError
    foreign_causes: Counter = field(default_factory=Counter)  # "DecodeError<-ValueError"
    findings: int = 0
    finding_kinds: Counter = field(default_factory=Counter)  # "KeyError at file:line"
    reproducers: list[dict[str, Any]] = field(default_factory=list)
    slowest_s: float = 0.0
    elapsed_s: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "inputs": self.inputs, "accepted": self.accepted,
            "refused": dict(self.refused.most_common()),
            "refused_exit_1": dict(self.refused_exit_1.most_common()),
            "refused_via_foreign_error": dict(self.foreign_causes.most_common()),
            "findings": self.findings, "finding_kinds": dict(self.finding_kinds.most_common()),
            "reproducers": self.reproducers, "slowest_s": round(self.slowest_s, 4),
            "elapsed_s": round(self.elapsed_s, 2),
        }


# --- the oracle -------------------------------------------------------------------------------


def _on_alarm(_signum: int, _frame: Any) -> None:
    raise HangError


def _where(exc: BaseException) -> str:
    """file:line where `exc` was raised (the innermost frame inside mergesvc, else the last)."""
    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if "/mergesvc/" in f.filename and "/bench/fuzz.py" not in f.filename]
    f = (ours or frames or [None])[-1]
    if f is None:
        return "?"
    return f"{f.filename.split('/mergesvc/')[-1]}:{f.lineno}"


def check_input(decoder: Decoder, data: bytes, timeout_s: float = INPUT_TIMEOUT_S
                ) -> tuple[str, str, BaseException | None]:
    """Run one input: ("accepted", "", None), ("refused", error type, exc) or
    ("finding", "<type> at <file:line>: <message>", exc)."""
    timer = threading.current_thread() is threading.main_thread()
    if timer:
        old = signal.signal(signal.SIGALRM, _on_alarm)
        signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        decoder.run(data)
    except HangError as exc:
        return "finding", f"hang: more than {timeout_s:g} s", exc
    except decoder.refused as exc:
        return "refused", type(exc).__name__, exc
    except BaseException as exc:
        if isinstance(exc, KeyboardInterrupt | SystemExit):
            raise
        return "finding", f"{type(exc).__name__} at {_where(exc)}: {one_line(exc)[:160]}", exc
    finally:
        if timer:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    return "accepted", "", None


def _foreign_cause(exc: BaseException) -> str | None:
    """The first non-mergesvc error in exc's cause chain: a refusal made by a catch-all."""
    c = exc.__cause__
    while c is not None:
        if not isinstance(c, MergeError):
            return type(c).__name__
        c = c.__cause__
    return None


# --- the decoders -----------------------------------------------------------------------------


class _Scratch:
    """A file path the file-reading decoders get their input through (one file rewritten)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def path(self, name: str, data: bytes) -> Path:
        p = self.folder / name
        p.write_bytes(data)
        return p


def _wire_decoders() -> list[Decoder]:
    from mergesvc.wire.envelope import decode_message, encode_message, peek_projection_id
    from mergesvc.wire.golden import golden_projection, golden_vectors

    proj = golden_projection()
    seeds = [encode_message(v.model, v.profile, v.sender, v.seq, projection=proj,
                            settings=v.settings) for v in golden_vectors()]
    mutate = mutator(seeds, mutate_msgpack)
    return [
        Decoder("wire.decode_message", FuzzTarget.WIRE, lambda d: decode_message(d, proj), mutate,
                weight=4.0),
        Decoder("wire.peek_projection_id", FuzzTarget.WIRE, peek_projection_id, mutate),
    ]


def _crc16_fix(rng: random.Random, data: bytes) -> bytes:
    """Most inputs get a valid CRC-16 trailer again: the header checks behind it get fuzzed."""
    import binascii

    if rng.random() < 0.2 or len(data) < 2:
        return data
    body = data[:-2]
    return body + binascii.crc_hqx(body, 0xFFFF).to_bytes(2, "big")


def _crc32_fix(rng: random.Random, data: bytes) -> bytes:
    if rng.random() < 0.3 or len(data) < 4:
        return data
    return data[:-4] + zlib.crc32(data[:-4]).to_bytes(4, "big")


def _mutate_fragment_header(rng: random.Random, data: bytes) -> bytes:
    word = (rng.randrange(1 << 12) << 20) | (rng.randrange(1 << 10) << 10) | rng.randrange(1 << 10)
    return word.to_bytes(4, "big") + data[4:]


def _link_decoders() -> list[Decoder]:
    from mergesvc.link.arq import (
        AckEntry,
        ack_entry,
        decode_ack,
        decode_fragment,
        encode_ack,
        encode_fragment,
        join_fragments,
        split_message,
    )
    from mergesvc.link.bridge import frame_sample, unframe_sample
    from mergesvc.wire.envelope import encode_message
    from mergesvc.wire.golden import golden_projection, golden_vectors

    proj = golden_projection()
    messages = [encode_message(v.model, v.profile, v.sender, v.seq, projection=proj,
                               settings=v.settings) for v in golden_vectors()]
    frags = [encode_fragment(f) for k, m in enumerate(messages)
             for f in split_message(k, m, 32 + 16 * (k % 4))]
    acks = [encode_ack([AckEntry(3, True)]), encode_ack([]),
            encode_ack([ack_entry(7, [0, 1, 3, 9], 8), AckEntry(4095, True)]),
            encode_ack([ack_entry(k, range(0, 40, 1 + k % 3), 4) for k in range(5)])]
    trailed = [m + zlib.crc32(m).to_bytes(4, "big") for m in messages]
    samples = [frame_sample(s, m) for s, m in zip(
        ("robot_a/submap/s0", "fleet0/factor/robot_b/f1", "", "é/ü"), messages)]
    return [
        Decoder("link.decode_fragment", FuzzTarget.LINK, decode_fragment,
                mutator(frags, _mutate_fragment_header, 0.3, _crc16_fix), weight=2.0),
        Decoder("link.decode_ack", FuzzTarget.LINK, decode_ack,
                mutator(acks, None, fix=_crc16_fix), weight=2.0),
        Decoder("link.join_fragments", FuzzTarget.LINK,
                lambda d: join_fragments([d[i:i + 37] for i in range(0, len(d), 37)]),
                mutator(trailed, None, fix=_crc32_fix)),
        Decoder("link.unframe_sample", FuzzTarget.LINK, unframe_sample, mutator(samples, None)),
    ]


def _golden_files() -> tuple[Any, Any]:
    """The golden vectors' full-profile map and submap (8-d embeddings, a few objects)."""
    from mergesvc.wire.golden import golden_vectors

    by_name = {v.name: v.model for v in golden_vectors()}
    return by_name["map_full"], by_name["submap_full"]


def match_files() -> tuple[bytes, bytes]:
    """The JSON map and submap the match target starts from (and pairs with)."""
    map_, sub = _golden_files()
    return map_.model_dump_json().encode(), sub.model_dump_json().encode()


def _match_decoders(scratch: _Scratch, pipeline: bool) -> list[Decoder]:
    from mergesvc.core.config import MatchConfig
    from mergesvc.core.model import ObjectMap, Submap
    from mergesvc.core.pipeline import match
    from mergesvc.wire.files import load_model

    map_, sub = _golden_files()
    cfg = MatchConfig()
    map_seeds = [map_.model_dump_json().encode(), sub.model_dump_json().encode()]
    sub_seeds = [sub.model_dump_json().encode(), map_.model_dump_json().encode()]

    def run_map(data: bytes) -> None:
        m = load_model(ObjectMap, scratch.path("map.json", data))
        if pipeline:
            match(m, sub, cfg)

    def run_submap(data: bytes) -> None:
        s = load_model(Submap, scratch.path("submap.json", data))
        if pipeline:
            match(map_, s, cfg)

    def structured(rng: random.Random, data: bytes) -> bytes:
        return mutate_json(rng, data)

    return [
        Decoder("match.map", FuzzTarget.MATCH, run_map, mutator(map_seeds, structured, 0.8),
                suffix=".json"),
        Decoder("match.submap", FuzzTarget.MATCH, run_submap, mutator(sub_seeds, structured, 0.8),
                suffix=".json"),
    ]


_TUM = (b"# timestamp tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n"
        b"0.5 1.25 -2 0.1 0 0 0.7071067811865476 0.7071067811865476\n1e3 3 4 5 0.5 0.5 0.5 0.5\n")
_TUM_NUMBERS = ("nan", "inf", "-inf", "1e999", "1" * 5000, "0x10", "1_0", "∞", "", "١", "1e-400",
                "0", "-0", "1.0000001", "2")


def _mutate_tum(rng: random.Random, data: bytes) -> bytes:
    lines = data.decode("utf-8", errors="replace").split("\n")
    k = rng.randrange(len(lines))
    fields = lines[k].split(" ")
    fields[rng.randrange(len(fields))] = rng.choice(_TUM_NUMBERS)
    if rng.random() < 0.2:
        fields = fields[:rng.randint(0, len(fields))]
    lines[k] = " ".join(fields)
    return "\n".join(lines).encode("utf-8", errors="surrogatepass")


_OBS_LINE = {
    "stamp_s": 1.5,
    "pose": {"translation": [1.0, 2.0, 0.5], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
    "up_body": [0.0, 0.0, 1.0],
    "detections": [{"embedding": [0.1, 0.2, 0.3, 0.4], "uncertainty": 0.2,
                    "position_body_m": [4.0, 0.5, -1.0], "position_sigma_m": 0.3}],
}


def _mutate_obslog(rng: random.Random, data: bytes) -> bytes:
    lines = data.split(b"\n")
    k = rng.randrange(len(lines))
    if lines[k].strip():
        lines[k] = mutate_json(rng, lines[k]).replace(b"\n", b" ")
    return b"\n".join(lines)


def _projection_npz(arrays: dict[str, Any]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _mutate_projection(rng: random.Random, _data: bytes) -> bytes:
    """A projection file whose arrays are the golden ones with one changed: shape, dtype,
    NaN, zero scale, missing, extra, 0-d, strings."""
    from mergesvc.wire.golden import golden_projection

    p = golden_projection()
    arrays: dict[str, Any] = {"mean": p.mean_d, "basis": p.basis_kd, "scale": p.scale_k,
                              "id": np.array(p.id)}
    key = rng.choice(list(arrays))
    a = np.asarray(arrays[key])
    change = rng.choice([
        lambda: None, lambda: a[..., :-1] if a.ndim else a, lambda: a.T, lambda: a.reshape(-1),
        lambda: np.full_like(a, np.nan) if a.dtype.kind == "f" else np.array(np.nan),
        lambda: np.zeros_like(a), lambda: a.astype(np.float16), lambda: a.astype(np.complex64),
        lambda: a.astype(np.int8), lambda: np.array("abc"), lambda: np.array(1e308),
        lambda: np.zeros((0, 0)), lambda: np.zeros((2, 3, 4)), lambda: -a,
        lambda: np.array([b"\x00" * 4]), lambda: np.array([True, False]),
        lambda: np.zeros((1, 70_000), dtype=np.float32),
    ])
    try:
        arrays[key] = change()
    except (ValueError, TypeError):  # e.g. the id string as complex
        arrays[key] = np.array([], dtype=np.float64)
    if arrays[key] is None:
        del arrays[key]
    if rng.random() < 0.1:
        arrays["extra"] = np.zeros(3)
    return _projection_npz(arrays)


def _other_decoders(scratch: _Scratch) -> list[Decoder]:
    from mergesvc.sim.logs import read_observation_log
    from mergesvc.wire.files import encode_file
    from mergesvc.wire.formats import read_tum
    from mergesvc.wire.golden import golden_projection, golden_vectors
    from mergesvc.wire.profiles import Profile
    from mergesvc.wire.projection import Projection

    codec_seeds = [v.model.model_dump_json(exclude_none=True).encode()
                   for v in golden_vectors() if v.profile is Profile.FULL]
    obs = json.dumps(_OBS_LINE).encode()
    obs_seeds = [obs + b"\n" + obs + b"\n", b"\n" + obs]
    p = golden_projection()
    npz = _projection_npz({"mean": p.mean_d, "basis": p.basis_kd, "scale": p.scale_k,
                           "id": np.array(p.id)})
    return [
        Decoder("other.codec_json", FuzzTarget.OTHER,
                lambda d: encode_file(scratch.path("in.json", d), scratch.folder / "out.bin",
                                      Profile.FULL),
                mutator(codec_seeds, mutate_json, 0.8),
                refused=(MergeError, ValueError), suffix=".json"),  # `codec encode`'s boundary
        Decoder("other.tum", FuzzTarget.OTHER, lambda d: read_tum(scratch.path("t.tum", d)),
                mutator([_TUM], _mutate_tum), suffix=".tum"),
        # `agent --log` iterates the log inside exit_on_error(ValueError, OSError)
        Decoder("other.obslog", FuzzTarget.OTHER,
                lambda d: list(read_observation_log(scratch.path("log.jsonl", d))),
                mutator(obs_seeds, _mutate_obslog, 0.8),
                refused=(MergeError, ValueError, OSError), suffix=".jsonl"),
        Decoder("other.projection", FuzzTarget.OTHER,
                lambda d: Projection.load(scratch.path("p.npz", d)),
                mutator([npz], _mutate_projection, 0.7), suffix=".npz", weight=0.5),
    ]


def decoders(targets: Sequence[FuzzTarget], scratch: _Scratch, pipeline: bool = True
             ) -> list[Decoder]:
    out: list[Decoder] = []
    for t in targets:
        if t is FuzzTarget.WIRE:
            out += _wire_decoders()
        elif t is FuzzTarget.LINK:
            out += _link_decoders()
        elif t is FuzzTarget.MATCH:
            out += _match_decoders(scratch, pipeline)
        elif t is FuzzTarget.OTHER:
            out += _other_decoders(scratch)
    return out


# --- the run ----------------------------------------------------------------------------------


def fuzz_decoder(decoder: Decoder, n_inputs: int, rng: random.Random,
                 reproducer_dir: Path | None = None, timeout_s: float = INPUT_TIMEOUT_S,
                 progress: Callable[[int], None] | None = None,
                 keep: Callable[[bytes, str], None] | None = None) -> DecoderStats:
    """Feed `n_inputs` mutated inputs to one decoder; count outcomes, save reproducers."""
    st = DecoderStats(decoder.name)
    t0 = time.perf_counter()
    for i in range(n_inputs):
        data = decoder.mutate(rng)
        t = time.perf_counter()
        outcome, kind, exc = check_input(decoder, data, timeout_s)
        st.slowest_s = max(st.slowest_s, time.perf_counter() - t)
        st.inputs += 1
        if outcome == "accepted":
            st.accepted += 1
        elif outcome == "refused":
            st.refused[kind] += 1
            if isinstance(exc, MergeError) and not isinstance(exc, InputError):
                st.refused_exit_1[kind] += 1  # e.g. the pipeline's SolverError on 1e300 m
            cause = _foreign_cause(exc) if exc is not None else None
            if cause is not None:
                st.foreign_causes[f"{kind}<-{cause}"] += 1
        else:
            st.findings += 1
            sig = kind.split(": ", 1)[0]
            st.finding_kinds[sig] += 1
            if st.finding_kinds[sig] == 1 and len(st.reproducers) < MAX_REPRODUCERS:
                rec: dict[str, Any] = {"error": kind, "bytes": len(data),
                                       "head": data[:80].decode("latin-1")}
                if reproducer_dir is not None:
                    reproducer_dir.mkdir(parents=True, exist_ok=True)
                    name = f"{decoder.name}-{len(st.reproducers) + 1}{decoder.suffix}"
                    path = reproducer_dir / name
                    path.write_bytes(data)
                    rec["file"] = str(path)
                st.reproducers.append(rec)
        if keep is not None:
            keep(data, outcome)
        if progress is not None and (i + 1) % 500 == 0:
            progress(500)
    if progress is not None:
        progress(n_inputs % 500)
    st.elapsed_s = time.perf_counter() - t0
    return st


def nasty_match_inputs() -> dict[str, bytes]:
    """Hand-made worst cases for the `match` subprocess check, named."""
    map_json, _ = match_files()

    def token(where: Callable[[dict], tuple[Any, Any]], raw: str) -> bytes:
        doc = json.loads(map_json)
        parent, key = where(doc)
        parent[key] = RAW_TOKEN
        return json.dumps(doc).replace(json.dumps(RAW_TOKEN), raw).encode("utf-8", "surrogatepass")

    def obj(field_: str) -> Callable[[dict], tuple[Any, Any]]:
        return lambda d: (d["objects"][0], field_)

    def pos(d: dict) -> tuple[Any, Any]:
        return d["objects"][0]["position"], 0

    return {
        "deep_nesting": b"[" * MAX_DEPTH + b"]" * MAX_DEPTH,
        "deep_objects": ('{"objects":' * 50_000 + "0" + "}" * 50_000).encode(),
        "giant_int": token(obj("n_obs"), "9" * 5000),
        "int_2_64": token(obj("n_obs"), "18446744073709551616"),
        "nan": token(pos, "NaN"),
        "inf_literal": token(pos, "1e999"),
        "lone_surrogate_key": token(lambda d: (d, "\ud800"), "1"),
        "lone_surrogate_id": token(obj("id"), '"\\ud800"'),
        "surrogate_bytes": token(obj("id"), '"\ud800"'),  # CESU-8: not UTF-8
        "wrong_dims": token(obj("embedding"), "[0.5]"),
        "missing_objects": b'{"schema_version": 1}',
        "wrong_type": b'{"schema_version": 1, "objects": "none"}',
        "not_utf8": b'{"objects": "\xff\xfe"}',
        "utf16_bom": map_json.decode().encode("utf-16"),
        "empty": b"",
        "top_level_list": b"[1, 2, 3]",
        "newline_key": token(lambda d: (d, "a\nb"), "1"),
    }


def expected_exit(decoder: Decoder, data: bytes) -> int:
    """The exit code `match` must give for `data` as its map, by the in-process oracle: 0 when
    the loader and the pipeline take it, 2 for bad input, 1 for another MergeError, -1 for a
    finding (no exit code is right)."""
    outcome, _kind, exc = check_input(decoder, data)
    if outcome == "accepted":
        return 0
    if outcome == "finding":
        return -1
    return 1 if isinstance(exc, MergeError) and not isinstance(exc, InputError) else 2


def check_cli(cli: Sequence[str], inputs: dict[str, tuple[bytes, int]], partner: bytes,
              folder: Path, timeout_s: float = 120.0) -> list[dict[str, Any]]:
    """Each input as `match --map` (with its expected exit code): a refused file must print
    exactly one line `error: ...` on stderr and exit with the expected code (2 for bad input);
    an accepted file exit 0."""
    sub = folder / "partner_submap.json"
    sub.write_bytes(partner)
    out = []
    for name, (data, expected) in inputs.items():
        p = folder / f"cli_{name}.json"
        p.write_bytes(data)
        r = subprocess.run([*cli, "match", "--map", str(p), "--submap", str(sub)],
                           capture_output=True, timeout=timeout_s, check=False)
        err = r.stderr.decode("utf-8", errors="replace").rstrip("\n")
        lines = err.split("\n") if err else []
        one_error_line = len(lines) == 1 and lines[0].startswith("error: ")
        ok = r.returncode == expected and (one_error_line if expected else not lines)
        out.append({"input": name, "bytes": len(data), "expected_exit": expected,
                    "exit": r.returncode, "stderr_lines": len(lines), "stderr": err[:200],
                    "ok": ok})
    return out


def run_fuzz(
    inputs: int = DEFAULT_INPUTS,
    seed: int = 0,
    target: FuzzTarget | str = FuzzTarget.ALL,
    out: Path | None = None,
    *,
    cli: Sequence[str] | None = None,
    cli_samples: int = 20,
    pipeline: bool = True,
    timeout_s: float = INPUT_TIMEOUT_S,
    echo: Callable[[str], None] = lambda _m: None,
    progress_factory: Callable[[str, int], Callable[[int], None]] | None = None,
) -> dict[str, Any]:
    """Fuzz every decoder of `target` with `inputs` inputs per target (split among its
    decoders by weight), seeded; optionally check a sample through the `match` command
    (`cli`: the command to run, e.g. [python, -m, mergesvc.cli]). Returns the report."""
    if inputs < 1:
        raise InputError(f"--inputs must be >= 1, got {inputs}")
    target = FuzzTarget(target)
    targets = [t for t in FuzzTarget if t is not FuzzTarget.ALL] if target is FuzzTarget.ALL \
        else [target]
    rng = random.Random(seed)
    repro = out.parent / f"{out.stem}.findings" if out is not None else None
    report: dict[str, Any] = {"seed": seed, "inputs_per_target": inputs, "targets": {},
                              "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    t_start = time.perf_counter()
    refused_samples: list[bytes] = []
    # memory-backed scratch files where there are (/dev/shm: ~0.02 ms per write and read
    # against ~2 ms on this machine's disk, which would dominate the file-reading decoders)
    shm = Path("/dev/shm")
    scratch_root = str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None
    with tempfile.TemporaryDirectory(prefix="mergesvc-fuzz-", dir=scratch_root) as tmp, \
            warnings.catch_warnings():
        warnings.simplefilter("ignore")  # overflow in casts etc.: warnings are not findings
        scratch = _Scratch(Path(tmp))
        for t in targets:
            decs = decoders([t], scratch, pipeline)
            total_w = sum(d.weight for d in decs)
            counts = [max(1, math.floor(inputs * d.weight / total_w)) for d in decs]
            counts[0] += max(0, inputs - sum(counts))
            per: list[dict[str, Any]] = []
            for d, n in zip(decs, counts):
                bar = progress_factory(d.name, n) if progress_factory else None

                def keep(data: bytes, outcome: str, name: str = d.name) -> None:
                    if name == "match.map" and outcome == "refused" and rng.random() < 0.01:
                        refused_samples.append(data)

                st = fuzz_decoder(d, n, rng, repro, timeout_s, bar,
                                  keep if d.name == "match.map" else None)
                per.append(st.as_dict())
                echo(f"  {d.name:<26} {st.inputs:>7} inputs  {st.accepted:>6} accepted  "
                     f"{sum(st.refused.values()):>7} refused  {st.findings:>4} findings  "
                     f"({st.elapsed_s:.1f} s)")
            report["targets"][t.value] = {
                "inputs": sum(p["inputs"] for p in per),
                "accepted": sum(p["accepted"] for p in per),
                "refused": sum(sum(p["refused"].values()) for p in per),
                "findings": sum(p["findings"] for p in per),
                "decoders": per,
            }
        if cli is not None and FuzzTarget.MATCH in targets and cli_samples > 0:
            map_decoder = decoders([FuzzTarget.MATCH], scratch, pipeline)[0]
            files = dict(list(nasty_match_inputs().items())[:cli_samples])
            pick = random.Random(seed).sample(refused_samples,
                                              min(len(refused_samples),
                                                  max(0, cli_samples - len(files))))
            files |= {f"fuzzed_{k}": d for k, d in enumerate(pick)}
            sample = {k: (d, expected_exit(map_decoder, d)) for k, d in files.items()}
            echo(f"  match command: {len(sample)} files through the real CLI ...")
            res = check_cli(cli, sample, match_files()[1], Path(tmp))
            report["cli_check"] = {"inputs": len(res), "ok": sum(r["ok"] for r in res),
                                   "results": res}
    report["elapsed_s"] = round(time.perf_counter() - t_start, 1)
    report["findings"] = sum(t["findings"] for t in report["targets"].values())
    report["markdown"] = fuzz_markdown(report)
    return report


def fuzz_markdown(report: dict[str, Any]) -> str:
    rows = ["| decoder | inputs | accepted | refused (by error) | findings |",
            "|---|---:|---:|---|---:|"]
    for t in report["targets"].values():
        for d in t["decoders"]:
            refused = ", ".join(
                f"{k} {v}" + (" (exit 1)" if k in d["refused_exit_1"] else "")
                for k, v in d["refused"].items()) or "-"
            rows.append(f"| {d['name']} | {d['inputs']} | {d['accepted']} | {refused} | "
                        f"{d['findings']} |")
    lines = [f"seed {report['seed']}, {report['inputs_per_target']} inputs per target, "
             f"{report['elapsed_s']} s, findings: {report['findings']}", "", *rows]
    for t in report["targets"].values():
        for d in t["decoders"]:
            for kind, n in d["finding_kinds"].items():
                lines.append(f"- {d['name']}: {n} x {kind}")
    cli = report.get("cli_check")
    if cli:
        refused = sum(r["expected_exit"] != 0 for r in cli["results"])
        lines += ["", f"`match` subprocess check: {cli['ok']}/{cli['inputs']} files as expected "
                      f"({refused} refused: one stderr line and exit 2 (1 for a solver "
                      "failure); the others, accepted in-process, exit 0)"]
        lines += [f"- {r['input']}: exit {r['exit']} (expected {r['expected_exit']}), "
                  f"{r['stderr_lines']} stderr lines: {r['stderr'][:100]}"
                  for r in cli["results"] if not r["ok"]]
    return "\n".join(lines)


__all__ = [
    "DEFAULT_INPUTS",
    "Decoder",
    "DecoderStats",
    "FuzzTarget",
    "HangError",
    "check_cli",
    "check_input",
    "decoders",
    "expected_exit",
    "fuzz_decoder",
    "fuzz_markdown",
    "match_files",
    "mutate_bytes",
    "mutate_json",
    "mutate_msgpack",
    "mutator",
    "nasty_match_inputs",
    "run_fuzz",
]
