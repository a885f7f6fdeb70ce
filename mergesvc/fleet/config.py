"""Settings of the merge service (`mergesvc serve`, the `service` section of the settings tree)
and the names its noise groups go by. Pydantic models only: cheap to import.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, field_validator

from mergesvc.core.calibration import CalibrationConfig
from mergesvc.core.config import GraphConfig, MatchConfig
from mergesvc.wire.keys import check_name
from mergesvc.wire.names import Profile


class ConsistencyConfig(BaseModel):
    """Settings of the pairwise-consistency test of inter-robot factors (PCM)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="trust only the largest pairwise-consistent set "
                          "of the factors between two sessions")
    quantile: float = Field(0.999, gt=0.0, lt=1.0, description="chi-square quantile (6 dof) "
                            "below which two factors' loop error counts as consistent")
    inflation: float = Field(3.0, ge=1.0, description="the factors' covariances are multiplied "
                             "by this in the test (their correlated errors)")
    window: int = Field(64, ge=2, le=1024, description="latest factors of a pair weighed "
                        "again when one arrives")


# Keyframes the service's pose graph solves at most (GraphConfig.max_live_nodes, rule 6 of the
# pose graph, docs/pose_graph.md); older ones freeze. Measured: docs/benchmarks.
LIVE_KEYFRAMES = 1000
CLOSURE_GROUP = "closures"  # the noise group of every inter-robot factor (calibration)


def odometry_group(robot: str) -> str:
    """The noise group of a robot's odometry edges: every session of one robot together."""
    return f"odometry:{robot}"


def bound_group(robot: str) -> str:
    """The noise group of a robot's bound edges (its keyframes against its session's first):
    an odometry group of its own, calibrated apart from the steps."""
    return f"{odometry_group(robot)}:bound"


class ServiceConfig(BaseModel):
    """Settings of `mergesvc serve`."""

    model_config = ConfigDict(extra="forbid")

    fleet: str = Field("fleet0", min_length=1, max_length=64)
    store: str = Field("mergesvc.db", description="SQLite file (WAL); ':memory:' for tests")
    factor_profile: Profile = Field(
        Profile.COMPACT, description="codec profile of factors: compact (a bit stream, ~100 "
        "bytes) or full (the factor document as a msgpack map, with its correlations: for "
        "clients that do not decode the compact factor); f16 and int8 do not exist for factors",
    )
    max_payload_bytes: int = Field(4 * 2**20, ge=1024, description="larger submaps are refused")
    queue_size: int = Field(
        64, ge=1, description="pending submaps the worker takes from the store at once (one "
        "batch: the pose graph is solved once per batch)",
    )
    optimize_interval_s: float = Field(
        2.0, ge=0.0, description="during a backlog longer than one batch, the pose graph is "
        "solved at most this often (and always when the backlog is drained)",
    )
    solve_duty: float = Field(
        0.3, gt=0.0, le=1.0, description="the share of the worker's time pose-graph solves "
        "may take: after a solve of t seconds the next waits (1 / solve_duty - 1) t, so "
        "submaps arriving meanwhile are merged at once rather than behind the next solve",
    )
    status_refresh_s: float = Field(
        0.5, ge=0.0, description="a status query over the network answers with the store's "
        "counts and sizes as read by a thread of its own this often (the reply's store.age_s), "
        "so it does no I/O; a reply without poses is built whole by that thread after each "
        "read (all of it this old); 0: a query reads and builds itself",
    )
    solve_in_child: bool = Field(
        True, description="run the pose graph's optimisations in a child process (GTSAM "
        "holds the GIL through a solve: in-process, queries and ingress would wait on it)",
    )
    solve_timeout_s: float | None = Field(
        900.0, gt=0.0, description="a solve in the child process that has not answered after "
        "this long is stopped and fails (retried after the solve backoff, with twice the "
        "time; the status says so); None: no limit. In-process solves (solve_in_child "
        "false) cannot be stopped. A large submap's matching (fleet/lane.py) is stopped "
        "after as long, and fails",
    )
    embedding_dim: int | None = Field(
        None, ge=1, le=4096, description="the only embedding dimension this fleet takes "
        "(submaps of another are refused, error code embedding_dim); None: see embedding_dims",
    )
    embedding_dims: list[int] | None = Field(
        None, description="the embedding models (dimensions) this fleet takes; None: any "
        "(each model's maps are matched only with each other; no robot locks another's "
        "model out). embedding_dim, when set, is the only one")
    max_open_sessions_per_robot: int = Field(
        4, ge=1, description="sessions a robot may have open (a submap within session_idle_s); "
        "a submap of one more is refused (error code too_many_sessions)",
    )
    session_idle_s: float = Field(
        600.0, gt=0.0, description="a session without a submap for this long no longer counts "
        "as open",
    )
    submap_rate_hz: float = Field(
        5.0, gt=0.0, description="new submaps per second a robot may send on average (token "
        "bucket; replays of stored submaps are free); more are refused (error code "
        "rate_limited)",
    )
    submap_burst: int = Field(
        600, ge=1, description="new submaps a robot may send at once (the bucket's size: "
        "covers the backlog a vehicle's cache replays after a service restart)",
    )
    ingress_queue_size: int = Field(
        10_000, ge=1, description="received submaps waiting to be checked and persisted (the "
        "Zenoh callback only enqueues: an fsync in the callback made a fast publisher's "
        "samples drop); more are refused (error code busy)",
    )
    large_submap_objects: int = Field(
        200, ge=0, description="submaps of more objects are matched in a child process of "
        "low priority while the worker merges the others (fleet/lane.py), one at a time; the "
        "later submaps of their session wait for them. 0: every submap in the worker",
    )
    max_candidate_frames: int = Field(
        3, ge=1, description="other sessions each submap is matched against at most: those "
        "whose objects look most like the submap's (one index over the fleet's objects, "
        "core/retrieval.py), so the cost per submap does not grow with the fleet",
    )
    max_frames_per_robot: int = Field(
        2, ge=1, description="... of which at most this many sessions of one robot (a robot "
        "that opens many sessions cannot take every slot)",
    )
    min_map_objects: int = Field(3, ge=3, description="frames with fewer objects are not matched")
    loop_gap_submaps: int = Field(
        4, ge=0, description="each submap is also matched against its own session's objects "
        "last seen this many submaps or more before it: a place the vehicle came back to gives "
        "a loop closure within its session (its odometry's drift since); fewer submaps apart "
        "the objects are still its own tracked detections. 0: only other sessions")
    drift_sigma: tuple[float, float] = Field(
        (0.05, 0.5),
        description="added to every factor's covariance: rotation rad, translation m. A "
        "session's map places objects of many keyframes with estimated (drifting) poses, and "
        "a frame-level factor (old clients) ties two whole drifting frames, so a factor "
        "differs from the truth by more than the fit's own covariance says",
    )
    consistency: ConsistencyConfig = Field(
        ConsistencyConfig(), description="the pairwise-consistency test factors between two "
        "sessions pass before the graph trusts them (fleet/closures.py)")
    solve_inflation: float = Field(
        4.0, ge=1.0, description="every inter-robot factor's covariance is multiplied by this "
        "when solving (not in what is sent): successive factors share objects and errors, "
        "so the graph counts them as fewer (docs/uncertainty.md)")
    odometry_bounds: dict[str, tuple[float, float, float, float, float, float]] = Field(
        default_factory=dict, description="robot id -> the standard deviations (rad x3, m x3, "
        "GTSAM order) of its odometry's error at any keyframe relative to its session's first, "
        "for a vehicle whose odometry is a loop-closed estimate (its error does not grow with "
        "distance): each keyframe is also tied to the first by that covariance (shared over "
        "odometry_bound_span_m), so the solve cannot bend the trajectory much further than "
        "that (docs/pose_graph.md). Robots not listed: the odometry's error grows as its "
        "edges compose")
    odometry_bound_span_m: float = Field(
        0.0, ge=0.0, description="the distance over which a bounded odometry's errors stay "
        "alike (they are correlated along the path): the bound edges within it count as one, "
        "each edge's covariance the declared one times this distance over the odometry edge's "
        "length (at least once). 0: every keyframe's error counts as independent")
    local_fit: bool = Field(
        True, description="fit each factor on the matched objects with the other session's "
        "placed around its anchoring keyframe by odometry (not by the merged solution, whose "
        "errors would become the factor's), each pair weighed by its noise and its "
        "placement's, the placements' covariance carried into the factor's; false: the "
        "match's own transform, placed by the solution, drift_sigma added")
    local_drift_sigma: tuple[float, float] = Field(
        (0.0, 0.0), description="added to a locally fitted factor's covariance: rotation rad, "
        "translation m (its placement uncertainty is in it already)")
    local_range_weighted: bool = Field(
        True, description="in the local fit, an object's noise grows with its range from the "
        "keyframe that placed it (sonar, stereo): far objects weigh less")
    local_sigma_floor_m: float = Field(
        0.01, gt=0.0, description="the smallest object noise (m) a local fit's covariance "
        "assumes, when two or three matches leave no residual to estimate it")
    match: MatchConfig = Field(
        default_factory=lambda: MatchConfig.model_validate(
            {"verify": {"min_matches": 4, "min_matches_vertical": 4, "gravity_aligned": True,
                        "max_chance_log10": None}}
        ),
        description="verified matching; an inter-robot factor needs 4 matched objects by "
        "default, with or without a known vertical (3 points admit coincidental fits in a "
        "small pool, and a wrong factor costs more than a late one); chance's count "
        "(core/chance.py) off: the graph's consistency tests judge factors, and the count "
        "refused right ones of partly overlapping pool submaps",
    )
    relocalize_max_chance_log10: float | None = Field(
        2.0, description="verify.max_chance_log10 of a relocalization (a new session's "
        "submap against the global map; the rest as `match`): its answer reaches the vehicle "
        "with no graph to check it, so one that chance explains is refused. None: off"
    )
    graph: GraphConfig = Field(
        GraphConfig(max_live_nodes=LIVE_KEYFRAMES, calibration=CalibrationConfig(),
                    rigid_chains=odometry_group("")),
        description="the GNC pose graph over the sessions' keyframes (outlier thresholds; "
        f"max_live_nodes, {LIVE_KEYFRAMES} here: past that many keyframes the oldest freeze at "
        "their solved poses, core/graph.py rule 6, so a long mission's solve stays the same "
        "size; fold_hops > 0 folds a closure into one it agrees with nearby, rule 5: a smaller "
        "graph, off by default as it cost accuracy where the odometry drifts more than its "
        "covariance says, docs/benchmarks.md)",
    )

    @field_validator("odometry_bounds")
    @classmethod
    def _odometry_bounds(cls, v: dict[str, tuple[float, ...]]) -> dict[str, tuple[float, ...]]:
        for robot, sigmas in v.items():
            if not all(math.isfinite(x) and x > 0 for x in sigmas):
                raise ValueError(f"odometry_bounds[{robot!r}]: six finite standard deviations "
                                 f"above 0, got {list(sigmas)}")
        return v

    @field_validator("fleet")
    @classmethod
    def _fleet(cls, v: str) -> str:
        return check_name("fleet", v)

    @field_validator("factor_profile")
    @classmethod
    def _factor_profile(cls, v: Profile) -> Profile:
        if v not in (Profile.FULL, Profile.COMPACT):
            raise ValueError(f"factors are coded full or compact, not {v.value} (docs/wire.md "
                             "§2)")
        return v


__all__ = ["CLOSURE_GROUP", "LIVE_KEYFRAMES", "ConsistencyConfig", "ServiceConfig", "bound_group",
           "odometry_group"]
