"""Message files: encode_file (a model JSON file -> one message file) and decode_file.

A compact map or submap is coded on the fleet's projection (`mergesvc projection make`) and
refused without one: a projection fitted on the file alone is one the service does not have.
decode_file finds a compact message's projection given, or as `projection-<id>.npz` beside it.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel

from mergesvc.core.model import (
    MAX_FILE_BYTES,
    SUBMAP_FIELDS,
    ErrorMessage,
    Factor,
    ObjectMap,
    Submap,
    parse_model,
    read_valid_json,
)
from mergesvc.errors import DecodeError, InputError, SchemaError, cannot_read, one_line
from mergesvc.wire.envelope import (
    AnyMessage,
    decode_message,
    encode_message,
    message_type_of,
    parse_profile,
    peek_projection_id,
)
from mergesvc.wire.fields import validate_model
from mergesvc.wire.profiles import (
    DEFAULT_LIMITS,
    CodecLimits,
    CodecSettings,
    Envelope,
    MessageType,
    Profile,
)
from mergesvc.wire.projection import Projection

PROJECTION_FILE = "projection-{id}.npz"  # a projection beside a message file (decode_file)


@dataclass(frozen=True)
class EncodeStats:
    msg_type: MessageType
    profile: Profile
    n_bytes: int
    n_objects: int
    bytes_per_object: float
    projection_id: str | None = None


def load_model(model: type[ObjectMap], path: Path | str) -> ObjectMap:
    """Read a map or submap JSON file (the `match` command's inputs)."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise SchemaError(f"{p}: {size} bytes is larger than the limit {MAX_FILE_BYTES}")
        data = p.read_bytes()
    except OSError as exc:
        raise DecodeError(cannot_read(
            p, exc, "`mergesvc example DIR` writes a map and a submap to try")) from exc
    _not_binary(p, data[:2])
    try:
        loaded = parse_model(model, data, what=str(p))
    except SchemaError:
        if model is ObjectMap:  # a submap given as a map (a map is a valid submap)
            try:
                parse_model(Submap, data)
            except (SchemaError, DecodeError):
                pass
            else:
                raise SchemaError(f"{p} is a submap file, not a map (map and submap "
                                  "swapped?)") from None
        raise
    except RecursionError as exc:  # the json module's own limit on nesting
        raise DecodeError(f"{p} is not usable JSON: nested too deeply") from exc
    except ValueError as exc:  # not JSON or pydantic errors (parse_model maps those): the
        # json module's refusal of integers beyond Python's digit limit (4300 digits)
        raise DecodeError(f"{p} is not usable JSON: {_json_limit(exc)}") from exc
    return _check_arrays(loaded, str(p))


def _not_binary(path: Path, head: bytes) -> None:
    """DecodeError when a JSON file's first bytes are a zip's (a binary map file)."""
    if head == b"PK":
        raise DecodeError(f"{path} is a binary map file and this reads JSON: `mergesvc "
                          f"convert {path} OUT.json` writes it as JSON")


def _check_arrays(loaded: ObjectMap, what: str) -> ObjectMap:
    """Numbers the model takes but arrays cannot hold (n_obs >= 2^63): SchemaError."""
    try:
        loaded.arrays()
    except (OverflowError, ValueError) as exc:
        big = next((k for k, o in enumerate(loaded.objects) if o.n_obs >= 2**63), None)
        where = f"objects.{big}.n_obs: " if big is not None else ""
        raise SchemaError(f"invalid {what}: {where}a number too large "
                          f"({one_line(exc)})") from exc
    return loaded


def _json_limit(exc: ValueError) -> str:
    """The json module's ValueError in words that fit any reader of the file."""
    text = one_line(exc)
    if "integer string conversion" in text:
        return f"an integer longer than {sys.get_int_max_str_digits()} digits"
    return text


def _valid_objects(data: bytes) -> ObjectMap | None:
    """A valid map or submap file as `read_valid_json` reads it (a map when it validates as
    one: a submap's own keys are extra fields to a map); None for anything else, which the
    json module then reads and says what is wrong with."""
    if b'"objects"' not in data:
        return None
    # a submap's keys anywhere (perhaps in a label): a submap first, a map if it has none
    is_sub = any(f'"{k}"'.encode() in data for k in SUBMAP_FIELDS)
    for model in (Submap, ObjectMap) if is_sub else (ObjectMap,):
        got = read_valid_json(model, data)
        if got is not None and (model is ObjectMap or got.model_fields_set & set(SUBMAP_FIELDS)):
            return got
    return None


def _read_json_model(path: Path) -> AnyMessage:
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            raise SchemaError(f"{path}: larger than {MAX_FILE_BYTES} bytes")
        data = path.read_bytes()
        _not_binary(path, data[:2])
        fast = _valid_objects(data)
        if fast is not None:
            return _check_arrays(fast, str(path))
        raw = json.loads(data)
    except OSError as exc:
        raise DecodeError(cannot_read(path, exc)) from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DecodeError(f"{path} is not valid JSON ({one_line(exc)}): give a map, submap, "
                          "factor or error message file") from exc
    except RecursionError as exc:
        raise DecodeError(f"{path} is not usable JSON: nested too deeply") from exc
    except ValueError as exc:  # an integer beyond Python's digit limit (4300 digits)
        raise DecodeError(f"{path} is not usable JSON: {_json_limit(exc)}") from exc
    if not isinstance(raw, dict):
        raise SchemaError(f"invalid {path}: expected a JSON object")
    if "objects" in raw:
        model: type[BaseModel] = Submap if any(k in raw for k in SUBMAP_FIELDS) else ObjectMap
    elif "factor_id" in raw:
        model = Factor
    elif "code" in raw:
        model = ErrorMessage
    else:
        raise SchemaError(f"invalid {path}: not a map, submap, factor or error message")
    loaded = validate_model(model, raw, str(path))
    return _check_arrays(loaded, str(path)) if isinstance(loaded, ObjectMap) else loaded


def load_objects(path: Path | str) -> ObjectMap:
    """A map or submap JSON file, whichever it is (a submap has `seq`, `stamp`, `keyframe` or
    `odometry`, as encode_file decides)."""
    p = Path(path)
    model = _read_json_model(p)
    if not isinstance(model, ObjectMap):
        raise SchemaError(f"invalid {p}: a {type(model).__name__}, not a map or submap")
    return model


def _projection_arg(projection: Projection | Path | str | None) -> Projection | None:
    if projection is None or isinstance(projection, Projection):
        return projection
    return Projection.load(projection)


def encode_file(
    in_json_path: Path | str,
    out_bin_path: Path | str,
    profile: Profile | str,
    projection: Projection | Path | str | None = None,
    *,
    sender: str | None = None,
    seq: int | None = None,
    settings: CodecSettings | None = None,
) -> EncodeStats:
    """Encode a map / submap / factor JSON file into one message file.

    A JSON object with `objects` is a submap if it has `seq` or `stamp`, else a map. sender
    defaults to the robot id (robot_a for factors), seq to the submap's seq (else 0).
    A `compact` map or submap needs the fleet's projection: InputError without one.
    """
    out = Path(out_bin_path)
    profile = parse_profile(profile)
    model = _read_json_model(Path(in_json_path))
    proj = _projection_arg(projection)
    if isinstance(model, ObjectMap) and profile is Profile.COMPACT and proj is None:
        raise InputError(
            "the compact profile codes embeddings on the fleet's projection: pass "
            "--projection P.npz (the file given to serve and agent; make one with "
            "`mergesvc projection make`), or use --profile full, f16 or int8"
        )
    if sender is None:
        sender = model.robot_a if isinstance(model, Factor) else getattr(model, "robot_id", "")
        sender = sender or "unknown"
    if seq is None:
        seq = getattr(model, "seq", None) or 0
    data = encode_message(model, profile, sender, seq, projection=proj, settings=settings)
    try:
        out.write_bytes(data)
    except OSError as exc:
        raise InputError(f"cannot write {out}: {exc.strerror or exc}") from exc
    is_map = isinstance(model, ObjectMap)
    n = len(model.objects) if is_map else 0
    used_proj = proj if is_map and profile is Profile.COMPACT else None
    exact = not is_map and not (isinstance(model, Factor) and profile is Profile.COMPACT)
    return EncodeStats(
        msg_type=message_type_of(model),
        profile=Profile.FULL if exact else profile,
        n_bytes=len(data),
        n_objects=n,
        bytes_per_object=len(data) / n if n else float(len(data)),
        projection_id=used_proj.id if used_proj else None,
    )


def decode_file(
    in_bin_path: Path | str,
    out_json_path: Path | str,
    projection: Projection | Path | str | None = None,
    *,
    limits: CodecLimits = DEFAULT_LIMITS,
) -> tuple[Envelope, AnyMessage]:
    """Decode one message file and write the model as JSON (loadable with load_model).

    A compact map needs its projection: the one given, else `projection-<id>.npz` beside
    the input."""
    src = Path(in_bin_path)
    try:
        if src.stat().st_size > limits.max_message_bytes:
            raise DecodeError(f"{src}: larger than {limits.max_message_bytes} bytes")
        data = src.read_bytes()
    except OSError as exc:
        raise DecodeError(f"cannot read {src}: {exc.strerror or exc}") from exc
    proj = _projection_arg(projection)
    if proj is None:
        pid = peek_projection_id(data, limits)
        if pid is not None:
            beside = src.parent / PROJECTION_FILE.format(id=pid)
            if not beside.exists():
                raise DecodeError(
                    f"{src} was coded with projection {pid}: {beside} not found; "
                    "pass --projection FILE"
                )
            proj = Projection.load(beside)
    envelope, model = decode_message(data, proj, limits)
    out = Path(out_json_path)
    try:
        out.write_text(model.model_dump_json())
    except OSError as exc:
        raise InputError(f"cannot write {out}: {exc.strerror or exc}") from exc
    return envelope, model


__all__ = [
    "PROJECTION_FILE",
    "EncodeStats",
    "decode_file",
    "encode_file",
    "load_model",
    "load_objects",
]
