"""Binary map files: a map's or submap's arrays as an uncompressed .npz, memory-mapped on load.

Members (each a .npy; any numpy reads the file with `np.load`):
    meta          uint8, UTF-8 JSON: {"format": "mergesvc-map", "version": 1, "kind": "map" |
                  "submap", "robot_id", "session_id", "up"?, "seq"?, "stamp"?, "keyframe"?,
                  "odometry"?} (the JSON file's fields besides `objects`)
    ids, id_ends  uint8 UTF-8 of every id back to back, int64 (n,) end offset of each
    labels, label_ends, has_label   the same for the optional labels (absent when none has one)
    position_xyz_m float64 (n, 3); embeddings float32 (n, d); n_obs int64 (n,)
    variances     float64 (n,) one number per object, or (n, d) per dimension
`load_arrays` maps the embeddings (and per-dimension variances) of a large map from the file
instead of reading them: it costs memory only for the rows a match touches. Members under
`MAP_FROM_BYTES` are read (mapped, each scattered row read would be a system call).
Everything is checked as the JSON files are (finite, positive variances, unique ids, sizes),
in one line.
"""

from __future__ import annotations

import json
import mmap
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.core.arrays import ObjectArrays, map_file, release_rows
from mergesvc.core.model import (
    MAX_EMBEDDING_DIM,
    MAX_ID_LENGTH,
    ObjectMap,
    Submap,
    arrays_to_nodes,
)
from mergesvc.errors import (
    DecodeError,
    InputError,
    MergeError,
    SchemaError,
    cannot_read,
    one_line,
)

FORMAT = "mergesvc-map"
VERSION = 1
# a binary map may be larger than a JSON one (MAX_OBJECTS): it is read without a per-object
# model, memory-mapped when large
MAX_BINARY_OBJECTS = 5_000_000
# members of at least this size are memory-mapped (about 20,000 objects of 384 float32)
MAP_FROM_BYTES = 32 << 20


def is_binary_map(path: Path | str) -> bool:
    """Whether `path` names a binary map file (by its .npz suffix)."""
    return Path(path).suffix.lower() == ".npz"


def _text_blob(values: list[str]) -> tuple[np.ndarray, np.ndarray]:
    raw = [v.encode() for v in values]
    ends = np.cumsum([len(b) for b in raw], dtype=np.int64)
    return np.frombuffer(b"".join(raw), dtype=np.uint8), ends


def _texts(blob: np.ndarray, ends: np.ndarray, what: str) -> list[str]:
    data = bytes(np.asarray(blob, dtype=np.uint8))
    starts = np.concatenate([[0], ends[:-1]]).tolist()
    try:
        return [data[a:b].decode() for a, b in zip(starts, ends.tolist())]
    except UnicodeDecodeError as exc:
        raise DecodeError(f"{what} are not UTF-8") from exc


def save_arrays(path: Path | str, arrays: ObjectArrays, meta: dict[str, Any],
                labels: list[str | None] | None = None) -> None:
    """Write `arrays` and the file fields `meta` (robot_id, session_id, ..., kind) to path."""
    ids, id_ends = _text_blob([str(i) for i in arrays.ids])
    members: dict[str, np.ndarray] = {
        "meta": np.frombuffer(json.dumps({"format": FORMAT, "version": VERSION, **meta})
                              .encode(), dtype=np.uint8),
        "ids": ids, "id_ends": id_ends,
        "position_xyz_m": np.ascontiguousarray(arrays.position_xyz_m, dtype=np.float64),
        "embeddings": np.ascontiguousarray(arrays.embeddings_nd, dtype=np.float32),
        "variances": np.ascontiguousarray(
            arrays.variances_nd[:, 0] if arrays.isotropic else arrays.variances_nd),
        "n_obs": np.asarray(arrays.n_obs, dtype=np.int64),
    }
    if labels is not None and any(lab is not None for lab in labels):
        members["labels"], members["label_ends"] = _text_blob([lab or "" for lab in labels])
        members["has_label"] = np.array([lab is not None for lab in labels])
    try:
        _write_npz(Path(path), members)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc


_ALIGN = 64  # member data starts at a multiple of this in the file (numpy pads .npy headers
# to 64 bytes): a mapped array is aligned, so BLAS multiplies it in place (an unaligned one
# made numpy fall back to a loop 30x slower)
_PAD_ID = 0x6D73  # a private zip extra field that only pads


def _write_npz(path: Path, members: dict[str, np.ndarray]) -> None:
    """An uncompressed .npz, as numpy.savez writes it, with each member's data aligned."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in members.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_STORED
            start = zf.fp.tell()  # the local header goes here
            # local header 30 bytes + name + our padding field (4 + pad) + zip64 field (20)
            head = 30 + len(info.filename.encode()) + 4 + 20
            header_len = len(_npy_header(arr))
            pad = (-(start + head + header_len)) % _ALIGN
            info.extra = (_PAD_ID.to_bytes(2, "little") + pad.to_bytes(2, "little")
                          + b"\0" * pad)
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)


def _npy_header(arr: np.ndarray) -> bytes:
    """The bytes numpy writes before an array's data in a .npy (magic + padded header)."""
    import io

    buf = io.BytesIO()  # write_array's own header (version 1.0: our headers are short)
    np.lib.format.write_array_header_1_0(
        buf, np.lib.format.header_data_from_array_1_0(np.asanyarray(arr)))
    return buf.getvalue()


def _member_views(path: Path) -> dict[str, tuple[int, np.dtype, tuple[int, ...], bool]]:
    """Each stored member: (byte offset of its data, dtype, shape, fortran order)."""
    out = {}
    with zipfile.ZipFile(path) as z, open(path, "rb") as f:
        for info in z.infolist():
            if not info.filename.endswith(".npy"):
                continue
            if info.compress_type != zipfile.ZIP_STORED:
                raise DecodeError(f"{path}: member {info.filename} is compressed (write it with "
                                  "numpy.savez, not savez_compressed)")
            f.seek(info.header_offset)
            local = f.read(30)
            if local[:4] != b"PK\x03\x04":
                raise DecodeError(f"{path}: broken zip entry {info.filename}")
            skip = int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
            f.seek(info.header_offset + 30 + skip)
            version = np.lib.format.read_magic(f)
            header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                      else np.lib.format.read_array_header_2_0)(f)
            shape, fortran, dtype = header
            if dtype.hasobject:
                raise DecodeError(f"{path}: member {info.filename} holds Python objects")
            out[info.filename[:-4]] = (f.tell(), dtype, shape, fortran)
    return out


def load_arrays(path: Path | str, mmap_large: bool = True
                ) -> tuple[ObjectArrays, dict[str, Any], list[str | None] | None]:
    """Read a binary map file: (arrays, the file fields, labels or None). The embeddings and
    per-dimension variances are memory-mapped (read-only) when mmap_large and they take at
    least `MAP_FROM_BYTES`. DecodeError / SchemaError (one line) on anything a JSON map file
    would be refused for."""
    p = Path(path)
    try:
        views = _member_views(p)
    except (FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        raise DecodeError(cannot_read(
            p, exc, "`mergesvc convert MAP.json MAP.npz` writes a binary map")) from exc
    except (OSError, zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise DecodeError(f"{p} is not a binary map file: {one_line(exc)}") from exc
    need = {"meta", "ids", "id_ends", "position_xyz_m", "embeddings", "variances", "n_obs"}
    if not need <= set(views):
        raise DecodeError(f"{p} is not a binary map file: missing {sorted(need - set(views))}")

    def read(name: str, mapped: bool = False) -> np.ndarray:
        offset, dtype, shape, fortran = views[name]
        mapped = mapped and int(np.prod(shape)) * dtype.itemsize >= MAP_FROM_BYTES
        # an unaligned member (a file numpy.savez wrote) is read instead: BLAS needs alignment
        if mapped and int(np.prod(shape)) > 0 and offset % max(dtype.alignment, 1) == 0:
            with open(p, "rb") as f:
                mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
                map_file(mm, f.fileno())  # scattered rows are read from the file, not mapped
            arr = np.ndarray(shape, dtype=dtype, buffer=mm, offset=offset,
                             order="F" if fortran else "C")
            return arr
        with open(p, "rb") as f:
            f.seek(offset)
            count = int(np.prod(shape))
            arr = np.fromfile(f, dtype=dtype, count=count)
        if arr.size != count:
            raise DecodeError(f"{p}: member {name} is truncated")
        return arr.reshape(shape, order="F" if fortran else "C")

    try:
        meta = json.loads(bytes(read("meta")).decode())
    except (ValueError, UnicodeDecodeError) as exc:
        raise DecodeError(f"{p}: meta is not JSON: {one_line(exc)}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DecodeError(f"{p} is not a binary map file (format {meta!r:.40})")
    if meta.get("version") != VERSION:
        raise SchemaError(f"{p}: unsupported version {meta.get('version')!r}, this build "
                          f"reads {VERSION}")
    n_emb = views["embeddings"][2]
    if len(n_emb) != 2 or not 1 <= n_emb[0] <= MAX_BINARY_OBJECTS or \
            not 1 <= n_emb[1] <= MAX_EMBEDDING_DIM:
        raise SchemaError(f"{p}: embeddings of shape {n_emb}: at most {MAX_BINARY_OBJECTS} "
                          f"objects of at most {MAX_EMBEDDING_DIM} dimensions")
    n = n_emb[0]
    id_ends = read("id_ends")
    if id_ends.shape != (n,) or id_ends.dtype.kind not in "iu":
        raise SchemaError(f"{p}: id_ends must be ({n},) integers")
    lengths = np.diff(np.concatenate([[0], id_ends]))
    if lengths.min() < 1 or lengths.max() > 4 * MAX_ID_LENGTH or id_ends[-1] != \
            int(np.prod(views["ids"][2])):
        raise SchemaError(f"{p}: ids must each have 1 to {MAX_ID_LENGTH} characters")
    ids = _texts(read("ids"), id_ends, f"{p}: ids")
    if max(len(i) for i in ids) > MAX_ID_LENGTH:
        raise SchemaError(f"{p}: ids must each have 1 to {MAX_ID_LENGTH} characters")
    if len(set(ids)) != n:
        raise SchemaError(f"{p}: duplicate object ids")
    var_shape = views["variances"][2]
    n_obs = read("n_obs")
    if n_obs.shape != (n,) or n_obs.dtype.kind not in "iu" or (n and n_obs.min() < 1):
        raise SchemaError(f"{p}: n_obs must be ({n},) integers >= 1")
    try:
        arrays = ObjectArrays(
            ids=ids,
            position_xyz_m=read("position_xyz_m"),
            embeddings_nd=read("embeddings", mapped=mmap_large),
            variances_nd=read("variances", mapped=mmap_large and len(var_shape) == 2),
            n_obs=n_obs.astype(np.int64),
            up_xyz=None if meta.get("up") is None else np.asarray(meta["up"], dtype=float),
        )
    except MergeError as exc:
        raise SchemaError(f"invalid {p}: {one_line(exc)}") from exc
    except (ValueError, TypeError) as exc:
        raise SchemaError(f"invalid {p}: {one_line(exc)}") from exc
    release_pages(arrays)  # the checks read every mapped page: not this process's memory
    labels = None
    if "has_label" in views:
        text = _texts(read("labels"), read("label_ends"), f"{p}: labels")
        has = read("has_label").astype(bool)
        if len(text) != n or has.shape != (n,):
            raise SchemaError(f"{p}: labels must be one per object")
        labels = [t if h else None for t, h in zip(text, has.tolist())]
    return arrays, {k: v for k, v in meta.items() if k not in ("format", "version")}, labels


def release_pages(arrays: ObjectArrays) -> None:
    """Drop the mapped pages a whole-map pass (validation, norms, an index) read from this
    process's resident memory; they stay in the page cache and come back on the next read."""
    for a in (arrays.embeddings_nd, arrays.variances_nd):
        release_rows(a)


def model_to_file(model: ObjectMap, path: Path | str) -> None:
    """A map or submap model as a binary map file."""
    meta: dict[str, Any] = {"kind": "submap" if isinstance(model, Submap) else "map",
                            **model.model_dump(mode="json", exclude={"objects", "schema_version"},
                                               exclude_none=True)}
    save_arrays(path, model.arrays(), meta, [o.label for o in model.objects])


def file_to_model(path: Path | str) -> ObjectMap:
    """A binary map file as the map or submap model its JSON file would give (validated)."""
    arrays, meta, labels = load_arrays(path, mmap_large=False)
    kind = meta.pop("kind", "map")
    nodes = arrays_to_nodes(arrays)
    if labels is not None:
        nodes = [n.model_copy(update={"label": lab}) for n, lab in zip(nodes, labels)]
    model = Submap if kind == "submap" else ObjectMap
    from pydantic import ValidationError

    try:
        return model.model_validate({**meta, "objects": [n.model_dump() for n in nodes]})
    except ValidationError as exc:
        raise SchemaError(f"invalid {path}: {one_line(exc)}") from exc


__all__ = ["FORMAT", "MAX_BINARY_OBJECTS", "VERSION", "file_to_model", "is_binary_map",
           "load_arrays", "model_to_file", "release_pages", "save_arrays"]
