"""Known errors at the command line, mapped to exit codes in one place.

Every command runs the code that can fail inside `exit_on_error()`: a `MergeError` becomes one
line `error: ...` on stderr and exit code 2 when it is bad input (`InputError` and its
subclasses), 1 otherwise. A command that reads user-typed values through constructors that
raise `ValueError`/`OSError` (a file path, a name) lists those types too: they are bad input,
exit 2. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

import typer

from mergesvc.errors import InputError, MergeError, one_line

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1


def fail(exc: BaseException, code: int) -> NoReturn:
    """One line on stderr (the message's first line, or the error's type) and exit `code`."""
    msg = one_line(exc)
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code) from exc


def exit_code(exc: MergeError) -> int:
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
