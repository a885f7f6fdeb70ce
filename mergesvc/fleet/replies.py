"""What the merge service sends as JSON (docs/wire.md §11): the result of every submap (key
result/{robot}), the status and relocalize replies; query errors are core's ErrorMessage as
JSON. Pydantic models, and their JSON Schemas (2020-12) that `mergesvc schemas` writes.

One error shape: ErrorMessage {schema_version, code, detail, about_seq}. It is msgpack-coded
(type 4) on error/{robot}, JSON in a query's error reply, and a refused submap's result carries
the same `code` and `detail` (and `seq` = about_seq): the result is a superset of the error
message, which stays as it was for the vehicles that read it.
"""

from __future__ import annotations

from enum import Enum
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from mergesvc.core.model import (
    SCHEMA_DIALECT,
    SCHEMA_ID,
    SCHEMA_VERSION,
    RejectReason,
    Transform,
)

_REPLY = ConfigDict(extra="forbid", allow_inf_nan=False)
_VERSION = Field(default=SCHEMA_VERSION, description="must be 1",
                 json_schema_extra={"const": SCHEMA_VERSION})

Row4 = Annotated[list[float], Field(min_length=4, max_length=4)]
Matrix4 = Annotated[list[Row4], Field(min_length=4, max_length=4, description="4x4 pose")]
Row6 = Annotated[list[float], Field(min_length=6, max_length=6)]
Covariance6 = Annotated[list[Row6], Field(
    min_length=6, max_length=6,
    description="6x6 covariance, GTSAM Pose3 order (rotation rad, then translation m)")]


def _check_version(v: Any) -> int:
    if v != SCHEMA_VERSION or isinstance(v, bool):
        raise ValueError(f"schema_version must be {SCHEMA_VERSION}, got {v!r}")
    return int(v)


class Outcome(str, Enum):
    """What became of a submap."""

    PROCESSED = "processed"  # matched: one or more factors
    NO_MATCH = "no_match"  # stored and matched against the candidate frames: no factor
    REFUSED = "refused"  # refused at the boundary (not stored) or not storable
    FAILED = "failed"  # stored, but processing it failed (a bug, a solver): see the log


class RefusalCode(str, Enum):
    """Why a submap was refused (the code of its error message on error/{robot}), or
    `processing` for a stored submap whose processing failed."""

    BAD_SUBMAP = "bad_submap"  # not a decodable submap, or its key, robot, seq are wrong
    OVERSIZE = "oversize"  # larger than service.max_payload_bytes
    EMBEDDING_DIM = "embedding_dim"  # not the fleet's embedding dimension
    TOO_MANY_SESSIONS = "too_many_sessions"  # service.max_open_sessions_per_robot
    RATE_LIMITED = "rate_limited"  # service.submap_rate_hz / submap_burst
    BUSY = "busy"  # service.ingress_queue_size full: send again later
    STORE = "store"  # could not be persisted
    CONFLICT = "conflict"  # its (robot, session, seq) is stored with other bytes: final
    PROCESSING = "processing"  # outcome failed


#: No other session had a map to match the submap against.
NO_FRAMES = "no_frames"


class FrameTried(BaseModel):
    """One candidate frame a submap was matched against."""

    model_config = _REPLY

    frame: str = Field(min_length=1, description="the other session, robot/session")
    reason: RejectReason = Field(description="the match's verdict (`verified`: accepted)")
    matches: int = Field(ge=0, description="objects matched (verified: the fit's inliers)")
    factor_id: str | None = Field(None, description="the factor it became, if any")


class SubmapResult(BaseModel):
    """What became of one submap: sent once per submap on result/{robot} (JSON), after its
    factors were published. Duplicates of a stored submap get no second result."""

    model_config = _REPLY

    schema_version: int = _VERSION
    robot: str = Field(min_length=1, max_length=128)
    session: str | None = Field(None, max_length=128, description="null when the payload "
                                "could not be decoded")
    seq: int | None = Field(None, ge=0, description="the submap's seq (the error message's "
                            "about_seq); null when unknown")
    outcome: Outcome
    factors: list[str] = Field(default_factory=list, description="processed: the ids of its "
                               "factors (each sent on its factor key)")
    tried: list[FrameTried] = Field(default_factory=list, description="processed, no_match: "
                                    "every candidate frame, best ranked first")
    reason: RejectReason | Literal["no_frames"] | None = Field(
        None, description="no_match: the verdict of the best-ranked frame tried, or no_frames "
        "(no other session has a map yet)")
    code: RefusalCode | None = Field(None, description="refused, failed: why")
    detail: str = Field("", max_length=1024, description="refused, failed: one line for people")

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)


class RelocalizeReply(BaseModel):
    """Answer of the relocalize queryable: where the query submap's frame is in the anchor
    frame (the anchor session's keyframe 0).

    T_anchor_session: the pose of the frame the query submap's positions are in: its keyframe
    (`keyframe`, the vehicle's pose where it cut the submap) when the submap has one, else the
    new session's frame (its origin)."""

    model_config = _REPLY

    schema_version: int = _VERSION
    localized: bool
    reason: RejectReason | Literal["no_map"] = Field(
        description="verified when localized; no_map: the fleet has no map yet")
    anchor: str | None = None
    T_anchor_session: Transform | None = None
    covariance: Covariance6 | None = None
    matches: int = Field(0, ge=0)
    keyframe: int | None = Field(
        None, ge=0, description="the query submap's keyframe T_anchor_session is the pose of; "
        "None: the session frame"
    )

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)


class SubmapCounts(BaseModel):
    model_config = _REPLY

    received: int = Field(ge=0)
    duplicate: int = Field(ge=0)
    processed: int = Field(ge=0)
    rejected: int = Field(ge=0, description="refused at the boundary")
    queued: int = Field(ge=0, description="stored, not yet processed")
    stored: dict[str, int] = Field(description="stored submaps per store status")


class FactorCounts(BaseModel):
    model_config = _REPLY

    accepted: int = Field(ge=0)
    retracted: int = Field(ge=0)
    active: int = Field(ge=0)
    held: int = Field(0, ge=0, description="kept, not trusted (yet): not pairwise consistent "
                      "with the factors in force between the same two sessions")


class ModelCounts(BaseModel):
    """One embedding model's (dimension's) share of the fleet."""

    model_config = _REPLY

    sessions: int = Field(ge=0)
    objects: int = Field(ge=0)


class SolveState(BaseModel):
    """The pose graph's last solve."""

    model_config = _REPLY

    ok: bool = Field(description="false: the last solve failed and is being tried again")
    error: str | None = None
    failures: int = Field(0, ge=0, description="failed solves in a row")
    solution_age_s: float | None = Field(None, ge=0, description="since the last solution")


class ResultCounts(BaseModel):
    """The results sent since the start, by outcome and reason."""

    model_config = _REPLY

    processed: int = Field(0, ge=0)
    no_match: dict[str, int] = Field(default_factory=dict, description="per reason")
    refused: dict[str, int] = Field(default_factory=dict, description="per code")
    failed: int = Field(0, ge=0)


class Percentiles(BaseModel):
    """Percentiles of the last 1000 values; null before any."""

    model_config = _REPLY

    p50: float | None
    p90: float | None
    p99: float | None


class StoreStats(BaseModel):
    model_config = _REPLY

    path: str
    schema_version: int
    journal_mode: str
    synchronous: str
    rows: dict[str, int]
    file_bytes: int = Field(ge=0)
    wal_bytes: int = Field(ge=0)
    page_bytes: int = Field(ge=0)
    age_s: float = Field(0.0, ge=0, description="how old these figures and the submap "
                         "counts are (the service reads them every status_refresh_s)")


class NoiseScale(BaseModel):
    """One noise group as the calibration left it (GTSAM order: rotation x y z, translation
    x y z of the group's own frames)."""

    model_config = _REPLY

    sigma_scale: Row6 = Field(description="sigma as calibrated / sigma as declared")
    redundancy: Row6 | None = Field(
        None, description="how many observations' worth of residuals checked each axis at "
        "the last calibration (null: restored, not estimated since)")
    relative_se: list[float | None] | None = Field(
        None, min_length=6, max_length=6, description="each scale's relative standard error "
        "from the residuals alone, at most 1 / sqrt(2 redundancy) (docs/uncertainty.md; null: "
        "no residual checks the axis)")


class StatusReply(BaseModel):
    """Answer of the status queryable (strict JSON: no NaN)."""

    model_config = _REPLY

    schema_version: int = _VERSION
    fleet: str
    robots_alive: list[str]
    frames: dict[str, int] = Field(description="objects held per session robot/session")
    models: dict[str, ModelCounts] = Field(
        default_factory=dict, description="per embedding model (its dimension): sessions and "
        "objects; each model's maps are matched only with each other")
    submaps: SubmapCounts
    factors: FactorCounts
    results: ResultCounts
    errors: dict[str, int] = Field(description="errors per code: refusals and failures")
    latency_ms: Percentiles = Field(description="processing time per submap")
    delay_ms: Percentiles = Field(description="stored -> processed, per submap")
    optimizations: int = Field(ge=0)
    solve: SolveState | None = Field(None, description="the last solve: failed or not, and "
                                     "how old its solution is")
    frozen_keyframes: int = Field(0, ge=0, description="pose-graph keyframes held at the poses "
                                  "of an earlier solve (the oldest, past the graph's "
                                  "max_live_nodes)")
    embedding_dim: int | None
    anchor: str | None = Field(description="the anchor session, robot/session")
    frame_poses: dict[str, Matrix4] = Field(description="each session's keyframe 0 in the "
                                            "anchor frame")
    keyframe_poses: dict[str, dict[str, Matrix4]] = Field(
        description="robot/session -> keyframe -> its pose in the anchor frame")
    store: StoreStats
    store_damage: list[str] = Field(
        default_factory=list, description="answers sent that the store no longer holds, found "
        "at start (a truncated write-ahead log): one line per session")
    noise: dict[str, NoiseScale] = Field(
        default_factory=dict, description="each calibrated noise group (odometry:robot) as "
        "the service's calibration estimated it from the residuals")

    @field_validator("schema_version", mode="before")
    @classmethod
    def _version(cls, v: Any) -> int:
        return _check_version(v)


def status_line(status: dict[str, Any]) -> str:
    """A StatusReply (as `MergeService.status` returns it) as one progress line: submaps,
    factors, the robots alive and a failing pose graph, no poses."""
    sub, fac, res = status["submaps"], status["factors"], status["results"]
    refused, no_match = sum(res["refused"].values()), sum(res["no_match"].values())
    alive = ", ".join(status["robots_alive"]) or "none"
    line = (f"submaps {sub['received']} received, {res['processed']} merged, {no_match} "
            f"without a match, {refused} refused, {sub['queued']} queued; factors "
            f"{fac['active']} in force, {fac['retracted']} retracted; robots alive: {alive}")
    if not status["solve"]["ok"]:
        line += f"; pose graph failing: {status['solve']['error']}"
    return line


def reply_schemas() -> dict[str, dict[str, Any]]:
    """JSON Schema (2020-12) of what the service sends as JSON, keyed by file name under
    schemas/ (query errors: error_message.schema.json)."""
    schemas = {
        "submap_result.schema.json": SubmapResult.model_json_schema(),
        "status_reply.schema.json": StatusReply.model_json_schema(),
        "relocalize_reply.schema.json": RelocalizeReply.model_json_schema(),
    }
    return {
        name: {"$schema": SCHEMA_DIALECT,
               "$id": SCHEMA_ID.format(version=SCHEMA_VERSION, name=name), **schema}
        for name, schema in schemas.items()
    }


__all__ = [
    "NO_FRAMES",
    "FactorCounts",
    "FrameTried",
    "ModelCounts",
    "NoiseScale",
    "Outcome",
    "Percentiles",
    "RefusalCode",
    "RelocalizeReply",
    "ResultCounts",
    "SolveState",
    "StatusReply",
    "StoreStats",
    "SubmapCounts",
    "SubmapResult",
    "reply_schemas",
    "status_line",
]
