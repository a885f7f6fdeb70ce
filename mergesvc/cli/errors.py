"""Known errors at the command line, mapped to exit codes in one place.

    code  meaning
    0     done
    1     failed: a MergeError that is neither of the two below (a settings or Zenoh config
          file that cannot be used, the store, a solver, a benchmark's or the demo's checks)
    2     bad input: InputError (a file, a flag value, an endpoint), and typer's usage errors
    3     network: TransportError (a --listen port in use or not on this machine, nothing
          answering at --connect within --connect-timeout)

Every command runs the code that can fail inside `exit_on_error()`: a known error becomes one
line `error: ...` on stderr (a TransportError's also says what to do) and its exit code; so do
the `ValueError`/`OSError` of constructors a command lists for user-typed values (bad input,
exit 2). With `-vv` the traceback is printed above the line; anything else is a bug and keeps it.
"""

from __future__ import annotations

import sys
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

import typer

from mergesvc.errors import InputError, MergeError, TransportError, TransportFault, one_line

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_NETWORK = 3

# what to do about a session that could not open, by its fault
TRANSPORT_ADVICE = {
    TransportFault.IN_USE: "pick another --listen, or stop the process that holds it",
    TransportFault.CANNOT_LISTEN: "--listen needs an address of this machine (and TLS "
                                  "endpoints their files in --config)",
    TransportFault.NO_ANSWER: "start the service or router there, or fix --connect (wrong "
                              "credentials in --config look the same)",
    TransportFault.OTHER: "check --listen, --connect and --config",
}

_traceback = {"on": False}


def show_tracebacks(on: bool) -> None:
    """Print each known error's traceback above its line (`-vv`)."""
    _traceback["on"] = on


def message(exc: BaseException) -> str:
    """The error's line: its text, and for a TransportError what to do about it; an OSError
    about a file names it ("cannot use PATH: File exists")."""
    msg = one_line(exc)
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        two = f" -> {exc.filename2}" if exc.filename2 is not None else ""
        msg = f"cannot use {exc.filename}{two}: {exc.strerror}"
        if isinstance(exc, FileExistsError):
            msg += " (a file, where a folder is wanted: give a folder's path)"
    if isinstance(exc, TransportError):
        msg = f"{msg}: {TRANSPORT_ADVICE[exc.fault]}"
    return msg


def fail(exc: BaseException, code: int) -> NoReturn:
    """One line on stderr (`message`) and exit `code`; with -vv the traceback first."""
    if _traceback["on"]:
        traceback.print_exception(exc, file=sys.stderr)
    typer.echo(f"error: {message(exc)}", err=True)
    raise typer.Exit(code) from exc


def exit_code(exc: MergeError) -> int:
    if isinstance(exc, TransportError):
        return EXIT_NETWORK
    return EXIT_BAD_INPUT if isinstance(exc, InputError) else EXIT_FAILED


@contextmanager
def exit_on_error(*bad_input: type[Exception]) -> Iterator[None]:
    """Map known errors raised in the block to an exit: `MergeError` by `exit_code`, any of
    `bad_input` (e.g. `ValueError`, `OSError`) to 2."""
    try:
        yield
    except MergeError as exc:
        fail(exc, exit_code(exc))
    except bad_input as exc:
        fail(exc, EXIT_BAD_INPUT)
