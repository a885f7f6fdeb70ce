"""The matching method, as pure computation: models, tracking, geometry and affinities,
candidates, solvers, verification, the pipeline that chains them, the pose graph and fusion.

May import: mergesvc.errors and core's own modules (numpy, scipy, pygmtools, gtsam, pydantic).
No zenoh, no sockets, no processes; modules import each other's leaves, never this package.
"""
