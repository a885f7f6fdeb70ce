"""Exception tree of mergesvc: one root, one subclass per boundary.

    MergeError
     ├── InputError        bad user input (files, CLI arguments, models)
     │    ├── DecodeError  bytes or text that cannot be parsed
     │    └── SchemaError  parsed, but violates the schema (fields, sizes, NaN, version)
     ├── SolverError       a solver failed or was asked something it cannot do
     ├── ConfigError       invalid configuration
     ├── CodecError        a model cannot be encoded (value outside what a profile can carry)
     ├── LinkError         the (simulated) link failed: a message was lost after all retries
     ├── TransportError    the network refused: a port in use, an endpoint that does not answer
     └── StoreError        persistence failed (database unreadable, disk full)
"No match" and "rejected" are results (`MatchResult.accepted=False`), never exceptions; error
text meant for one line (a log line, stderr) goes through `one_line` (its one copy)."""

from __future__ import annotations

from enum import Enum


def one_line(exc: BaseException | str) -> str:
    """An error's text on one line: the first line of its text once blank space around the
    whole text is removed. An exception without text gives its type's name ("KeyError"); an
    empty string gives ""."""
    text = str(exc).strip()
    if not text:
        return "" if isinstance(exc, str) else type(exc).__name__
    return text.splitlines()[0]


def cannot_read(path: object, exc: OSError, hint: str = "") -> str:
    """The line for a file that cannot be read; when it does not exist, "check the path" and
    the caller's hint (what writes such a file)."""
    more = f"; check the path{f' ({hint})' if hint else ''}" if isinstance(
        exc, FileNotFoundError) else ""
    return f"cannot read {path}: {exc.strerror or exc}{more}"


class MergeError(Exception):
    """Root of every error mergesvc raises on purpose."""


class InputError(MergeError):
    """Input from outside (file, message, argument) is unusable."""


class DecodeError(InputError):
    """Bytes or text that cannot be decoded (malformed JSON, msgpack, truncated data)."""


class SchemaError(InputError):
    """Decoded data that violates the schema (missing field, bad value, wrong version)."""


class SolverError(MergeError):
    """A solver failed or received a problem it cannot solve."""


class ConfigError(MergeError):
    """Invalid configuration."""


class CodecError(MergeError):
    """A model cannot be encoded with the chosen profile (decoding errors are DecodeError)."""


class LinkError(MergeError):
    """The link could not deliver a message (lost after every retry, or closed)."""


class TransportFault(str, Enum):
    """Why a network session could not be opened (`TransportError.fault`)."""

    IN_USE = "in_use"  # a listen endpoint's port is taken by another process
    CANNOT_LISTEN = "cannot_listen"  # a listen endpoint this machine cannot open (address, TLS)
    NO_ANSWER = "no_answer"  # no connect endpoint answered within the connect timeout
    OTHER = "other"


class TransportError(MergeError):
    """A network session could not be opened; `endpoint` names the endpoint at fault (None
    when no single one is) and `fault` says what went wrong."""

    def __init__(self, message: str, *, fault: TransportFault = TransportFault.OTHER,
                 endpoint: str | None = None) -> None:
        super().__init__(message)
        self.fault = fault
        self.endpoint = endpoint


class StoreError(MergeError):
    """Persistence failed."""


__all__ = [
    "CodecError",
    "ConfigError",
    "DecodeError",
    "InputError",
    "LinkError",
    "MergeError",
    "SchemaError",
    "SolverError",
    "StoreError",
    "TransportError",
    "TransportFault",
    "cannot_read",
    "one_line",
]
