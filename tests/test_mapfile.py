"""Binary map files: round trips both ways, memory mapping, the boundary's one-line errors,
and `mergesvc convert` / `match` on them."""

from __future__ import annotations

import io
import json
import mmap
import zipfile
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mergesvc.cli import app
from mergesvc.core.arrays import ObjectArrays
from mergesvc.core.model import ObjectMap, Submap
from mergesvc.errors import DecodeError, SchemaError
from mergesvc.wire import mapfile
from mergesvc.wire.files import load_model
from mergesvc.wire.mapfile import (
    file_to_model,
    load_arrays,
    model_to_file,
    release_pages,
    save_arrays,
)

runner = CliRunner()


def _submap(n: int = 6, d: int = 8) -> Submap:
    rng = np.random.default_rng(0)
    return Submap.model_validate({
        "robot_id": "b", "session_id": "s1", "seq": 4, "keyframe": 9, "up": [0, 0, 1],
        "objects": [{"id": f"ob\u00e9{k}", "position": rng.normal(size=3).tolist(),
                     "embedding": rng.normal(size=d).tolist(),
                     "variance": 0.2 if k % 2 else rng.uniform(0.1, 1, size=d).tolist(),
                     "n_obs": k + 1, "label": None if k % 3 else "car"} for k in range(n)]})


def test_json_to_binary_and_back_keeps_everything_at_float32(tmp_path: Path) -> None:
    sub = _submap()
    model_to_file(sub, tmp_path / "s.npz")
    back = file_to_model(tmp_path / "s.npz")
    assert isinstance(back, Submap)
    assert (back.seq, back.keyframe, back.up, back.robot_id) == (4, 9, (0.0, 0.0, 1.0), "b")
    for a, b in zip(sub.objects, back.objects):
        assert (a.id, a.position, a.n_obs, a.label) == (b.id, b.position, b.n_obs, b.label)
        np.testing.assert_array_equal(np.float32(a.embedding), np.float32(b.embedding))
        assert a.variance == b.variance  # float64 as given, a number stays a number
    # binary -> model -> binary is exact
    model_to_file(back, tmp_path / "t.npz")
    x, _, _ = load_arrays(tmp_path / "s.npz")
    y, _, _ = load_arrays(tmp_path / "t.npz")
    for name in ("position_xyz_m", "embeddings_nd", "variances_nd", "n_obs"):
        np.testing.assert_array_equal(getattr(x, name), getattr(y, name))


def _mapping(a: np.ndarray) -> mmap.mmap | None:
    base = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    return base if isinstance(base, mmap.mmap) else None


def test_large_members_are_memory_mapped_and_scalar_variances_stored_as_one_column(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    n, d = 1000, 64
    rng = np.random.default_rng(1)
    arr = ObjectArrays([f"m{i}" for i in range(n)], rng.normal(size=(n, 3)),
                       rng.normal(size=(n, d)), rng.uniform(0.1, 1, n),
                       np.ones(n, dtype=np.int64))
    save_arrays(tmp_path / "m.npz", arr, {"kind": "map", "robot_id": "a", "session_id": "s"})
    with np.load(tmp_path / "m.npz") as z:  # any numpy reads it
        assert z["variances"].shape == (n,) and z["embeddings"].dtype == np.float32
    small, _, _ = load_arrays(tmp_path / "m.npz")  # 256 kB: read, not mapped
    assert _mapping(small.embeddings_nd) is None
    np.testing.assert_array_equal(small.embeddings_nd, arr.embeddings_nd)
    monkeypatch.setattr(mapfile, "MAP_FROM_BYTES", n * d * 4)
    got, meta, labels = load_arrays(tmp_path / "m.npz")
    assert _mapping(got.embeddings_nd) is not None and not got.embeddings_nd.flags.writeable
    assert got.isotropic and labels is None and meta["kind"] == "map"
    np.testing.assert_array_equal(got.embeddings_nd, arr.embeddings_nd)
    release_pages(got)  # pages dropped from this process, data still readable
    np.testing.assert_array_equal(got.embeddings_nd[::97], arr.embeddings_nd[::97])


def _npz(members: dict[str, np.ndarray], compressed: bool = False) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **members)
    return buf.getvalue()


def _members(**change: np.ndarray) -> dict[str, np.ndarray]:
    meta = json.dumps({"format": "mergesvc-map", "version": 1, "kind": "map",
                       "robot_id": "a", "session_id": "s"}).encode()
    m = {"meta": np.frombuffer(meta, np.uint8), "ids": np.frombuffer(b"ab", np.uint8),
         "id_ends": np.array([1, 2]), "position_xyz_m": np.zeros((2, 3)),
         "embeddings": np.ones((2, 4), np.float32), "variances": np.ones(2),
         "n_obs": np.ones(2, np.int64)}
    m.update(change)
    return m


@pytest.mark.parametrize(("members", "compressed", "error", "text"), [
    (_members(), True, DecodeError, "compressed"),
    (_members(ids=np.frombuffer(b"aa", np.uint8)), False, SchemaError, "duplicate"),
    (_members(embeddings=np.full((2, 4), np.nan, np.float32)), False, SchemaError,
     r"object 0 \(id 'a'\): its embedding has NaN or inf"),
    (_members(embeddings=np.array([[1, 0, 0, 0], [0, 1, np.inf, 0]], np.float32)), False,
     SchemaError, r"object 1 \(id 'b'\): its embedding has NaN or inf"),
    (_members(variances=np.array([1.0, np.nan])), False, SchemaError,
     r"object 1 \(id 'b'\): its variance has NaN or inf"),
    (_members(position_xyz_m=np.array([[0.0, np.nan, 0], [0, 0, 0]])), False, SchemaError,
     r"object 0 \(id 'a'\): its position has NaN or inf"),
    (_members(variances=np.zeros(2)), False, SchemaError, "positive"),
    (_members(variances=np.array([1.0, -1.0])), False, SchemaError,
     r"object 1 \(id 'b'\): its variance must be positive, not -1$"),
    (_members(n_obs=np.zeros(2, np.int64)), False, SchemaError, "n_obs"),
    (_members(id_ends=np.array([1, 5])), False, SchemaError, "ids"),
    ({k: v for k, v in _members().items() if k != "n_obs"}, False, DecodeError, "missing"),
    (_members(meta=np.frombuffer(b'{"format": "x"}', np.uint8)), False, DecodeError, "not a"),
])
def test_bad_files_are_refused_in_one_line(tmp_path: Path, members, compressed, error,
                                           text) -> None:
    (tmp_path / "bad.npz").write_bytes(_npz(members, compressed))
    with pytest.raises(error, match=text) as info:
        load_arrays(tmp_path / "bad.npz")
    assert "\n" not in str(info.value)
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(DecodeError):
        load_arrays(tmp_path / "junk.npz")
    good = zipfile.ZipFile(io.BytesIO(_npz(_members())))
    assert "meta.npy" in good.namelist()


def test_convert_and_match_through_the_cli(tmp_path: Path, small_kitti_scenario) -> None:
    sc = small_kitti_scenario
    (tmp_path / "map.json").write_text(sc.map.model_dump_json())
    (tmp_path / "sub.json").write_text(sc.submap.model_dump_json())
    for a, b in (("map.json", "map.npz"), ("sub.json", "sub.npz"), ("map.npz", "back.json")):
        res = runner.invoke(app, ["convert", str(tmp_path / a), str(tmp_path / b)])
        assert res.exit_code == 0, res.output
    assert len(load_model(ObjectMap, tmp_path / "back.json").objects) == len(sc.map.objects)
    out = {}
    for m, s in (("map.json", "sub.json"), ("map.npz", "sub.npz")):
        res = runner.invoke(app, ["match", "--map", str(tmp_path / m), "--submap",
                                  str(tmp_path / s), "--json"])
        assert res.exit_code == 0, res.output
        out[m] = json.loads(res.output)
    assert out["map.json"]["matches"] == out["map.npz"]["matches"]
    res = runner.invoke(app, ["convert", str(tmp_path / "map.json"), str(tmp_path / "x.json")])
    assert res.exit_code == 2 and "error:" in res.output
