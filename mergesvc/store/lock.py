"""One service per store file: an advisory lock (flock) on `<store>.lock`, held while a
service runs, the file holding its pid and removed when it lets go. SQLite itself would let two
services write one store, each then taking the other's pending submaps; the second is refused
instead. The kernel drops the lock when the holder exits, however it exits (SIGKILL too: the
file is left, and the next holder takes it over); child processes do not inherit it. A memory
store needs none.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from mergesvc.errors import StoreError
from mergesvc.store.database import is_memory


@contextlib.contextmanager
def held_store(path: Path | str) -> Iterator[None]:
    """Hold `path`'s lock for the block; StoreError (one line, what to do) when another process
    holds it or the folder cannot take the store."""
    path = str(path)
    if is_memory(path):
        yield
        return
    folder = Path(path).resolve().parent
    if Path(path).is_dir():
        raise StoreError(f"store {path} is a folder: give a file path for the store")
    lock = path + ".lock"
    try:
        fd = _locked(lock, path)
    except FileNotFoundError as exc:
        raise StoreError(f"no folder {folder} for store {path}: create it or pick another "
                         "--store") from exc
    except OSError as exc:
        what = "is read-only" if exc.errno == errno.EROFS else "cannot be written"
        raise StoreError(f"folder {folder} {what} ({exc.strerror}): the store {path} needs "
                         "it; pick another --store") from exc
    try:
        with contextlib.suppress(OSError):  # the pid is for the message only (a full disk)
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # before the lock goes: whoever opens it next makes a new one
        os.close(fd)  # the lock goes with the descriptor


def _locked(lock: str, path: str) -> int:
    """A descriptor of `lock` holding its flock, the file still at that path (one removed
    by its last holder between our open and our flock is not the lock: open again)."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise StoreError(f"store {path} is in use by another service (pid {holder}): stop "
                             "it or pick another --store") from None
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


__all__ = ["held_store"]
