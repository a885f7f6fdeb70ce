"""The pose graph's optimisations in a child process (fleet/solve_process.py): the same answer
as in-process, a dead child is a SolverError and the next job starts a new one, and the
service's status answers while a solve runs (GTSAM holds the GIL through an optimise: in the
service's own process nothing else would run)."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from mergesvc.core.graph import PoseGraph
from mergesvc.core.graph_job import SolveJob, SolveResult, run_job
from mergesvc.errors import SolverError
from mergesvc.fleet.config import ServiceConfig
from mergesvc.fleet.service import MergeService
from mergesvc.fleet.solve_process import ProcessOptimizer, TimedOptimizer, shared_optimizer


def hard_graph(n: int, closures: int, g: PoseGraph | None = None) -> PoseGraph:
    """A chain of n keyframes (known inliers) and `closures` wrong loop closures: GNC works
    through many iterations before it rejects them."""
    rng = np.random.default_rng(0)
    g = g if g is not None else PoseGraph(anchor="a#0")
    C = np.eye(6) * 1e-2
    step = np.eye(4)
    step[0, 3] = 1.0
    for i in range(1, n):
        g.add_factor(f"o{i}", f"a#{i - 1}", f"a#{i}", step, C, known_inlier=True)
    for j in range(closures):
        a, b = sorted(int(x) for x in rng.choice(n, 2, replace=False))
        T = np.eye(4)
        T[:3, 3] = rng.normal(0, 20, 3)
        g.add_factor(f"c{j}", f"a#{a}", f"a#{b}", T, C)
    return g


def recorded(g: PoseGraph) -> list[SolveJob]:
    jobs: list[SolveJob] = []

    def rec(job: SolveJob) -> SolveResult:
        jobs.append(job)
        return run_job(job)

    g.optimizer = rec
    return jobs


def test_the_child_gives_the_same_answer_as_this_process() -> None:
    g = hard_graph(12, 4)
    jobs = recorded(g)
    here = g.optimize(marginals=False)
    assert jobs and any(j.gnc_known is not None for j in jobs)  # GNC and LM jobs both ran
    child = ProcessOptimizer()
    try:
        for job in jobs:
            a, b = run_job(job), child(job)
            np.testing.assert_array_equal(a.keys, b.keys)
            np.testing.assert_array_equal(a.poses, b.poses)  # bit for bit
            if a.weights is None:
                assert b.weights is None
            else:
                np.testing.assert_array_equal(a.weights, b.weights)
        g2 = hard_graph(12, 4)
        g2.optimizer = child
        there = g2.optimize(marginals=False)
        assert there.outlier_factor_ids == here.outlier_factor_ids
        for n, T in here.T_anchor_frame.items():
            np.testing.assert_array_equal(T.matrix(), there.T_anchor_frame[n].matrix())
    finally:
        child.close()


def test_a_dead_child_is_a_solver_error_and_the_next_job_starts_another() -> None:
    """A job the child dies of (its arrays malformed: not a SolverError, the child exits)."""
    g = hard_graph(6, 1)
    jobs = recorded(g)
    g.optimize(marginals=False)
    child = ProcessOptimizer()
    try:
        child(jobs[0])
        broken = replace(jobs[0], prior_poses=np.zeros((1, 3, 3)))  # the child raises, exits
        with pytest.raises(SolverError, match="solver process failed"):
            child(broken)
        assert child(jobs[0]).poses.shape == (len(jobs[0].initial_keys), 4, 4)
        assert child.starts == 2
    finally:
        child.close()


def test_ctrl_c_to_the_process_group_leaves_the_child_to_its_parent() -> None:
    """SIGINT (a terminal's Ctrl-C reaches the whole group) is the parent's to act on: the
    child neither dies nor prints a KeyboardInterrupt traceback, and answers the next job."""
    import os
    import signal

    g = hard_graph(6, 1)
    jobs = recorded(g)
    g.optimize(marginals=False)
    child = ProcessOptimizer()
    try:
        first = child(jobs[0])
        os.kill(child._proc.pid, signal.SIGINT)
        time.sleep(0.3)
        assert child._proc.poll() is None
        np.testing.assert_allclose(child(jobs[0]).poses, first.poses)
        assert child.starts == 1
    finally:
        child.close()


def test_status_answers_while_a_large_solve_runs() -> None:
    """The service solves a graph that takes GNC many iterations while another thread asks
    status over and over: many answers come while the GNC job is out (with GTSAM in the
    service's process its optimise holds the GIL, and at most one or two would)."""
    svc = MergeService(ServiceConfig(store=":memory:"), session=None)
    try:
        hard_graph(40, 40, svc.graph)
        child = shared_optimizer()
        answers = [0]
        during: list[int] = []

        def gated(job: SolveJob) -> SolveResult:
            before = answers[0]
            try:
                return child(job)
            finally:
                if job.gnc_known is not None:
                    during.append(answers[0] - before)

        svc.graph.optimizer = gated
        svc._dirty = True
        stop = threading.Event()

        def ask() -> None:
            while not stop.is_set():
                assert svc.status(poses=False)["solve"]["ok"]
                answers[0] += 1

        th = threading.Thread(target=ask)
        th.start()
        try:
            svc._optimize()
        finally:
            stop.set()
            th.join(30.0)
        assert svc.stats.optimizations == 1 and len(during) == 1
        assert during[0] >= 10, during
    finally:
        svc.close()


class _StopError(Exception):
    pass


def gnc_job(n: int) -> SolveJob:
    """The GNC job of hard_graph(n, n), not solved here (n = 100: ~4 s of GNC at no load)."""
    g = hard_graph(n, n)
    got: list[SolveJob] = []

    def rec(job: SolveJob) -> SolveResult:
        if job.gnc_known is not None:
            got.append(job)
            raise _StopError
        return run_job(job)

    g.optimizer = rec
    with pytest.raises(_StopError):
        g.optimize(marginals=False)
    return got[0]


def test_a_child_that_does_not_answer_in_time_is_stopped_and_the_next_job_starts_another(
) -> None:
    """A GNC job that takes seconds, given a timeout far below that: SolverError that says
    so, the child killed (not left solving); the next job, with time enough, answers."""
    slow = gnc_job(100)
    small = hard_graph(6, 1)
    small_jobs = recorded(small)
    small.optimize(marginals=False)
    child = ProcessOptimizer()
    try:
        child(small_jobs[0])  # the child started and warm
        first = child._proc
        assert first is not None
        timed = TimedOptimizer(child, 0.05)
        with pytest.raises(SolverError, match=r"no answer from the solver process within 0\.05 s"):
            timed(slow)
        assert first.poll() is not None  # killed, not solving on
        assert timed.timeout_s == 0.1  # the next try waits twice as long
        with pytest.raises(SolverError, match=r"within 0\.1 s"):
            timed(slow)
        assert timed.timeout_s == 0.2
        assert child(small_jobs[0], timeout_s=60.0).poses.shape[1:] == (4, 4)
        assert child.starts == 3
    finally:
        child.close()


def test_the_child_dies_with_its_parent(tmp_path) -> None:
    """A parent process whose solver child is in the middle of a seconds-long GNC job is killed
    with SIGKILL (as `bench soak` kills the service): the child is gone within 2 s, not
    solving on to the end of the job (Linux: PR_SET_PDEATHSIG)."""
    import os
    import pickle
    import signal
    import subprocess
    import sys
    import time

    small = hard_graph(6, 1)
    small_jobs = recorded(small)
    small.optimize(marginals=False)
    job_file = tmp_path / "job.pickle"
    job_file.write_bytes(pickle.dumps((small_jobs[0], gnc_job(100))))
    code = (
        "import pickle, sys\n"
        "from mergesvc.fleet.solve_process import ProcessOptimizer\n"
        f"small, slow = pickle.loads(open({str(job_file)!r}, 'rb').read())\n"
        "p = ProcessOptimizer()\n"
        "p(small)\n"  # the child is up (and has asked to die with its parent)
        "print(p._proc.pid, flush=True)\n"
        "p(slow)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        child_pid = int(parent.stdout.readline())
        time.sleep(0.5)  # the job is in the child, solving
        os.kill(child_pid, 0)  # alive
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        gone = time.monotonic() + 2.0
        while time.monotonic() < gone:
            try:
                with open(f"/proc/{child_pid}/stat") as fh:
                    if fh.read().split(") ")[1].startswith("Z"):  # dead, not yet reaped
                        break
            except (FileNotFoundError, ProcessLookupError):
                break
            time.sleep(0.05)
        else:
            os.kill(child_pid, signal.SIGKILL)
            pytest.fail("the solver child outlived its parent by 2 s")
    finally:
        if parent.poll() is None:
            parent.kill()


def test_the_child_outlives_the_thread_that_started_it() -> None:
    """The parent-death signal follows the thread that started the child: children are
    started from one thread that lives as long as the process, so a service's worker thread
    that ends (a closed service) does not take the process's solver child with it."""
    import time

    small = hard_graph(6, 1)
    small_jobs = recorded(small)
    small.optimize(marginals=False)
    child = ProcessOptimizer()
    try:
        th = threading.Thread(target=child, args=(small_jobs[0],))
        th.start()
        th.join(60.0)
        proc = child._proc
        assert proc is not None and child.jobs == 1
        time.sleep(0.5)
        assert proc.poll() is None  # alive after its first job's thread ended
        child(small_jobs[0])
        assert child.starts == 1
    finally:
        child.close()
