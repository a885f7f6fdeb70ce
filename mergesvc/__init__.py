"""mergesvc: multi-robot object-map merging by semantic, uncertainty-aware graph matching.

The package is layered along the data flow; each layer imports only the ones below it
(tests/test_layout.py enforces this; docs/architecture.md describes each layer):

    errors < core (the method: pure computation, no zenoh, no sockets, no files) < wire, sim
    < link < fleet, bench < settings < ros2, view < cli (nothing imports it)

The names below are the public API for Python users: `mergesvc.match(map, submap)`, the file
and message models, and the codec's entry points.
"""

import importlib
import logging
import os
import typing

# A multi-threaded OpenBLAS call leaves its worker threads spinning for 2^28 cycles afterwards,
# on a core that the next small match (pinned to one thread: core/threads.py) or another
# robot's work wants; 2^20 cycles keeps them awake between back-to-back products only. Read
# when OpenBLAS loads: it holds when mergesvc is imported before numpy; a value set is kept.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "20")

# name -> the module that defines it. Imported on first use (PEP 562), so `import mergesvc`
# (and `mergesvc --help`) does not load numpy, scipy, gtsam and pydantic up front.
_WHERE = {
    **dict.fromkeys(("MatchConfig", "MatchMode", "NodeAffinity", "SolverName"),
                    "mergesvc.core.config"),
    **dict.fromkeys(("Correspondence", "ErrorMessage", "Factor", "FactorStatus", "Match",
                     "MatchResult", "ObjectArrays", "ObjectMap", "ObjectNode", "RejectReason",
                     "Submap", "Transform"), "mergesvc.core.model"),
    **dict.fromkeys(("MatchOutcome", "match"), "mergesvc.core.pipeline"),
    **dict.fromkeys(("CodecError", "ConfigError", "DecodeError", "InputError", "MergeError",
                     "SchemaError", "SolverError"), "mergesvc.errors"),
    **dict.fromkeys(("CODEC_VERSION", "CodecLimits", "CodecSettings", "MessageType", "Profile",
                     "Projection", "decode_file", "decode_message", "encode_file",
                     "encode_message", "load_model"), "mergesvc.wire"),
}


def __getattr__(name: str) -> typing.Any:
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module 'mergesvc' has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__version__ = "0.1.0"

# A library does not configure logging: its records go nowhere until the application (the CLI
# here, or a user's program) adds a handler.
logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "CODEC_VERSION",
    "CodecError",
    "CodecLimits",
    "CodecSettings",
    "ConfigError",
    "Correspondence",
    "DecodeError",
    "ErrorMessage",
    "Factor",
    "FactorStatus",
    "InputError",
    "Match",
    "MatchConfig",
    "MatchMode",
    "MatchOutcome",
    "MatchResult",
    "MergeError",
    "MessageType",
    "NodeAffinity",
    "ObjectArrays",
    "ObjectMap",
    "ObjectNode",
    "Profile",
    "Projection",
    "RejectReason",
    "SchemaError",
    "SolverError",
    "SolverName",
    "Submap",
    "Transform",
    "__version__",
    "decode_file",
    "decode_message",
    "encode_file",
    "encode_message",
    "load_model",
    "match",
]
