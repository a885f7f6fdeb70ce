"""docs/wire.md is the protocol: the golden vectors decode to their JSON with a second decoder
written from the spec alone (tests/wire_reference.py), mergesvc's decoder agrees, both refuse
the same corrupted messages, and the checked-in vectors are what this build writes."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
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
def test_the_reference_encoder_writes_each_vector_byte_for_byte(name: str, ref_projections) -> None:
    """A sender that follows docs/wire.md to the letter writes what mergesvc writes."""
    inp = json.loads((GOLDEN / f"{name}.in.json").read_text())
    assert ref.encode(inp, ref_projections) == (GOLDEN / f"{name}.bin").read_bytes()


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
    (tmp_path / "empty").mkdir()
    r = subprocess.run([*cli, "--out", str(tmp_path / "empty"), "--check"], capture_output=True,
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


# ------------------------------------------------------------------ what the vectors pin down
# (docs/wire.md's answers to what a client written from it alone had to guess, issue 27):
# each vector below would come out otherwise under the other reading.

def _payload(name: str) -> list:
    return msgpack.unpackb((GOLDEN / f"{name}.bin").read_bytes(), raw=False)


def _doc(name: str) -> dict[str, Any]:
    return json.loads((GOLDEN / f"{name}.in.json").read_text())["document"]


def test_one_object_and_one_correspondence_have_delta_min_0() -> None:
    assert _payload("submap_one_object")[6][6] == [1, "obj", 8, 0, 0]
    f = _payload("factor_compact_one_correspondence")[6]
    assert f[7] == [1, "m", 10, 0, 0] and f[8] == [1, "obj", 3, 0, 0]


def test_who_writes_nil_and_the_envelope_seq_of_a_submap_without_seq() -> None:
    env = _payload("submap_full")  # seq = the envelope's, robot_id = the sender: both nil
    assert env[4] == 5 and env[6][0] is None and env[6][2] is None
    env = _payload("submap_seq_differs")
    assert env[4] == 3 and env[6][0] is None and env[6][2] == 40
    env = _payload("submap_no_seq")
    assert env[4] == 0 and env[6][2] == -1
    env = _payload("map_full")  # a map sent by another node: robot_id written, seq nil
    assert env[3] == "mergesvc" and env[6][0] == "auv1" and env[6][2] is None


def test_an_explicit_seq_equal_to_the_envelopes_reads_as_nil(ref_projections,
                                                             projections) -> None:
    data = _repack("submap_full", lambda env: env[6].__setitem__(2, 5))
    assert ref.decode(data, ref_projections) == ref.decode(
        (GOLDEN / "submap_full.bin").read_bytes(), ref_projections)
    assert decode_message(data, projections)[1].seq == 5


def test_a_stamp_is_a_float_even_a_whole_one(ref_projections, projections) -> None:
    data = (GOLDEN / "submap_no_seq.bin").read_bytes()
    assert b"\xcb" + struct.pack(">d", 1700000000.0) in data  # msgpack float64
    for bad in (1700000000, math.nan, math.inf):  # an integer; not finite (§8)
        _both_refuse(_repack("submap_no_seq", lambda env, b=bad: env[6].__setitem__(3, b)),
                     ref_projections, projections)


def test_compact_odometry_sigmas_are_rounded_to_nearest() -> None:
    """Six 11-bit codes rint((log2 sigma + 32) * 32), after translation and rotation."""
    doc = _doc("submap_pose_compact")
    pose = _payload("submap_pose_compact")[6][15]
    r = ref.Bits(pose[2])
    for _ in range(3):
        r.read(r.read(6))
    r.read(2 + 3 * 15)
    codes = [r.read(11) for _ in range(6)]
    log2_sigma = [math.log2(math.sqrt(doc["odometry"]["covariance"][i][i])) for i in range(6)]
    assert codes == [round((x + 32) * 32) for x in log2_sigma]
    assert codes != [math.floor((x + 32) * 32) for x in log2_sigma]  # the vector tells them apart


def test_z_is_clipped_before_atanh() -> None:
    """Correlations 1 - 2^-52: z clipped to 1 - 1e-15 gives atanh 17.62, code 8191 (and -z, 0);
    clipping a instead would give floor((1 + 5) / 10 * 8192) = 4915."""
    blob = _payload("factor_compact_near_singular")[6][9]
    r = ref.Bits(blob)
    r.read(2)
    for _ in range(3):
        r.read(r.read(6))
    r.read(2), r.many(3, 15), r.many(6, 14)  # rotation, sigmas
    g = r.many(15, 13)  # z_10; z_20, z_21; z_30, z_31, z_32; z_40, z_41, z_42, z_43; ...
    assert (g[0], g[9]) == (8191, 0)
    assert math.floor((1 - 1e-15 + 5) / 10 * 8192) == 4915


def test_scores_equal_in_float32_take_no_bits_and_decode_to_lo(ref_projections) -> None:
    got = ref.decode((GOLDEN / "factor_compact_scores_equal_in_f32.bin").read_bytes(),
                     ref_projections)
    lo = float(np.float32(0.7))
    assert [c["score"] for c in got["message"]["correspondences"]] == [lo, lo, lo]
    scores = [c["score"] for c in _doc("factor_compact_scores_equal_in_f32")["correspondences"]]
    assert len(set(scores)) == 3  # they differ in float64


def test_f16_is_rounded_once_from_float64(ref_projections) -> None:
    emb = np.array([o["embedding"] for o in _doc("submap_f16_rounding")["objects"]])
    got = ref.decode((GOLDEN / "submap_f16_rounding.bin").read_bytes(), ref_projections)
    dec = np.array([o["embedding"] for o in got["message"]["objects"]])
    np.testing.assert_array_equal(dec, emb.astype(np.float16).astype(np.float64))
    twice = emb.astype(np.float32).astype(np.float16).astype(np.float64)
    assert (dec != twice).sum() >= 3  # through float32 the vector comes out otherwise
    assert dec[0, 0] == 1.0 and dec[0, 1] == 1 + 2**-9  # ties to even
    assert dec[0, 4] == 65504.0 and np.signbit(dec[0, 7])


def test_int8_divides_in_float64_by_the_float32_scale() -> None:
    doc = _doc("submap_int8_rounding")
    blob = _payload("submap_int8_rounding")[6][13]
    n, d = 2, 8
    start = len(blob) - n * d  # the int8 codes end the stream (sizes of §4.6)
    codes = np.frombuffer(blob[start:], dtype="i1").reshape(n, d)
    scales = np.frombuffer(blob[start - 4 * n:start], dtype="<f4")
    E = np.array([o["embedding"] for o in doc["objects"]])
    for e, s, c in zip(E, scales, codes):
        peak = np.abs(e).max()
        assert s == np.float32(peak / 127)
        np.testing.assert_array_equal(c, np.rint(e / float(s)))
        assert not np.array_equal(c, np.rint(e / (peak / 127)))  # the unrounded scale
        assert not np.array_equal(c, np.rint(e.astype(np.float32) / s))  # float32 arithmetic


def test_trailing_digits_are_ascii() -> None:
    f = _payload("factor_compact_unicode_ids")[6]
    assert f[7][:2] == [1, "pier\u0663"]  # ASCII digits after an Arabic-Indic one
    assert f[8][0] == 0  # 'buoy\u0663': no ASCII digit at the end
