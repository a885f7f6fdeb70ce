"""Golden test vectors of the wire protocol (docs/wire.md): small messages of every type and
profile, each as `<name>.bin` (the message) and `<name>.json` (what it decodes to).

The messages are built from fixed numbers (no fitting, no random draws at encode time), so the
bytes are the same on every run; `check_golden` says which files of a folder differ from
what this build writes. `<name>.json` holds {"envelope": ..., "message": ...}: the envelope
fields and the decoded model as JSON, fields that are null left out; `<name>.in.json` the
document that was encoded and the encoder's choices (a second encoder checks its bytes). The
compact vectors need the projection saved beside them as `projection-<id>.npz`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mergesvc.core.model import ErrorMessage, Factor, ObjectMap, Submap
from mergesvc.errors import InputError
from mergesvc.wire.envelope import (
    CODEC_VERSION,
    AnyMessage,
    decode_message,
    encode_message,
    message_type_of,
)
from mergesvc.wire.files import PROJECTION_FILE
from mergesvc.wire.profiles import CodecSettings, Envelope, Profile
from mergesvc.wire.projection import Projection

DIM = 8  # embedding dimension of every vector: small files
_COMPACT_SETTINGS = CodecSettings(embedding_bits=28)  # fewer bits than 8 per component
_DEFAULT_SETTINGS = CodecSettings()


@dataclass(frozen=True)
class GoldenVector:
    """One message to write: `name`.bin / `name`.json."""

    name: str
    model: AnyMessage
    profile: Profile
    sender: str
    seq: int
    settings: CodecSettings = _DEFAULT_SETTINGS
    about: str = ""  # what the vector exercises, for people


def golden_projection() -> Projection:
    """A fixed PCA projection (DIM -> 6): rows of the 8x8 Sylvester-Hadamard matrix / sqrt(8),
    decreasing scales. Built from exact numbers, not fitted: the same id on every machine."""
    H = np.array([[1.0]])
    while H.shape[0] < DIM:
        H = np.block([[H, H], [H, -H]])
    basis = H[[1, 2, 4, 3, 5, 6]] / math.sqrt(DIM)
    mean = np.arange(DIM) / 16.0 - 0.25
    scale = np.array([2.0, 1.5, 1.0, 0.75, 0.5, 0.25])
    return Projection(mean, basis, scale)


def _embedding(k: int, seed: int) -> list[float]:
    """Fixed pseudo-random numbers with 4 decimals (a tiny LCG: the same everywhere)."""
    out = []
    x = (seed * 7919 + k * 104729 + 1) % 2**31
    for _ in range(DIM):
        x = (1103515245 * x + 12345) % 2**31
        out.append(round(x / 2**31 * 2 - 1, 4))
    return out


def _objects(
    n: int,
    seed: int,
    *,
    ids: list[str] | None = None,
    variances: str = "iso",
    labels: bool = False,
    n_obs: list[int] | None = None,
    zero_embedding: bool = False,
) -> list[dict[str, Any]]:
    out = []
    for k in range(n):
        var: float | list[float] = round(0.05 + 0.1 * k, 3)
        if variances == "dim" or (variances == "mixed" and k % 2):
            var = [round(0.01 * (j + 1) * (k + 1), 4) for j in range(DIM)]
        obj: dict[str, Any] = {
            "id": ids[k] if ids else f"obj{3 + 2 * k + (k == n - 1) * 5}",
            "position": [round(1.25 * k - 2.0, 2), round(0.5 * k * k, 2), round(-0.3 * k, 2)],
            "embedding": [0.0] * DIM if zero_embedding and k == 1 else _embedding(k, seed),
            "variance": var,
            "n_obs": n_obs[k] if n_obs else k + 1,
        }
        if labels and k != 2:
            obj["label"] = ["buoy", "tire", "crate"][k % 3]
        out.append(obj)
    return out


def _odometry() -> dict[str, Any]:
    c, s = math.cos(0.15), math.sin(0.15)  # a yaw of 0.3 rad
    sig = [0.01, 0.012, 0.02, 0.1, 0.15, 0.05]
    C = np.diag(np.square(sig))
    C[0, 3] = C[3, 0] = 0.3 * sig[0] * sig[3]
    C[4, 5] = C[5, 4] = -0.2 * sig[4] * sig[5]
    return {
        "from_keyframe": 4,
        "T_from_to": {"translation": [3.5, -1.25, 0.1], "quaternion_wxyz": [c, 0.0, 0.0, s]},
        "covariance": C.tolist(),
    }


def _covariance6() -> list[list[float]]:
    A = np.array([[((3 * i + 5 * j) % 7 - 3) / 10.0 for j in range(6)] for i in range(6)])
    C = A @ A.T + np.diag([1e-3, 2e-3, 1e-3, 0.04, 0.09, 0.01])
    return ((C + C.T) / 2).tolist()


def _factor(**kw: Any) -> Factor:
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    doc: dict[str, Any] = {
        "factor_id": "f17",
        "robot_a": "auv1",
        "session_a": "s0",
        "robot_b": "auv2",
        "session_b": "s1",
        "T_a_b": {"translation": [12.345, -6.789, 0.25], "quaternion_wxyz": q.tolist()},
        "covariance": _covariance6(),
    }
    doc.update(kw)
    return Factor.model_validate(doc)


def _corr(scores: list[float]) -> list[dict[str, Any]]:
    return [
        {"object_a": f"m{10 + 3 * k}", "object_b": f"obj{3 + 2 * k}", "score": s}
        for k, s in enumerate(scores)
    ]


def _near_singular_covariance() -> list[list[float]]:
    """Correlations 1 - 2^-52 (rotation x, y) and -(1 - 2^-52) (translation x, y): z past
    1 - 1e-15, clipped before atanh (docs/wire.md §6.2 item 4). Powers of two: exact."""
    sig = [1.0, 1.0, 0.5, 0.25, 2.0, 4.0]
    r = 1.0 - 2.0**-52
    C = np.diag(np.square(sig))
    C[0, 1] = C[1, 0] = r * sig[0] * sig[1]
    C[3, 4] = C[4, 3] = -r * sig[3] * sig[4]
    return C.tolist()


def _f16_rounding_embeddings() -> list[list[float]]:
    """Values where binary16 rounding from float64 (once) differs from rounding through
    float32 (twice), exact ties (to even), a subnormal, the largest finite value, -0."""
    h = 2.0**-11  # half a binary16 step at 1
    return [
        [1 + h, 1 + 3 * h, 1 + h + 2.0**-40, -(1 + h + 2.0**-40), 65519.99, 2.0**-25 + 2.0**-60,
         3 * 2.0**-26, -0.0],
        [0.1, -0.2, 0.3, 2.0**-25, -(2.0**-25), 1000.0625, 1 - 2.0**-12, 0.5],
    ]


def _int8_rounding_embeddings() -> list[list[float]]:
    """Quotients e / s just past a half (the float32 scale is below peak / 127): rounded up
    in float64, to even with the unrounded scale or in float32 arithmetic."""
    return [
        [1.0, 10.5 / 127, 0.492126, -20.5 / 127, 64.5 / 127, -100.5 / 127, 0.25, 0.0],
        [-0.3, 0.3 * 10.5 / 127, 0.3 * 0.492126, 0.1, -0.2, 0.0, 0.3 * 64.5 / 127, 0.3],
    ]


def golden_vectors() -> list[GoldenVector]:
    """Every golden message, in a fixed order."""
    sub = {"robot_id": "auv2", "session_id": "s1", "stamp": 12.5}
    v = [
        GoldenVector(
            "submap_full", Submap(**sub, seq=5, objects=_objects(4, 1)), Profile.FULL, "auv2", 5,
            about="isotropic variances, delta-coded ids, seq as the envelope's",
        ),
        GoldenVector(
            "submap_f16",
            Submap(**sub, seq=6, up=(0.0, 0.0, 2.0),
                   objects=_objects(5, 2, variances="mixed", labels=True)),
            Profile.F16, "auv2", 6,
            about="labels (one absent), mixed variances (var_mode 2), up declared",
        ),
        GoldenVector(
            "submap_int8",
            Submap(robot_id="auv2", session_id="s1",
                   objects=_objects(3, 3, ids=["rock-a", "tire", "buoy_7"], variances="dim",
                                    zero_embedding=True)),
            Profile.INT8, "auv2", 7,
            about="ids as strings, per-dimension variances, an all-zero embedding, no seq "
            "(-1), no stamp",
        ),
        GoldenVector(
            "submap_compact",
            Submap(**sub, seq=8, objects=_objects(5, 4, labels=True, n_obs=[1, 2, 300, 4, 5])),
            Profile.COMPACT, "auv2", 8, _COMPACT_SETTINGS,
            about="PCA coefficients on the golden projection, n_obs saturated at 255",
        ),
        GoldenVector(
            "submap_pose_full",
            Submap(**sub, seq=9, keyframe=7, odometry=_odometry(), objects=_objects(3, 5)),
            Profile.FULL, "auv2", 9, about="keyframe and exact odometry; no up (nil before pose)",
        ),
        GoldenVector(
            "submap_pose_f16",
            Submap(**sub, seq=10, keyframe=7, odometry=_odometry(), up=(0.0, -1.0, 0.0),
                   objects=_objects(3, 6)),
            Profile.F16, "auv2", 10, about="keyframe, odometry bit stream with correlations, up",
        ),
        GoldenVector(
            "submap_pose_int8",
            Submap(**sub, seq=11, keyframe=0, objects=_objects(3, 7)),
            Profile.INT8, "auv2", 11, about="a session's first keyframe: pose [keyframe] only",
        ),
        GoldenVector(
            "submap_pose_compact",
            Submap(**sub, seq=12, keyframe=7, odometry=_odometry(), objects=_objects(3, 8)),
            Profile.COMPACT, "auv2", 12, _COMPACT_SETTINGS,
            about="compact odometry: six standard deviations, no correlations",
        ),
        GoldenVector(
            "map_full",
            ObjectMap(robot_id="auv1", session_id="s0", objects=_objects(4, 9, labels=True)),
            Profile.FULL, "mergesvc", 0, about="a map sent by another node: robot_id given",
        ),
        GoldenVector(
            "map_compact",
            ObjectMap(robot_id="auv1", session_id="s0", up=(0.0, 0.0, -1.0),
                      objects=_objects(4, 10, variances="dim")),
            Profile.COMPACT, "auv1", 1, _COMPACT_SETTINGS,
            about="compact map: per-dimension variances sent as their mean",
        ),
        GoldenVector(
            "factor_full",
            _factor(correspondences=_corr([0.91, 0.85, 0.7]), status="accepted"),
            Profile.FULL, "mergesvc", 20, about="a factor as its JSON document (msgpack map)",
        ),
        GoldenVector(
            "factor_full_keyframes",
            _factor(keyframe_a=3, keyframe_b=7),
            Profile.FULL, "mergesvc", 21, about="a pose-level factor, no status",
        ),
        GoldenVector(
            "factor_compact",
            _factor(correspondences=_corr([0.91, 0.85, 0.7, 0.66]), status="accepted",
                    keyframe_a=3, keyframe_b=7),
            Profile.COMPACT, "mergesvc", 22, about="compact factor with correspondences, keyframes",
        ),
        GoldenVector(
            "factor_compact_retracted",
            _factor(factor_id="f9", status="retracted"), Profile.COMPACT, "mergesvc", 23,
            about="no correspondences (ids nil)",
        ),
        GoldenVector(
            "factor_compact_equal_scores",
            _factor(correspondences=[
                {"object_a": "door", "object_b": "tire", "score": 0.5},
                {"object_a": "m4", "object_b": "obj9", "score": 0.5},
                {"object_a": "m5", "object_b": "obj12", "score": 0.5},
            ]),
            Profile.COMPACT, "mergesvc", 24,
            about="ids as strings, equal scores (0-bit score codes), no status",
        ),
        GoldenVector(
            "error",
            ErrorMessage(code="decode_error", detail="submap 7: truncated", about_seq=7),
            Profile.FULL, "mergesvc", 25, about="an error answer",
        ),
        GoldenVector(
            "error_no_seq", ErrorMessage(code="schema_error"), Profile.FULL, "mergesvc", 26,
            about="an error about no particular message",
        ),
        # the encoder's choices docs/wire.md pins down (issue 27)
        GoldenVector(
            "submap_one_object",
            Submap(**sub, seq=30, objects=_objects(1, 11)), Profile.FULL, "auv2", 30,
            about="n = 1: kind-1 ids with delta_min 0 and width 0 (§4.1)",
        ),
        GoldenVector(
            "submap_seq_differs",
            Submap(**sub, seq=40, objects=_objects(2, 12)), Profile.FULL, "auv2", 3,
            about="the payload seq (40) is not the envelope's (3): written; robot_id is the "
            "sender's: nil (§4)",
        ),
        GoldenVector(
            "submap_no_seq",
            Submap(robot_id="auv2", session_id="s1", stamp=1700000000.0,
                   objects=_objects(2, 13)),
            Profile.FULL, "auv2", 0,
            about="no seq: payload seq -1, envelope seq 0; a whole-second stamp is still a "
            "float64 (§4)",
        ),
        GoldenVector(
            "submap_f16_rounding",
            Submap(**sub, seq=41, objects=[
                {**o, "embedding": e}
                for o, e in zip(_objects(2, 14), _f16_rounding_embeddings(), strict=True)]),
            Profile.F16, "auv2", 41,
            about="binary16 rounded once from float64, ties to even, subnormals, 65519.99 "
            "-> 65504 (§4.6)",
        ),
        GoldenVector(
            "submap_int8_rounding",
            Submap(**sub, seq=42, objects=[
                {**o, "embedding": e}
                for o, e in zip(_objects(2, 15), _int8_rounding_embeddings(), strict=True)]),
            Profile.INT8, "auv2", 42,
            about="int8: float32 scale, the division in float64 (§4.6)",
        ),
        GoldenVector(
            "factor_compact_near_singular",
            _factor(factor_id="f30", covariance=_near_singular_covariance(), status="accepted"),
            Profile.COMPACT, "mergesvc", 30,
            about="correlations of +-(1 - 2^-52): z clipped to +-(1 - 1e-15) before atanh, "
            "codes 8191 and 0 (§6.2 item 4)",
        ),
        GoldenVector(
            "factor_compact_one_correspondence",
            _factor(factor_id="f31", correspondences=_corr([0.8])), Profile.COMPACT,
            "mergesvc", 31,
            about="one correspondence: ids with delta_min 0, hi = lo, no score bits (§4.1, §6.2)",
        ),
        GoldenVector(
            "factor_compact_scores_equal_in_f32",
            _factor(factor_id="f32", correspondences=_corr([0.7, 0.7000000000000001,
                                                            0.70000001])),
            Profile.COMPACT, "mergesvc", 32,
            about="scores that differ in float64, not in float32: hi = lo, each decodes to "
            "float32(0.7) (§6.2 item 5)",
        ),
        GoldenVector(
            "factor_compact_unicode_ids",
            _factor(factor_id="f33", correspondences=[
                {"object_a": f"pier\u0663{k}", "object_b": f"buoy{d}", "score": 0.9 - 0.1 * i}
                for i, (k, d) in enumerate(zip((7, 9, 12), "\u0663\u0664\u0665",
                                               strict=True))]),
            Profile.COMPACT, "mergesvc", 33,
            about="trailing digits are ASCII 0-9 only: 'pier\u06637' is prefix 'pier\u0663' + 7;"
            " 'buoy\u0663' (an Arabic-Indic digit) has none: ids as strings (§4.1)",
        ),
    ]
    return v


def decoded_json(env: Envelope, model: AnyMessage) -> dict[str, Any]:
    """What `<name>.json` holds: the envelope and the decoded model, nulls left out."""
    envelope: dict[str, Any] = {
        "schema_version": env.schema_version,
        "codec_version": CODEC_VERSION,
        "type": env.msg_type.value,
        "sender": env.sender,
        "seq": env.seq,
        "profile": env.profile.value,
    }
    if env.projection_id is not None:
        envelope["projection_id"] = env.projection_id
    return {"envelope": envelope, "message": model.model_dump(mode="json", exclude_none=True)}


def encoder_input(g: GoldenVector) -> dict[str, Any]:
    """What `<name>.in.json` holds: the document the sender had, and every choice of its
    encoder in the terms of docs/wire.md (the header values it writes): encoding it as the
    spec says gives `<name>.bin` byte for byte."""
    return {
        "type": message_type_of(g.model).value,
        "profile": g.profile.value,
        "sender": g.sender,
        "seq": g.seq,
        "resolution_um": round(g.settings.position_resolution_m * 1e6),
        "translation_resolution_um": round(g.settings.translation_resolution_m * 1e6),
        "budget_bits": g.settings.embedding_bits,
        "step16": max(1, round(g.settings.coef_step_scale * 16)),
        "document": g.model.model_dump(mode="json", exclude_none=True),
    }


def golden_files() -> dict[str, bytes]:
    """File name -> content of every golden file except the projection (see golden_projection):
    `<name>.bin`, `<name>.json`, `<name>.in.json` and `index.json` (each vector's name and what
    it exercises)."""
    proj = golden_projection()
    files: dict[str, bytes] = {}
    index = []
    for g in golden_vectors():
        data = encode_message(g.model, g.profile, g.sender, g.seq, projection=proj,
                              settings=g.settings)
        env, model = decode_message(data, proj)
        files[f"{g.name}.bin"] = data
        text = json.dumps(decoded_json(env, model), indent=1, sort_keys=True) + "\n"
        files[f"{g.name}.json"] = text.encode()
        text = json.dumps(encoder_input(g), sort_keys=True, ensure_ascii=False) + "\n"
        files[f"{g.name}.in.json"] = text.encode()
        index.append({"name": g.name, "type": env.msg_type.value, "profile": env.profile.value,
                      "bytes": len(data), "about": g.about})
    files["index.json"] = (json.dumps(index, indent=1) + "\n").encode()
    return files


def write_golden(out_dir: Path | str) -> list[Path]:
    """Write every golden file and the projection into `out_dir`; returns the paths."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        paths = []
        for name, content in golden_files().items():
            (out / name).write_bytes(content)
            paths.append(out / name)
    except OSError as exc:
        raise InputError(f"cannot write golden vectors to {out}: {exc.strerror or exc}") from exc
    proj = golden_projection()
    paths.append(proj.save(out / PROJECTION_FILE.format(id=proj.id)))
    return paths


def check_golden(folder: Path | str) -> list[str]:
    """Names of the golden files in `folder` that are missing or differ from this build's
    (the projection compared by content: .npz files carry time stamps); [] when current."""
    src = Path(folder)
    stale = []
    files = golden_files()
    for name, content in files.items():
        path = src / name
        try:
            if path.read_bytes() != content:
                stale.append(name)
        except OSError:
            stale.append(name)
    stale += sorted(  # left over from vectors this build no longer writes
        p.name for p in src.glob("*") if p.suffix in (".bin", ".json") and p.name not in files
    )
    proj = golden_projection()
    name = PROJECTION_FILE.format(id=proj.id)
    try:
        if Projection.load(src / name).id != proj.id:
            stale.append(name)
    except InputError:
        stale.append(name)
    return stale


__all__ = [
    "DIM",
    "GoldenVector",
    "check_golden",
    "decoded_json",
    "encoder_input",
    "golden_files",
    "golden_projection",
    "golden_vectors",
    "write_golden",
]
