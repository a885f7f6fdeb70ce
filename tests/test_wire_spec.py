"""docs/wire.md is the protocol: the golden vectors decode to their JSON with a second decoder
written from the spec alone (tests/wire_reference.py), mergesvc's decoder agrees, both refuse
the same corrupted messages, and the checked-in vectors are what this build writes."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgpack
import pytest
import wire_reference as ref

from mergesvc.errors import DecodeError, SchemaError
from mergesvc.link.arq import decode_fragment, encode_fragment, join_fragments, split_message
from mergesvc.link.bridge import frame_sample
from mergesvc.wire.envelope import decode_message
from mergesvc.wire.golden import check_golden, decoded_json, golden_files, write_golden
from mergesvc.wire.projection import Projection

GOLDEN = Path(__file__).resolve().parent / "golden"
NAMES = sorted(p.stem for p in GOLDEN.glob("*.bin"))
PROFILES_BY_TYPE = {("submap", p) for p in ("full", "f16", "int8", "compact")} | {
    ("map", "full"), ("map", "compact"), ("factor", "full"), ("factor", "compact"),
    ("error", "full"),
}


@pytest.fixture(scope="module")
def ref_projections() -> dict[str, dict]:
    projs = [ref.load_projection(p) for p in GOLDEN.glob("projection-*.npz")]
    return {p["id"]: p for p in projs}


@pytest.fixture(scope="module")
def projections() -> list[Projection]:
    return [Projection.load(p) for p in GOLDEN.glob("projection-*.npz")]


def _close(a: Any, b: Any, where: str = "") -> None:
    """Equal documents; floats within a relative 1e-9 (ints and floats are told apart)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {set(a) ^ set(b)}"
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{where}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{where}.{i}")
    elif isinstance(a, float) or isinstance(b, float):
        assert isinstance(a, float) and isinstance(b, float), f"{where}: {a!r} vs {b!r}"
        assert math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12), f"{where}: {a!r} vs {b!r}"
    else:
        assert type(a) is type(b) and a == b, f"{where}: {a!r} vs {b!r}"


def test_the_golden_set_covers_every_type_and_profile() -> None:
    index = json.loads((GOLDEN / "index.json").read_text())
    assert {e["name"] for e in index} == set(NAMES)
    assert {(e["type"], e["profile"]) for e in index} == PROFILES_BY_TYPE
    total = sum(p.stat().st_size for p in GOLDEN.iterdir())
    assert total < 100_000, f"tests/golden holds {total} bytes"


@pytest.mark.parametrize("name", NAMES)
def test_the_reference_decoder_reads_each_vector(name: str, ref_projections) -> None:
    data = (GOLDEN / f"{name}.bin").read_bytes()
    expected = json.loads((GOLDEN / f"{name}.json").read_text())
    _close(ref.decode(data, ref_projections), expected, name)


@pytest.mark.parametrize("name", NAMES)
def test_mergesvc_decodes_each_vector_to_its_json(name: str, projections) -> None:
    data = (GOLDEN / f"{name}.bin").read_bytes()
    expected = json.loads((GOLDEN / f"{name}.json").read_text())
    env, model = decode_message(data, projections)
    assert decoded_json(env, model) == expected  # the same code wrote it: exactly


def test_the_comparison_sees_a_difference(ref_projections) -> None:
    """The check above can fail: a changed number, a missing field, an int for a float."""
    data = (GOLDEN / "submap_f16.bin").read_bytes()
    got = ref.decode(data, ref_projections)
    bad = json.loads(json.dumps(got))
    bad["message"]["objects"][0]["position"][0] += 1e-6
    with pytest.raises(AssertionError):
        _close(got, bad)
    bad = json.loads(json.dumps(got))
    del bad["message"]["objects"][1]["label"]
    with pytest.raises(AssertionError):
        _close(got, bad)
    bad = json.loads(json.dumps(got))
    bad["message"]["stamp"] = 12
    with pytest.raises(AssertionError):
        _close(got, bad)


def _both_refuse(data: bytes, ref_projections, projections) -> None:
    with pytest.raises(ref.RefusedError):
        ref.decode(data, ref_projections)
    with pytest.raises((DecodeError, SchemaError)):
        decode_message(data, projections)


def _repack(name: str, edit) -> bytes:
    env = msgpack.unpackb((GOLDEN / f"{name}.bin").read_bytes(), raw=False)
    edit(env)
    return msgpack.packb(env, use_bin_type=True)


@pytest.mark.parametrize("name", NAMES)
def test_wrong_versions_are_refused_by_both(name: str, ref_projections, projections) -> None:
    for field, value in ((0, 2), (0, 0), (1, 2)):
        data = _repack(name, lambda env, f=field, v=value: env.__setitem__(f, v))
        _both_refuse(data, ref_projections, projections)
    with pytest.raises(SchemaError, match="schema_version 2"):
        decode_message(_repack(name, lambda env: env.__setitem__(0, 2)), projections)


@pytest.mark.parametrize("name", NAMES)
def test_truncated_and_extended_messages_are_refused_by_both(
    name: str, ref_projections, projections
) -> None:
    data = (GOLDEN / f"{name}.bin").read_bytes()
    for cut in (1, 2, len(data) // 2, len(data) - 1):
        _both_refuse(data[:cut], ref_projections, projections)
    _both_refuse(data + b"\x00", ref_projections, projections)


BLOB_NAMES = [n for n in NAMES if n.startswith(("submap", "map")) or n.startswith(
    "factor_compact")]


@pytest.mark.parametrize("name", BLOB_NAMES)
def test_a_truncated_or_padded_bit_stream_is_refused_by_both(
    name: str, ref_projections, projections
) -> None:
    at = 13 if name.startswith(("submap", "map")) else 9

    def cut(env: list) -> None:
        env[6][at] = env[6][at][:-1]

    def extend(env: list) -> None:
        env[6][at] = env[6][at] + b"\x00"

    _both_refuse(_repack(name, cut), ref_projections, projections)
    _both_refuse(_repack(name, extend), ref_projections, projections)


def test_nonzero_padding_is_refused_by_both(ref_projections, projections) -> None:
    """submap_compact's stream ends in padding bits; setting the last one is refused."""
    env = msgpack.unpackb((GOLDEN / "submap_compact.bin").read_bytes(), raw=False)
    blob = env[6][13]
    assert blob[-1] & 1 == 0
    env[6][13] = blob[:-1] + bytes([blob[-1] | 1])
    _both_refuse(msgpack.packb(env, use_bin_type=True), ref_projections, projections)


@pytest.mark.parametrize(("field", "value"), [(2, 5), (2, 6), (2, 9), (5, 4), (3, ""), (4, -1)])
def test_bad_envelope_fields_are_refused_by_both(
    field: int, value: Any, ref_projections, projections
) -> None:
    """Reserved and unknown types, an unknown profile, an empty sender, a negative seq."""
    data = _repack("submap_full", lambda env: env.__setitem__(field, value))
    _both_refuse(data, ref_projections, projections)


def test_a_factor_in_f16_and_a_missing_projection_are_refused_by_both(
    ref_projections, projections
) -> None:
    _both_refuse(_repack("factor_full", lambda env: env.__setitem__(5, 1)), ref_projections,
                 projections)
    data = (GOLDEN / "submap_compact.bin").read_bytes()
    with pytest.raises(ref.RefusedError, match="unknown"):
        ref.decode(data, {})
    with pytest.raises(DecodeError, match="projection"):
        decode_message(data, [])


def test_the_projection_id_is_the_documented_hash(ref_projections, projections) -> None:
    assert set(ref_projections) == {p.id for p in projections}


# ------------------------------------------------------------------ CRCs of the acoustic link

def _link_frames(name: str, payload_bytes: int = 40) -> list[bytes]:
    """A golden message framed as the acoustic bridge sends it (mergesvc/link)."""
    sample = frame_sample(f"submap/auv2/s1/{name}", (GOLDEN / f"{name}.bin").read_bytes())
    return [encode_fragment(f) for f in split_message(17, sample, payload_bytes)]


@pytest.mark.parametrize("name", ["submap_compact", "factor_compact", "error"])
def test_the_reference_unframes_the_acoustic_link(name: str) -> None:
    frames = _link_frames(name)
    assert len(frames) > 1
    suffix, message = ref.unframe_link(frames[::-1])
    assert suffix == f"submap/auv2/s1/{name}"
    assert message == (GOLDEN / f"{name}.bin").read_bytes()


def test_flipped_crc_bytes_are_refused_by_both() -> None:
    frames = _link_frames("submap_compact")
    for k, pos in ((0, -1), (1, -2), (len(frames) - 1, -1)):
        bad = list(frames)
        bad[k] = bad[k][:pos] + bytes([bad[k][pos] ^ 0x01]) + bad[k][len(bad[k]) + pos + 1 :]
        with pytest.raises(ref.RefusedError, match="CRC-16"):
            ref.unframe_link(bad)
        with pytest.raises(DecodeError, match="CRC-16"):
            decode_fragment(bad[k])
    # a flipped byte of the CRC-32 trailer, the fragment's CRC-16 made to match again
    last = decode_fragment(frames[-1])
    body = last.payload[:-1] + bytes([last.payload[-1] ^ 0x80])
    bad = [*frames[:-1], encode_fragment(dataclasses.replace(last, payload=body))]
    with pytest.raises(ref.RefusedError, match="CRC-32"):
        ref.unframe_link(bad)
    with pytest.raises(DecodeError, match="CRC-32"):
        join_fragments([decode_fragment(f).payload for f in bad])


def test_crc16_is_ccitt_false() -> None:
    assert ref.crc16_ccitt_false(b"123456789") == 0x29B1  # the standard check value


# ------------------------------------------------------------------ generation and --check

def test_the_checked_in_vectors_are_current() -> None:
    assert check_golden(GOLDEN) == []


def test_check_golden_sees_a_stale_folder(tmp_path: Path) -> None:
    write_golden(tmp_path)
    assert check_golden(tmp_path) == []
    (tmp_path / "error.bin").write_bytes(b"\x00")
    (tmp_path / "old_vector.json").write_text("{}")
    (tmp_path / "submap_full.json").unlink()
    assert sorted(check_golden(tmp_path)) == ["error.bin", "old_vector.json", "submap_full.json"]


def test_generation_is_deterministic() -> None:
    assert golden_files() == golden_files()


def test_codec_golden_check_command(tmp_path: Path) -> None:
    cli = [sys.executable, "-m", "mergesvc.cli", "codec", "golden"]
    r = subprocess.run([*cli, "--out", str(GOLDEN), "--check"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([*cli, "--out", str(tmp_path / "none"), "--check"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 1
    assert r.stderr.count("\n") == 1 and "out of date" in r.stderr


def test_check_golden_reports_a_missing_projection(tmp_path: Path) -> None:
    """A folder without the projection: the projection is reported, not an exception."""
    write_golden(tmp_path)
    for p in tmp_path.glob("projection-*.npz"):
        p.unlink()
    stale = check_golden(tmp_path)
    assert len(stale) == 1 and stale[0].startswith("projection-")
