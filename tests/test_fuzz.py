"""`bench fuzz` (mergesvc/bench/fuzz.py): a quick seeded run finds nothing in the decoders, the
oracle reports what it should, and the `match` command gives one line and exit 2."""

from __future__ import annotations

import json
import random
import sys
from pathlib import Path

import pytest

from mergesvc.bench.fuzz import (
    Decoder,
    FuzzTarget,
    check_cli,
    check_input,
    decoders,
    expected_exit,
    fuzz_decoder,
    match_files,
    nasty_match_inputs,
    run_fuzz,
)
from mergesvc.errors import DecodeError
from mergesvc.wire import decode_message

QUICK = 2_000  # inputs per target
CLI = [sys.executable, "-m", "mergesvc.cli"]


@pytest.mark.parametrize("target", ["wire", "link", "match", "other"])
def test_quick_run_finds_nothing(target: str, tmp_path: Path) -> None:
    report = run_fuzz(QUICK, seed=1, target=target, out=tmp_path / "fuzz.json")
    t = report["targets"][target]
    assert t["inputs"] == QUICK
    assert t["findings"] == 0, report["markdown"]
    assert t["refused"] > 0 and t["accepted"] > 0  # the mutations reach both sides
    assert not (tmp_path / "fuzz.findings").exists()


def test_a_run_is_reproducible_from_its_seed() -> None:
    def counts(report: dict) -> list:
        return [(d["accepted"], d["refused"], d["findings"])
                for d in report["targets"]["link"]["decoders"]]

    a = run_fuzz(500, seed=7, target="link")
    assert counts(a) == counts(run_fuzz(500, seed=7, target="link"))
    assert counts(a) != counts(run_fuzz(500, seed=8, target="link"))


def _broken(data: bytes) -> None:
    """decode_message behind a wrapper with the bug the fuzzer exists to find."""
    if len(data) > 40 and data[7] % 3 == 0:
        raise ValueError("unchecked field")
    decode_message(data)


def test_the_oracle_reports_foreign_errors_and_saves_reproducers(tmp_path: Path) -> None:
    wire = decoders([FuzzTarget.WIRE], _scratch(tmp_path))[0]
    broken = Decoder("broken", FuzzTarget.WIRE, _broken, wire.mutate)
    st = fuzz_decoder(broken, 300, random.Random(0), tmp_path)
    assert st.findings > 0
    assert any(k.startswith("ValueError at") for k in st.finding_kinds)
    saved = Path(st.reproducers[0]["file"])
    assert saved.exists()
    outcome, kind, _ = check_input(broken, saved.read_bytes())
    assert outcome == "finding" and kind.startswith("ValueError")
    assert st.inputs == st.accepted + sum(st.refused.values()) + st.findings


def test_the_oracle_reports_a_hang() -> None:
    def hang(_data: bytes) -> None:
        while True:
            pass

    d = Decoder("hang", FuzzTarget.LINK, hang, lambda rng: b"x")
    outcome, kind, _ = check_input(d, b"x", timeout_s=0.2)
    assert outcome == "finding" and kind.startswith("hang")


def test_refusals_with_the_declared_errors_are_not_findings() -> None:
    def refuse(_data: bytes) -> None:
        raise DecodeError("bad bytes")

    d = Decoder("refuse", FuzzTarget.WIRE, refuse, lambda rng: b"x")
    assert check_input(d, b"x")[:2] == ("refused", "DecodeError")


def test_match_command_gives_one_line_and_exit_2_on_the_nastiest_files(tmp_path: Path) -> None:
    nasty = nasty_match_inputs()
    map_decoder = decoders([FuzzTarget.MATCH], _scratch(tmp_path))[0]
    names = ("deep_nesting", "giant_int", "lone_surrogate_id")
    sample = {k: (nasty[k], expected_exit(map_decoder, nasty[k])) for k in names}
    assert all(e == 2 for _, e in sample.values())
    res = check_cli(CLI, sample, match_files()[1], tmp_path)
    assert all(r["ok"] for r in res), json.dumps(res, indent=1)


def _scratch(folder: Path):
    from mergesvc.bench.fuzz import _Scratch

    return _Scratch(folder)


def test_the_defects_the_fuzzer_found_stay_fixed(tmp_path: Path) -> None:
    """Reproducers of what the first runs found, each refused with a MergeError now:
    `codec encode` of a map with n_obs >= 2^63 (was OverflowError) and of an error message
    with about_seq >= 2^64 (OverflowError from msgpack; now refused as the wire's int64 range,
    2^63 - 1, at load, like a submap's seq); a projection file that is a lone .npy
    (TypeError) or a zip with an unsupported compression method (NotImplementedError)."""
    import io

    import numpy as np

    from mergesvc.errors import SchemaError
    from mergesvc.wire import Projection, encode_file
    from mergesvc.wire.golden import golden_projection, golden_vectors

    models = {v.name: v.model for v in golden_vectors()}
    doc = json.loads(models["map_full"].model_dump_json())
    doc["objects"][0]["n_obs"] = 2**63
    (tmp_path / "map.json").write_text(json.dumps(doc))
    with pytest.raises(SchemaError, match="too large"):
        encode_file(tmp_path / "map.json", tmp_path / "map.bin", "full")
    doc = json.loads(models["error"].model_dump_json())
    for big in (2**63, 2**64):
        doc["about_seq"] = big
        (tmp_path / "error.json").write_text(json.dumps(doc))
        with pytest.raises(SchemaError, match="about_seq"):
            encode_file(tmp_path / "error.json", tmp_path / "error.bin", "full")
    doc["about_seq"] = 2**63 - 1  # the largest the wire carries
    (tmp_path / "error.json").write_text(json.dumps(doc))
    encode_file(tmp_path / "error.json", tmp_path / "error.bin", "full")
    doc = json.loads(models["map_full"].model_dump_json())
    doc["objects"][0]["variance"] = 1e300  # valid JSON and model, no float32 carries it
    (tmp_path / "var.json").write_text(json.dumps(doc))
    with pytest.raises(SchemaError, match="variances must lie in"):
        encode_file(tmp_path / "var.json", tmp_path / "var.bin", "full")
    doc["objects"][0]["variance"] = 0.1
    doc["objects"][0]["position"] = [1e300, 0.0, 0.0]  # finite; the affinity matrix was not
    (tmp_path / "far.json").write_text(json.dumps(doc))
    with pytest.raises(SchemaError, match="less than or equal to 1000000000"):
        encode_file(tmp_path / "far.json", tmp_path / "far.bin", "full")

    p = golden_projection()
    np.save(tmp_path / "one.npy", p.mean_d)
    buf = io.BytesIO()
    np.savez(buf, mean=p.mean_d, basis=p.basis_kd, scale=p.scale_k, id=np.array(p.id))
    raw = bytearray(buf.getvalue())
    raw[raw.index(b"PK\x01\x02") + 10] = 99  # compression method 99 in the central directory
    (tmp_path / "method.npz").write_bytes(bytes(raw))
    for name in ("one.npy", "method.npz"):
        with pytest.raises(DecodeError, match="is not a projection file"):
            Projection.load(tmp_path / name)
    # pickled objects: refused in our words (numpy's would suggest loading them unsafely)
    np.savez(tmp_path / "pickled.npz", mean=np.array([{"a": 1}], dtype=object))
    with pytest.raises(DecodeError, match=r"is not a projection file: it holds pickled objects, "
                       r"which are never loaded \(`mergesvc projection make` writes one\)$"):
        Projection.load(tmp_path / "pickled.npz")
