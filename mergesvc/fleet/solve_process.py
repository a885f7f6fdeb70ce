"""Pose-graph optimisations (core/graph_job.py) run in a child process, so that the service's
threads (queries, ingress, acks) go on while GTSAM, which holds the GIL through an optimise,
solves. One child per service process, started at the first job (`python -m
mergesvc.fleet.solve_process`, its stdin and stdout a pipe of pickled jobs and results; its
stderr the parent's), shared by every graph of the process one job at a time. The caller's
thread waits on the pipe without the GIL. A child that dies, or does not answer within the
job's timeout (then it is killed), fails its job with SolverError (the solve's backoff retries
it) and the next job starts a new one; the arrays are the same, so is the answer. A job that
is not a SolveJob runs its own `run()` (the large submaps' matches: fleet/lane.py), in a
child of its own, which may run at a lower priority (`nice`). On Linux the
child dies with its parent (a parent killed with SIGKILL leaves no solver running), and it
hands its heap's free pages back after each job.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import os
import pickle
import queue
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any, BinaryIO

from mergesvc.core.graph_job import Optimizer, SolveJob, SolveResult, run_job
from mergesvc.errors import SolverError, one_line


class SolverTimeoutError(SolverError):
    """The solver child did not answer a job in time (it was stopped)."""


class ProcessOptimizer:
    """Callable as an `Optimizer`: each job run in the child process."""

    def __init__(self, nice: int = 0) -> None:
        self.nice = nice  # the child's niceness added (a background child: 10)
        self._killed = False
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self.jobs = 0  # jobs the child answered
        self.starts = 0  # children started

    def _child(self) -> subprocess.Popen[bytes]:
        if self._killed:
            raise SolverError("the child process was stopped for good (kill)")
        if self._proc is None or self._proc.poll() is not None:
            self._stop()
            self._proc = _spawn([sys.executable, "-m", "mergesvc.fleet.solve_process",
                                 str(os.getpid()), str(self.nice)])
            self.starts += 1
        return self._proc

    def __call__(self, job: SolveJob, timeout_s: float | None = None) -> SolveResult:
        """The job's result from the child; SolverError when it fails, dies, or has not
        answered after `timeout_s` (None: waits as long as it takes)."""
        with self._lock:
            proc = self._child()
            assert proc.stdin is not None and proc.stdout is not None
            try:
                pickle.dump(job, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                proc.stdin.flush()
                if timeout_s is not None and not select.select([proc.stdout], [], [],
                                                               timeout_s)[0]:
                    self._stop()
                    raise SolverTimeoutError(
                        f"{_what(job)}: no answer from the solver process within "
                        f"{timeout_s:g} s (stopped)")
                ok, out = pickle.load(proc.stdout)
            except (OSError, EOFError, pickle.UnpicklingError) as exc:
                self._stop()
                raise SolverError(f"{_what(job)}: the solver process failed "
                                  f"({one_line(exc) or type(exc).__name__})") from exc
            except BaseException:  # a job or reply half through the pipe: never read it later
                self._stop()
                raise
            self.jobs += 1
        if not ok:
            raise SolverError(out)
        return out  # type: ignore[no-any-return]

    def _stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                with contextlib.suppress(OSError):
                    pipe.close()

    def close(self) -> None:
        with self._lock:
            self._stop()

    def kill(self) -> None:
        """Stop the child now, a job in flight or not (that job fails with SolverError), and
        for good: no later job starts one (without waiting for the lock a job holds)."""
        self._killed = True
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()


def _what(job: Any) -> str:
    return str(job.what) if hasattr(job, "run") else f"{job.what} optimisation"


class _Spawner:
    """One thread that lives as long as the process and starts every solver child: Linux's
    parent-death signal fires when the thread that started a child ends, not its process, and
    the threads that solve (a service's worker) come and go."""

    def __init__(self) -> None:
        self._jobs: queue.Queue[tuple[list[str], list[Any], threading.Event]] = queue.Queue()
        threading.Thread(target=self._run, name="mergesvc-solver-spawner", daemon=True).start()

    def _run(self) -> None:
        while True:
            argv, box, done = self._jobs.get()
            try:
                box.append(subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE))
            except BaseException as exc:  # handed to the caller's thread, raised there
                box.append(exc)
            done.set()

    def popen(self, argv: list[str]) -> subprocess.Popen[bytes]:
        box: list[Any] = []
        done = threading.Event()
        self._jobs.put((argv, box, done))
        done.wait()
        if isinstance(box[0], BaseException):
            raise box[0]
        return box[0]  # type: ignore[no-any-return]


@functools.cache
def _spawner() -> _Spawner:
    return _Spawner()


def _spawn(argv: list[str]) -> subprocess.Popen[bytes]:
    return _spawner().popen(argv)


_shared: ProcessOptimizer | None = None
_shared_lock = threading.Lock()


def shared_optimizer() -> ProcessOptimizer:
    """The process's solver child (started at its first job, stopped at exit)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = ProcessOptimizer()
            atexit.register(_shared.close)
        return _shared


class TimedOptimizer:
    """An `Optimizer`: each job to the process's solver child with a timeout that doubles after
    each job that ran out of it, so a graph whose solve needs longer is solved at a later try
    rather than stopped at every one."""

    def __init__(self, child: ProcessOptimizer, timeout_s: float) -> None:
        self.child = child
        self.timeout_s = timeout_s

    def __call__(self, job: SolveJob) -> SolveResult:
        try:
            return self.child(job, timeout_s=self.timeout_s)
        except SolverTimeoutError:
            self.timeout_s *= 2.0
            raise


def optimizer(in_child: bool, timeout_s: float | None = None) -> Optimizer:
    """The process's solver child (`in_child`; with `timeout_s`, a TimedOptimizer), or GTSAM
    in the calling thread (no timeout: a thread cannot be stopped)."""
    if not in_child:
        return run_job
    if timeout_s is None:
        return shared_optimizer()
    return TimedOptimizer(shared_optimizer(), timeout_s)


def _die_with_parent(parent: int | None) -> None:
    """Linux: SIGKILL this process when the thread that started it ends (prctl
    PR_SET_PDEATHSIG; the parent starts it from a thread that lives as long as the process);
    elsewhere nothing (the child still ends at its next read, on the closed pipe)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent:  # it died before the call
        sys.exit(0)


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        import ctypes

        fn = ctypes.CDLL("libc.so.6").malloc_trim
        fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
        return fn  # type: ignore[no-any-return]
    except (OSError, AttributeError):  # not glibc: nothing to trim
        return None


def trim_heap() -> None:
    """Hand the C heap's free pages back to the system after a solve (glibc `malloc_trim(0)`)."""
    fn = _malloc_trim()
    if fn is not None:
        fn(0)


def serve(inp: BinaryIO, out: BinaryIO) -> None:
    """The child's loop: a job in, (True, result) or (False, message) out, until EOF."""
    while True:
        try:
            job = pickle.load(inp)
        except EOFError:
            return
        reply: tuple[bool, Any]
        try:
            run = getattr(job, "run", None)
            reply = (True, run() if run is not None else run_job(job))
        except SolverError as exc:
            reply = (False, str(exc))
        pickle.dump(reply, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()
        del job, reply
        trim_heap()


def main() -> None:
    # the pipe is a private copy of fd 1; fd 1 itself goes to stderr, so nothing GTSAM prints
    # can corrupt it
    _die_with_parent(int(sys.argv[1]) if len(sys.argv) > 1 else None)
    # Ctrl-C in a terminal reaches the whole process group: the parent decides (it closes
    # the pipe, or its death ends the child); no KeyboardInterrupt traceback here
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if len(sys.argv) > 2 and int(sys.argv[2]):
        os.nice(int(sys.argv[2]))
    pipe = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    try:
        serve(sys.stdin.buffer, pipe)
    except Exception as exc:  # the parent gets EOF (a SolverError); its log gets one line
        print(f"solver process: {one_line(exc) or type(exc).__name__}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()


__all__ = ["ProcessOptimizer", "SolverTimeoutError", "TimedOptimizer", "main", "optimizer",
           "serve", "shared_optimizer", "trim_heap"]
