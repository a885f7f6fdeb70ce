"""Wire and file models (pydantic v2): object nodes, object maps, submaps, match results.

Everything crossing a boundary is validated here: finite numbers, positive variances, one
embedding dimension per map, unique ids, bounded sizes. The core works on `ObjectArrays`.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from enum import Enum
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

from mergesvc.core.arrays import MAX_COORDINATE_M, ObjectArrays
from mergesvc.errors import DecodeError, MergeError, SchemaError

if TYPE_CHECKING:
    from typing_extensions import Self

SCHEMA_VERSION = 1
MAX_EMBEDDING_DIM = 4096
MAX_OBJECTS = 200_000
MAX_ID_LENGTH = 128
MAX_FILE_BYTES = 2 * 1024**3
# |coordinate| of an object, metres (MAX_COORDINATE_M, 1e9): beyond the Moon's orbit, so any
# map on or around the Earth (ECEF ~6.4e6 m) fits; beyond it, squared distances lose all
# precision and a finite 1e300 made the solver's affinity matrix inf (found by `bench fuzz`)
MAX_SEQ = 2**63 - 1  # seq, keyframe and about_seq: the wire's int64 (docs/wire.md §2)

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

# JSON Schema only (validation is the models' own): what the schemas say beyond the types
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_ID = "urn:mergesvc:schemas:v{version}:{name}"  # $id of schemas/<name>
_VERSION_SCHEMA: dict[str, Any] = {"const": SCHEMA_VERSION}
_ROW6 = {"type": "array", "items": {"type": "number"}, "minItems": 6, "maxItems": 6}
_COV6_SCHEMA: dict[str, Any] = {"items": _ROW6, "minItems": 6, "maxItems": 6}


def _in_array_branch(extra: dict[str, Any]) -> Any:
    """json_schema_extra of an optional array field: `extra` goes into the array branch of
    its anyOf, so strict validators (ajv) see array keywords only where the type is array."""

    def update(schema: dict[str, Any]) -> None:
        for branch in schema.get("anyOf", [schema]):
            if branch.get("type") == "array":
                branch.update(extra)

    return update


_NONZERO3_SCHEMA = _in_array_branch({"not": {"const": [0, 0, 0]}})

Identifier = Annotated[str, Field(min_length=1, max_length=MAX_ID_LENGTH)]
# numbers of an object are numbers: "0.1" and true are refused, as the schemas refuse them
Number = Annotated[float, Strict()]
Coordinate = Annotated[float, Strict(), Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]


def _check_version(v: Any) -> int:
    if v != SCHEMA_VERSION:
        raise ValueError(f"unsupported schema_version {v!r}: this build reads {SCHEMA_VERSION}")
    return v


class ObjectNode(BaseModel):
    """One object of a map: position, embedding mean and its diagonal variance.

    `variance` is either one number (isotropic: the same variance in every dimension) or one
    positive number per embedding dimension. The scalar uncertainty s of the weighted cosine is
    the mean of the per-dimension variances (for an isotropic variance, the number itself), so a
    single observation with image uncertainty s and Sigma = s I has uncertainty s, and n fused
    observations of it have s / n.
    """

    model_config = _STRICT

    id: Identifier
    position: tuple[Coordinate, Coordinate, Coordinate] = Field(
        description="object centre [x, y, z] in metres")
    embedding: list[Number] = Field(min_length=1, max_length=MAX_EMBEDDING_DIM)
    variance: Annotated[Number, Field(gt=0)] | list[Annotated[Number, Field(gt=0)]] = Field(
        description="per-dimension variance of the embedding, or one number if isotropic"
    )
    n_obs: int = Field(default=1, ge=1, description="observations fused into this object")
    label: str | None = Field(default=None, max_length=128, description="optional class name")

    @model_validator(mode="after")
    def _variance_matches_embedding(self) -> ObjectNode:
        if isinstance(self.variance, list) and len(self.variance) != len(self.embedding):
            raise ValueError(
                f"variance has {len(self.variance)} values but embedding has "
                f"{len(self.embedding)} (give one per dimension, or a single number)"
            )
        return self


class ObjectMap(BaseModel):
    """A robot's object map (or the global map): the file `mergesvc match --map` reads."""

    model_config = _STRICT

    schema_version: int = Field(
        default=SCHEMA_VERSION, description="must be 1", json_schema_extra=_VERSION_SCHEMA
    )
    robot_id: Identifier
    session_id: Identifier
    objects: list[ObjectNode] = Field(min_length=1, max_length=MAX_OBJECTS)
    up: tuple[float, float, float] | None = Field(
        default=None,
        description="optional: the direction opposite to gravity in this file's frame, e.g. "
        "[0, 0, 1] for ENU, [0, 0, -1] for NED, [0, -1, 0] for a camera frame (y down); any "
        "non-zero length. Without it the vertical is inferred from the object layout where "
        "that is reliable, and nothing is assumed otherwise",
        json_schema_extra=_NONZERO3_SCHEMA,
    )
    _arrays: ObjectArrays | None = PrivateAttr(default=None)

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)

    @field_validator("up", mode="before")
    @classmethod
    def _up_numbers(cls, v: Any) -> Any:
        if isinstance(v, (list, tuple)) and any(
            isinstance(x, bool) or not isinstance(x, (int, float)) for x in v
        ):
            raise ValueError("up must be three numbers")
        return v

    @field_validator("up")
    @classmethod
    def _up_nonzero(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None and not max(abs(x) for x in v) > 0.0:
            raise ValueError("up must be a non-zero vector")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> ObjectMap:
        d = len(self.objects[0].embedding)
        seen: set[str] = set()
        for k, obj in enumerate(self.objects):
            if len(obj.embedding) != d:
                raise ValueError(
                    f"embeddings differ in length: objects.0 ({self.objects[0].id}) has {d} "
                    f"values, objects.{k} ({obj.id}) has {len(obj.embedding)}"
                )
            if obj.id in seen:
                raise ValueError(f"objects.{k}: duplicate id {obj.id!r}")
            seen.add(obj.id)
        return self

    @property
    def dim(self) -> int:
        return len(self.objects[0].embedding)

    def arrays(self) -> ObjectArrays:
        """The objects as arrays; computed once (the model is frozen), then shared."""
        if self._arrays is None:
            self._arrays = ObjectArrays.from_objects(self.objects, up=self.up)
        return self._arrays

    def model_copy(self, *, update: Mapping[str, Any] | None = None,
                   deep: bool = False) -> Self:
        """A copy; one with changed fields computes its arrays anew (pydantic would carry the
        original's cached arrays over)."""
        out = super().model_copy(update=update, deep=deep)
        if update:
            out._arrays = None
        return out


class Transform(BaseModel):
    """Rigid transform T_map_submap: p_map = R p_submap + t."""

    model_config = _STRICT

    translation: tuple[float, float, float]
    quaternion_wxyz: tuple[float, float, float, float]


def _check_unit_quaternion(v: Transform) -> Transform:
    norm = sum(x * x for x in v.quaternion_wxyz) ** 0.5  # no overflow warning: inf
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"quaternion_wxyz must have unit norm, got {norm:.6g}")
    return v


def _check_spd(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 6 or any(len(r) != 6 for r in v):
        raise ValueError("covariance must be 6x6")
    C = np.array(v, dtype=np.float64)
    with np.errstate(all="ignore"):  # huge entries: judged by the result, not warnings
        if not np.abs(C - C.T).max() <= 1e-9 * np.abs(C).max():
            raise ValueError("covariance must be symmetric")
        try:
            L = np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            L = None
    if L is None or not np.all(np.isfinite(L)):
        raise ValueError("covariance must be positive definite")
    return v


# A rigid transform whose quaternion has unit norm; a 6x6 SPD covariance (GTSAM Pose3 order).
Pose = Annotated[Transform, AfterValidator(_check_unit_quaternion)]
Covariance6 = Annotated[list[list[float]], AfterValidator(_check_spd)]


class Odometry(BaseModel):
    """The vehicle's own estimate of how far it moved between two of its keyframes:
    T_from_to, the pose of keyframe `to` (the submap's) in keyframe `from_keyframe`,
    p_from = R p_to + t, with its 6x6 covariance in GTSAM order (rotation, translation)."""

    model_config = _STRICT

    from_keyframe: int = Field(ge=0, le=MAX_SEQ,
                               description="the earlier keyframe (the previous submap's)")
    T_from_to: Pose = Field(description="pose of the submap's keyframe in from_keyframe")
    covariance: Covariance6 = Field(
        description="6x6 SPD covariance of T_from_to, GTSAM Pose3 order (rotation, translation)",
        json_schema_extra=_COV6_SCHEMA,
    )


# what a submap has and a map does not: a file with any of these keys is a submap
SUBMAP_FIELDS = ("seq", "stamp", "keyframe", "odometry")


class Submap(ObjectMap):
    """A window of a robot's recent objects, matched against a map.

    Anchored to a pose when `keyframe` is set: the submap was cut at the vehicle's keyframe
    `keyframe` (an index in its session, increasing), object positions are in that keyframe's
    body frame, and `odometry` (absent for a session's first keyframe) is the vehicle's motion
    since an earlier keyframe, so the service holds every robot's odometry chain. Without
    `keyframe`, positions are in the session's own frame (the session origin)."""

    seq: int | None = Field(default=None, ge=0, le=MAX_SEQ,
                            description="submap sequence number")
    stamp: float | None = Field(default=None, description="time of the submap cut, seconds")
    keyframe: int | None = Field(
        default=None, ge=0, le=MAX_SEQ,
        description="keyframe (pose index in the session) the submap is anchored at; object "
        "positions are then in that keyframe's body frame",
    )
    odometry: Odometry | None = Field(
        default=None, description="motion since an earlier keyframe (needs `keyframe`)"
    )

    @model_validator(mode="after")
    def _odometry_needs_keyframe(self) -> Submap:
        if self.odometry is not None:
            if self.keyframe is None:
                raise ValueError("odometry needs keyframe")
            if self.odometry.from_keyframe >= self.keyframe:
                raise ValueError(
                    f"odometry.from_keyframe {self.odometry.from_keyframe} must be before "
                    f"keyframe {self.keyframe}"
                )
        return self


class RejectReason(str, Enum):
    """Why a match was (not) accepted; `verified` means accepted."""

    VERIFIED = "verified"
    NOT_VERIFIED = "not_verified"  # paper mode: no verification is done
    TOO_FEW_MATCHES = "too_few_matches"
    AMBIGUOUS = "ambiguous"  # another configuration explains the submap almost as well
    TILTED = "tilted"  # the transform turns "up" over: a mirror image of the true match
    DEGENERATE_GEOMETRY = "degenerate_geometry"
    RESIDUAL_TOO_LARGE = "residual_too_large"
    SEARCH_INCOMPLETE = "search_incomplete"
    NO_CANDIDATES = "no_candidates"


class Match(BaseModel):
    model_config = _STRICT

    submap_object: str
    map_object: str
    score: float


class MatchResult(BaseModel):
    """Result of matching a submap against a map; `mergesvc match --json` prints it."""

    model_config = _STRICT

    schema_version: int = Field(default=SCHEMA_VERSION, json_schema_extra=_VERSION_SCHEMA)
    accepted: bool
    reason: RejectReason
    matches: list[Match]
    transform: Transform | None
    covariance: list[list[float]] | None = Field(
        description="6x6 covariance of the transform, GTSAM order (rotation, translation)",
        json_schema_extra=_in_array_branch(_COV6_SCHEMA),
    )
    timings_ms: dict[str, float]

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)

    @field_validator("covariance")
    @classmethod
    def _six_by_six(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None and (len(v) != 6 or any(len(r) != 6 for r in v)):
            raise ValueError("covariance must be 6x6")
        return v

    def cli_dict(self) -> dict[str, Any]:
        """The exact JSON object `mergesvc match --json` prints (no schema_version)."""
        return self.model_dump(mode="json", exclude={"schema_version"})


def arrays_to_nodes(arr: ObjectArrays, isotropic_tol: float = 0.0) -> list[ObjectNode]:
    """Arrays back to file objects; a variance row that is constant becomes one number."""
    nodes = []
    for k, oid in enumerate(arr.ids):
        v = arr.variances_nd[k]
        var: float | list[float] = (
            float(v[0]) if np.ptp(v) <= isotropic_tol * v[0] else v.tolist()
        )
        nodes.append(
            ObjectNode(
                id=oid,
                position=tuple(float(x) for x in arr.position_xyz_m[k]),
                embedding=arr.embeddings_nd[k].astype(np.float64).tolist(),
                variance=var,
                n_obs=int(arr.n_obs[k]),
            )
        )
    return nodes


# the member tags pydantic adds to a location inside a union (`constrained-float`,
# `list[constrained-float]`, `function-after[...]`), not fields of a file
_UNION_TAG = re.compile(r"[a-z]+(-[a-z]+)+(\[.*\])?|[a-z]+\[.*\]")


def _field_path(error: dict[str, Any]) -> str:
    """pydantic's error location as the file's field path: a union's member tags left out
    (a field a file should not have is named as written, whatever its characters)."""
    loc = error["loc"]
    if error["type"] != "extra_forbidden":
        loc = [x for x in loc if not (isinstance(x, str) and _UNION_TAG.fullmatch(x))]
    return ".".join(str(x) for x in loc)


def _format_validation_error(exc: ValidationError, what: str) -> str:
    """One line naming the first offending field, e.g. `objects.3.variance.7: ...`; the other
    fields at fault counted (a union's members refusing one value count once)."""
    errors = exc.errors()
    loc = _field_path(errors[0])
    msg = errors[0]["msg"].removeprefix("Value error, ")
    ctx = errors[0].get("ctx") or {}
    if errors[0]["type"] == "too_short" and "actual_length" in ctx:
        msg = f"needs at least {ctx['min_length']}, has {ctx['actual_length']}"
    others = len({_field_path(e) for e in errors} - {loc})
    more = f" (and {others} more field{'s' if others > 1 else ''})" if others else ""
    return f"invalid {what}: {loc + ': ' if loc else ''}{msg}{more}"


# pydantic's JSON parser turns an integer literal of 2^128 or more into a float that may be a
# unit in the last place off Python's (correctly rounded) reading of it
_EXACT_BELOW = 2.0**128


def read_exactly(m: ObjectMap) -> bool:
    """Whether every float of `m` that a file may give as an integer literal is below 2^128 in
    magnitude (positions and embeddings are bounded below it): then pydantic's JSON parser
    read the same numbers as the json module."""
    try:
        variance = m.arrays().variance_column
    except (OverflowError, ValueError, MergeError):  # the json module's path then says why
        return False
    if float(np.abs(variance).max(initial=0.0)) >= _EXACT_BELOW:
        return False
    if isinstance(m, Submap):
        small = [m.stamp or 0.0]
        if m.odometry is not None:
            small += [*m.odometry.T_from_to.translation, *np.ravel(m.odometry.covariance)]
        return bool(np.all(np.abs(small) < _EXACT_BELOW))
    return True


def read_valid_json(model: type[ObjectMap], data: str | bytes) -> ObjectMap | None:
    """A valid file read by pydantic's own JSON parser (faster than the json module and
    validation: docs/benchmarks/scale.md); None when it refuses the file or holds a number it
    may have read less exactly (`read_exactly`): the json module's reading then decides."""
    try:
        got = model.model_validate_json(data)
    except ValueError:  # pydantic's ValidationError among them
        return None
    return got if read_exactly(got) else None


def parse_model(model: type[ObjectMap], data: str | bytes, what: str = "file") -> ObjectMap:
    """Validate JSON text into `model`; raise DecodeError / SchemaError with one clear line.

    `read_valid_json` first; what it does not read is read again by the json module and
    validated, whose errors say what is wrong in the words every reader of these files gets
    (and which also reads UTF-16 and -32)."""
    fast = read_valid_json(model, data)
    if fast is not None:
        return fast
    try:
        raw = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DecodeError(f"{what} is not valid JSON ({exc}): give a map or submap file, "
                          f"JSON or a binary .npz (`mergesvc convert`)") from exc
    if not isinstance(raw, dict):
        raise SchemaError(f"invalid {what}: expected a JSON object, got {type(raw).__name__}")
    if "objects" not in raw:  # another kind of file (a truth file, a factor, settings)
        kind = "submap" if model is Submap else "map"
        fields = ", ".join(repr(k)[:40] for k in list(raw)[:5]) or "none"
        raise SchemaError(f"invalid {what}: not a {kind} file (it has no `objects`; its "
                          f"fields: {fields}); `mergesvc example DIR` writes one to compare")
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise SchemaError(_format_validation_error(exc, what)) from exc


def json_schemas() -> dict[str, dict[str, Any]]:
    """JSON Schema (2020-12) of every file model, keyed by file name under schemas/.

    They refuse what the models refuse where JSON Schema can say it (types, ranges, lengths,
    `schema_version` 1, a 6x6 covariance, a non-zero `up`, keyframe_a with keyframe_b,
    odometry with keyframe). What it cannot say, the models still check: every object's
    embedding of one length and a per-dimension variance of that length, unique object ids,
    a unit quaternion, a symmetric positive definite covariance, odometry.from_keyframe
    before keyframe, truth matches naming objects of the files.
    """
    schemas = {
        "object_map.schema.json": ObjectMap.model_json_schema(),
        "submap.schema.json": Submap.model_json_schema(),
        "match_result.schema.json": MatchResult.model_json_schema(),
        "factor.schema.json": Factor.model_json_schema(),
        "error_message.schema.json": ErrorMessage.model_json_schema(),
        "truth.schema.json": _truth_schema(),
    }
    schemas["submap.schema.json"]["allOf"] = [_needs("odometry", "keyframe")]
    schemas["factor.schema.json"]["allOf"] = [
        _needs("keyframe_a", "keyframe_b"), _needs("keyframe_b", "keyframe_a")
    ]
    return {
        name: {"$schema": SCHEMA_DIALECT,
               "$id": SCHEMA_ID.format(version=SCHEMA_VERSION, name=name), **schema}
        for name, schema in schemas.items()
    }


def _needs(field: str, other: str) -> dict[str, Any]:
    """JSON Schema: when `field` is given (not null), `other` must be given (not null)."""
    return {
        "if": {"required": [field], "properties": {field: {"not": {"type": "null"}}}},
        "then": {"required": [other], "properties": {other: {"not": {"type": "null"}}}},
    }


def _truth_schema() -> dict[str, Any]:
    """The ground truth `mergesvc example` and `mergesvc scenario` write beside a submap
    (truth.json, NAME.truth.json; mergesvc.sim.Scenario.truth_dict)."""
    ident = {"type": "string", "minLength": 1, "maxLength": MAX_ID_LENGTH}
    number = {"type": "number"}
    return {
        "title": "Truth",
        "description": "Ground truth of a generated submap against its map.",
        "type": "object",
        "additionalProperties": False,
        "required": ["matches", "equivalent", "transform"],
        "properties": {
            "matches": {
                "description": "submap object id -> the map object it is, or null (an object "
                "the map does not have: a false detection or one outside the map)",
                "type": "object",
                "propertyNames": ident,
                "additionalProperties": {"anyOf": [ident, {"type": "null"}]},
            },
            "equivalent": {
                "description": "submap object id -> every map object that is an equally right "
                "answer (look-alikes at one place); only ids with more than one",
                "type": "object",
                "propertyNames": ident,
                "additionalProperties": {
                    "type": "array", "items": ident, "minItems": 2, "uniqueItems": True
                },
            },
            "transform": {
                "description": "T_map_submap: p_map = R p_submap + t",
                "type": "object",
                "additionalProperties": False,
                "required": ["translation", "quaternion_wxyz"],
                "properties": {
                    "translation": {"type": "array", "prefixItems": [number] * 3,
                                    "items": False, "minItems": 3, "maxItems": 3},
                    "quaternion_wxyz": {"type": "array", "prefixItems": [number] * 4,
                                        "items": False, "minItems": 4, "maxItems": 4},
                },
            },
        },
    }


__all__ = [
    "SCHEMA_VERSION",
    "SUBMAP_FIELDS",
    "Correspondence",
    "Covariance6",
    "ErrorMessage",
    "Factor",
    "FactorStatus",
    "Match",
    "MatchResult",
    "ObjectArrays",
    "ObjectMap",
    "ObjectNode",
    "Odometry",
    "Pose",
    "RejectReason",
    "Submap",
    "Transform",
    "arrays_to_nodes",
    "json_schemas",
    "parse_model",
    "read_exactly",
    "read_valid_json",
]


# ------------------------------------------------------------------ inter-robot messages

MAX_CORRESPONDENCES = 10_000


class FactorStatus(str, Enum):
    """Lifecycle of an inter-robot factor: add it, or take back one sent earlier."""

    ACCEPTED = "accepted"
    RETRACTED = "retracted"


class Correspondence(BaseModel):
    """One object pair behind a factor: object `object_a` of robot a is `object_b` of robot b."""

    model_config = _STRICT

    object_a: Identifier
    object_b: Identifier
    score: float


class Factor(BaseModel):
    """Inter-robot factor: relative pose T_a_b between the frames of (robot_a, session_a) and
    (robot_b, session_b), p_a = R p_b + t, as a GTSAM BetweenFactorPose3 would hold it. With
    `keyframe_a`/`keyframe_b` it ties two keyframe poses (a pose-level loop closure); without,
    the two sessions' frames.

    `covariance` is 6x6, symmetric positive definite, in the Pose3 tangent space of T_a_b,
    GTSAM order: rotation (rad) then translation (m).
    """

    model_config = _STRICT

    schema_version: int = Field(
        default=SCHEMA_VERSION, description="must be 1", json_schema_extra=_VERSION_SCHEMA
    )
    factor_id: Identifier
    robot_a: Identifier
    session_a: Identifier
    robot_b: Identifier
    session_b: Identifier
    T_a_b: Pose = Field(description="pose of frame b in frame a: p_a = R p_b + t")
    covariance: Covariance6 = Field(
        description="6x6 SPD covariance of T_a_b, GTSAM Pose3 order (rotation, translation)",
        json_schema_extra=_COV6_SCHEMA,
    )
    correspondences: list[Correspondence] = Field(
        default_factory=list, max_length=MAX_CORRESPONDENCES
    )
    status: FactorStatus | None = Field(default=None, description="accepted or retracted")
    keyframe_a: int | None = Field(
        default=None, ge=0, le=MAX_SEQ,
        description="pose-level factor: T_a_b is between keyframe keyframe_a of session a and "
        "keyframe_b of session b (both set, or neither: then between the session frames)",
    )
    keyframe_b: int | None = Field(default=None, ge=0, le=MAX_SEQ,
                                    description="see keyframe_a")

    @model_validator(mode="after")
    def _keyframes_together(self) -> Factor:
        if (self.keyframe_a is None) != (self.keyframe_b is None):
            raise ValueError("keyframe_a and keyframe_b go together")
        return self

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)


class ErrorMessage(BaseModel):
    """An error reply on the wire, e.g. the service could not decode submap `about_seq`."""

    model_config = _STRICT

    schema_version: int = Field(
        default=SCHEMA_VERSION, description="must be 1", json_schema_extra=_VERSION_SCHEMA
    )
    code: str = Field(min_length=1, max_length=64, description="short machine-readable code")
    detail: str = Field(default="", max_length=1024, description="one line for people")
    about_seq: int | None = Field(default=None, ge=0, le=MAX_SEQ,
                                   description="seq of the message at fault")

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)
