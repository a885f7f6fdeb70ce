"""The fuzzer's mutators: bytes (flips, interesting values, splices of the seeds), and the
structure-aware ones for msgpack and JSON documents (a subtree replaced by a nasty value: deep
nesting up to MAX_DEPTH, huge numbers, wrong types, raw tokens spliced in after serialisation).
Every draw comes from the caller's seeded `random.Random`.
"""

from __future__ import annotations

import json
import random
from collections.abc import Callable, Sequence
from typing import Any

import msgpack

MAX_DEPTH = 100_000  # deepest nesting the structure-aware mutators build


# --- mutators ---------------------------------------------------------------------------------

_INTERESTING_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFF, 0xC0, 0xC1, 0xDC, 0xDD, 0xDE, 0xDF, 0xD9)


def mutate_bytes(rng: random.Random, data: bytes, seeds: Sequence[bytes]) -> bytes:
    """1-4 byte-level edits: bit flips, interesting bytes, inserts, deletes, truncation,
    duplicated ranges, splices with another seed, random bytes."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(9)
        n = len(b)
        if op == 0 and n:
            b[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n:
            b[rng.randrange(n)] = rng.choice(_INTERESTING_BYTES)
        elif op == 2:
            i = rng.randint(0, n)
            b[i:i] = rng.randbytes(rng.randint(1, 8))
        elif op == 3 and n:
            i = rng.randrange(n)
            del b[i:i + rng.randint(1, 16)]
        elif op == 4:
            del b[rng.randint(0, n):]
        elif op == 5 and n:
            i = rng.randrange(n)
            j = min(n, i + rng.randint(1, 64))
            b[i:i] = b[i:j] * rng.randint(1, 8)
        elif op == 6:
            other = rng.choice(seeds)
            b = b[:rng.randint(0, n)] + other[rng.randint(0, len(other)):]
        elif op == 7 and n:
            i = rng.randrange(n)
            b[i:i + 4] = rng.randrange(1 << 32).to_bytes(4, "big")
        elif op == 8:
            b = bytearray(rng.randbytes(rng.randint(0, 64)))
    return bytes(b)


def _pick_path(rng: random.Random, tree: Any) -> list[tuple[Any, Any]]:
    """(container, key) pairs from the root to a random node (at least one step)."""
    path: list[tuple[Any, Any]] = []
    node = tree
    while isinstance(node, list | dict) and node:
        keys = list(range(len(node))) if isinstance(node, list) else list(node)
        key = rng.choice(keys)
        path.append((node, key))
        node = node[key]
        if rng.random() < 0.25:
            break
    return path


RAW_TOKEN = "\x00FUZZ\x00"  # placeholder a raw token is spliced in for after serialisation


def _edit_tree(rng: random.Random, tree: Any, nasty: Callable[[random.Random], Any]) -> Any:
    """One structural edit of a decoded tree: replace, delete, duplicate, append, wrap a node."""
    path = _pick_path(rng, tree)
    if not path:
        return nasty(rng)
    parent, key = rng.choice(path) if rng.random() < 0.3 else path[-1]
    op = rng.randrange(6)
    if op <= 1:
        parent[key] = nasty(rng)
    elif op == 2:
        del parent[key]
    elif op == 3 and isinstance(parent, list):
        parent.insert(key, parent[key])
    elif op == 3:
        parent[f"{key}_"] = parent[key]  # an extra key
    elif op == 4:
        parent[key] = [parent[key]]
    elif isinstance(parent, list):
        parent.extend(parent[:rng.randint(1, 4)])
    else:
        parent[key] = {"x": parent[key]} if rng.random() < 0.5 else None
    return tree


def _nasty_msgpack(rng: random.Random) -> Any:
    choices: list[Any] = [
        2**64 - 1, 2**63, 2**63 - 1, -(2**63), -1, 0, 255, 256, 2**31, 2**32,
        float("nan"), float("inf"), float("-inf"), 1e308, -0.0, 5e-324, True, False, None,
        "", "x" * rng.choice((1, 128, 129, 4096, 70_000)), "\u00e9\U0001f600", b"", b"\x00" * 4,
        rng.randbytes(rng.randint(1, 40)), [], {}, [0] * rng.choice((3, 7, 64, 70_000)),
        {"": 0}, {"objects": []}, [[]], [None] * 16, RAW_TOKEN,
    ]
    return rng.choice(choices)


def _raw_msgpack(rng: random.Random) -> bytes:
    """Bytes no packer writes: deep nesting, lying lengths, ext types, reserved codes."""
    depth = rng.choice((64, 600, 5000, MAX_DEPTH))
    return rng.choice((
        b"\x91" * depth + b"\xc0",
        b"\x81\xa1k" * min(depth, 5000) + b"\xc0",
        b"\xdd\xff\xff\xff\xff",  # array32 claiming 4 billion items
        b"\xdf\xff\xff\xff\xff",  # map32 claiming 4 billion entries
        b"\xc6\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff",
        b"\xd4\x01\x00", b"\xc7\x01\x05\x00", b"\xc1", b"\xcb" + b"\x7f\xf8" + b"\x00" * 6,
        b"\x82\x01\x02\x01\x03",  # int map keys, one duplicated
    ))


def mutate_msgpack(rng: random.Random, data: bytes) -> bytes:
    """Decode a valid message, edit its tree 1-3 times, encode it again."""
    try:
        tree = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception:
        return data
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        tree = _edit_tree(rng, tree, _nasty_msgpack)
    try:
        out = msgpack.packb(tree, use_bin_type=True)
    except (ValueError, TypeError, OverflowError):
        return data
    marker = msgpack.packb(RAW_TOKEN)
    return out.replace(marker, _raw_msgpack(rng), 1)


_JSON_TOKENS = (
    "NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1e-400", "-0", "-0.0", "0e0",
    "18446744073709551616", "9223372036854775808", "-9223372036854775809",
    "1.7976931348623157e308", "4.9e-324", "1" * 4301, "9" * 5000, "-" + "9" * 4300,
    "0." + "1" * 5000, "1E+2147483648", '"\\ud800"', '"\\udfff\\ud800"', '"\\u0000"',
    '"\U0001f600\u202e"', '"a\\nb"', '"' + "x" * 100_000 + '"', "true", "false", "null",
    "[]", "{}", '""', "[null]", '{"": null}',
)


def _nasty_json(rng: random.Random) -> Any:
    if rng.random() < 0.5:
        return RAW_TOKEN
    return rng.choice([
        0, -1, 1, 2**63, -(2**63) - 1, 2**64, 0.5, -1.5, 1e300, "", "a", "\u00e9", True, False,
        None, [], {}, [0.0] * rng.choice((1, 2, 4, 7, 9, 1000)), [[0.0, 0.0, 0.0]], {"id": "a"},
        [1.0, 0.0, 0.0, 0.0], [[1.0] * 6] * 6, "objects", "NaN",
    ])


def _json_raw_token(rng: random.Random) -> str:
    if rng.random() < 0.15:
        depth = rng.choice((100, 1000, 5000, MAX_DEPTH))
        inner = rng.choice(("[", '{"a":', '{"objects":['))
        close = {"[": "]", '{"a":': "}", '{"objects":[': "]}"}[inner]
        return inner * depth + "0" + close * depth
    return rng.choice(_JSON_TOKENS)


def mutate_json(rng: random.Random, text: bytes) -> bytes:
    """Parse a valid JSON document, edit its tree 1-3 times, dump it again with raw tokens
    (NaN, 1e999, 5000-digit integers, lone surrogates, deep nesting) spliced in."""
    tree = json.loads(text)
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        tree = _edit_tree(rng, tree, _nasty_json)
    out = json.dumps(tree, ensure_ascii=rng.random() < 0.5)
    marker = json.dumps(RAW_TOKEN)
    while marker in out:
        out = out.replace(marker, _json_raw_token(rng), 1)
    enc = "utf-8" if rng.random() < 0.95 else rng.choice(("utf-16", "utf-32", "utf-8-sig"))
    return out.encode(enc, errors="surrogatepass")


def mutator(seeds: Sequence[bytes], structured: Callable[[random.Random, bytes], bytes] | None,
            p_structured: float = 0.6, fix: Callable[[random.Random, bytes], bytes] | None = None
            ) -> Callable[[random.Random], bytes]:
    """Next input: a seed through the structure-aware mutator (p_structured) or byte edits,
    sometimes both; `fix` then e.g. recomputes a checksum so the decoder looks further."""

    def next_input(rng: random.Random) -> bytes:
        data = rng.choice(seeds)
        if structured is not None and rng.random() < p_structured:
            data = structured(rng, data)
            if rng.random() < 0.1:
                data = mutate_bytes(rng, data, seeds)
        else:
            data = mutate_bytes(rng, data, seeds)
        return fix(rng, data) if fix is not None else data

    return next_input


__all__ = ["MAX_DEPTH", "RAW_TOKEN", "mutate_bytes", "mutate_json", "mutate_msgpack", "mutator"]
