"""How many threads the BLAS may use for one match: one for small problems.

The matching stages multiply small matrices (a few hundred candidates): a multi-threaded BLAS
spends more time waking and joining its threads than computing, so default settings were
several times slower than one thread. `blas_threads` pins the BLAS (every loaded copy:
numpy's, scipy's) to one thread for problems below PIN_BELOW_PAIRS submap x map objects and
leaves it alone above, where a whole-map product does gain from threads.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any

from threadpoolctl import ThreadpoolController

# submap x map objects from which the BLAS keeps its own thread count (a 20-object submap
# against a million-object map: its exact cosine pass is one large product)
PIN_BELOW_PAIRS = 20_000_000

_controller: Any = None
_modules_seen = -1

# what a BLAS library's file name holds (threadpoolctl's prefixes: libopenblas,
# libscipy_openblas, libblas, libblis, libmkl_rt, mkl_rt, libflexiblas; and a LAPACK name,
# which a distribution may link to its BLAS: conda's liblapack.so.3 -> libopenblas)
_BLAS_NAMES = ("blas", "blis", "mkl", "lapack")


class _BlasController(ThreadpoolController):
    """threadpoolctl's controller over the BLAS libraries only. The library resolves the path
    of every loaded shared object before it reads its name (each extension module: more than a
    small match costs, in a fresh process; docs/benchmarks/scale.md); this one passes on the
    files whose name names a BLAS or LAPACK and leaves the rest of the work (the real name,
    symbols, controllers) to threadpoolctl."""

    def _make_controller_from_path(self, filepath: str, *args: Any, **kwargs: Any) -> None:
        name = os.path.basename(str(filepath)).lower()
        if any(k in name for k in _BLAS_NAMES):
            super()._make_controller_from_path(filepath, *args, **kwargs)


def _listing() -> Any:
    """The narrow listing; threadpoolctl's full one when it finds no BLAS or fails (a
    threadpoolctl whose hook changed): slower, as right."""
    try:
        narrow = _BlasController()
    except Exception:  # any failure of the override: the library's own listing
        return ThreadpoolController()
    if any(lib.user_api == "blas" for lib in narrow.lib_controllers):
        return narrow
    return ThreadpoolController()


def _threadpools() -> Any:
    """threadpoolctl's controller over the BLAS libraries loaded now: listing them costs
    milliseconds, switching their thread count microseconds, so the list is made again only
    when modules were imported since (one may have brought its own BLAS, as faiss does)."""
    global _controller, _modules_seen
    if _controller is None or len(sys.modules) != _modules_seen:
        _controller = _listing()
        _modules_seen = len(sys.modules)
    return _controller


def list_blas() -> None:
    """List the loaded BLAS libraries now, once the modules a run needs are imported: a
    process's first `blas_threads` then only switches them (a command that runs one match
    lists them with its set-up, as it imports its modules, not inside the match it times)."""
    _threadpools()


@contextlib.contextmanager
def blas_threads(n_pairs: int) -> Iterator[None]:
    """One BLAS thread inside the block when n_pairs (submap x map objects) is below
    PIN_BELOW_PAIRS; the BLAS's own setting otherwise."""
    if n_pairs >= PIN_BELOW_PAIRS:
        yield
        return
    # each library switched directly, and only when it is not on one thread already: a
    # fifth of threadpoolctl's `limit` context per match
    changed = []
    for lib in _threadpools().lib_controllers:
        if lib.user_api == "blas":
            n = lib.get_num_threads()
            if n != 1:
                lib.set_num_threads(1)
                changed.append((lib, n))
    try:
        yield
    finally:
        for lib, n in changed:
            lib.set_num_threads(n)


def blas_thread_counts() -> list[int]:
    """Threads each loaded BLAS library uses right now (for tests and benchmarks)."""
    from threadpoolctl import threadpool_info

    return [int(lib["num_threads"]) for lib in threadpool_info() if lib["user_api"] == "blas"]


__all__ = ["PIN_BELOW_PAIRS", "blas_thread_counts", "blas_threads", "list_blas"]
