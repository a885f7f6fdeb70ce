"""core/calibration.py: variance-component estimation on synthetic pose graphs whose noise is
known. The Monte-Carlo redundancy numbers against the exact ones (dense I - A H^-1 A^T), and the
scales a few iterations recover against the truth they were drawn with; then through PoseGraph.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from mergesvc.core.calibration import (
    CalibrationConfig,
    Component,
    factor_normal_matrix,
    scale_standard_error,
    updated_scale,
    variance_components,
)
from mergesvc.core.config import GraphConfig
from mergesvc.core.graph import PoseGraph

DECLARED = np.array([0.006] * 3 + [0.01] * 3)
CLOSURE_SIGMA = np.array([0.01] * 3 + [0.1] * 3)
LOOP_SIGMA = np.array([0.003] * 3 + [0.05] * 3)  # loop closures along one robot's chain


def _world(seed: int, n: int, closures: int, true_scale: np.ndarray, closure_scale: float):
    """Two robots' odometry chains (noise = DECLARED x true_scale per step) and closures
    between them (noise = CLOSURE_SIGMA x closure_scale): (truth, odometry steps, closures)."""
    rng = np.random.default_rng(seed)
    truth, odo = {}, {}
    for r in (0, 1):
        T = gtsam.Pose3(gtsam.Rot3(), np.array([0.0, 5.0 * r, 0.0]))
        truth[r], odo[r] = [T], []
        for i in range(n - 1):
            D = gtsam.Pose3(gtsam.Rot3.Yaw(0.03 * np.sin(i / 20 + r)), np.array([0.5, 0, 0]))
            T = T.compose(D)
            truth[r].append(T)
            odo[r].append(D.compose(gtsam.Pose3.Expmap(rng.normal(0, DECLARED * true_scale))))
    pairs = []
    for _ in range(closures):
        i, j = (int(x) for x in rng.integers(0, n, 2))
        Z = truth[0][i].between(truth[1][j]).compose(
            gtsam.Pose3.Expmap(rng.normal(0, CLOSURE_SIGMA * closure_scale)))
        pairs.append((i, j, Z))
    return truth, odo, pairs


def _key(r: int, i: int) -> int:
    return gtsam.symbol("abc"[r], i)


def _graph(truth, odo, pairs, scales: dict[str, np.ndarray]):
    g, groups = gtsam.NonlinearFactorGraph(), []
    g.add(gtsam.PriorFactorPose3(_key(0, 0), truth[0][0],
                                 gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    groups.append(None)
    for r in (0, 1):
        s = DECLARED * scales[f"o{r}"]
        for i, D in enumerate(odo[r]):
            g.add(gtsam.BetweenFactorPose3(_key(r, i), _key(r, i + 1), D,
                                           gtsam.noiseModel.Gaussian.Covariance(np.diag(s**2))))
            groups.append(f"o{r}")
    s = CLOSURE_SIGMA * scales["c"]
    for i, j, Z in pairs:
        g.add(gtsam.BetweenFactorPose3(_key(0, i), _key(1, j), Z,
                                       gtsam.noiseModel.Gaussian.Covariance(np.diag(s**2))))
        groups.append("c")
    return g, groups


def _initial(truth) -> gtsam.Values:
    v = gtsam.Values()
    for r in (0, 1):
        for i, T in enumerate(truth[r]):
            v.insert(_key(r, i), T)
    return v


def _whitened_jacobian(g: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> np.ndarray:
    """The whitened Jacobian A (6 rows a factor, 6 columns a pose) of g at values, dense."""
    gfg = g.linearize(values)
    cols: dict[int, int] = {}
    blocks = []
    for i in range(g.size()):
        jf = gfg.at(i)
        A, _ = jf.jacobian()
        blocks.append((i, jf.keys(), A))
        for k in list(jf.keys()):
            cols.setdefault(k, 6 * len(cols))
    A_full = np.zeros((6 * g.size(), 6 * len(cols)))
    for i, keys, A in blocks:
        for j, k in enumerate(keys):
            A_full[6 * i:6 * i + 6, cols[k]:cols[k] + 6] = A[:, 6 * j:6 * j + 6]
    return A_full


def test_monte_carlo_redundancy_matches_the_exact_one() -> None:
    truth, odo, pairs = _world(3, 40, 30, np.ones(6), 1.0)
    scales = {"o0": np.ones(6), "o1": np.ones(6), "c": np.ones(6)}
    g, groups = _graph(truth, odo, pairs, scales)
    est = gtsam.LevenbergMarquardtOptimizer(g, _initial(truth)).optimize()
    got = variance_components(g, est, groups, CalibrationConfig(samples=256))
    # the exact redundancy numbers: the diagonal of I - A H^-1 A^T, per group and axis
    A_full = _whitened_jacobian(g, est)
    n_cols = A_full.shape[1] // 6
    R = np.eye(len(A_full)) - A_full @ np.linalg.solve(A_full.T @ A_full, A_full.T)
    for name in ("o0", "o1", "c"):
        exact = sum(np.diag(R[6 * i:6 * i + 6, 6 * i:6 * i + 6])
                    for i, gr in enumerate(groups) if gr == name)
        # 256 draws: a few per cent of each group's total
        np.testing.assert_allclose(got[name].redundancy, exact, rtol=0.15, atol=1.0)
        assert got[name].factors == groups.count(name)
    total = sum(c.redundancy.sum() for c in got.values())
    assert total == pytest.approx(6 * g.size() - 6 * n_cols, rel=0.05)  # m - n, all told


def _fleet_graph(n: int = 40, closures: int = 60) -> tuple[gtsam.NonlinearFactorGraph,
                                                             gtsam.Values]:
    """Three robots' odometry chains of n keyframes 5 m apart (rotations whose lever arms
    reach 200 m, as a fleet's do) and closures between random keyframes of two of them."""
    rng = np.random.default_rng(5)
    g, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.002] * 3 + [0.02] * 3))
    clo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.02] * 3 + [0.2] * 3))
    truth = {}
    for r in range(3):
        T = gtsam.Pose3(gtsam.Rot3.Yaw(r), np.array([0.0, 20.0 * r, 0.0]))
        truth[r] = [T]
        for i in range(n - 1):
            D = gtsam.Pose3(gtsam.Rot3.Yaw(0.1 * np.sin(i / 7 + r)), np.array([5.0, 0, 0]))
            T = T.compose(D)
            truth[r].append(T)
            g.add(gtsam.BetweenFactorPose3(_key(r, i), _key(r, i + 1), D, odo))
        for i, T in enumerate(truth[r]):
            values.insert(_key(r, i), T)
    g.add(gtsam.PriorFactorPose3(_key(0, 0), truth[0][0],
                                 gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    for _ in range(closures):
        a, b = (int(x) for x in rng.choice(3, 2, replace=False))
        i, j = (int(x) for x in rng.integers(0, n, 2))
        g.add(gtsam.BetweenFactorPose3(_key(a, i), _key(b, j), truth[a][i].between(truth[b][j]),
                                       clo))
    return g, values


def test_the_normal_matrix_is_factored_in_its_fill_reducing_order() -> None:
    """A fleet's normal matrix H = A^T A factored with its pivots on the diagonal (rows
    permuted as the columns): half as many nonzeros as with SuperLU's partial pivoting, which
    leaves the fill-reducing order, and solving as a dense solve does."""
    A = _whitened_jacobian(*_fleet_graph())
    H = sp.csc_matrix(A.T @ A)
    lu = factor_normal_matrix(H)
    assert np.array_equal(lu.perm_r, lu.perm_c)
    pivoted = sla.splu(H, permc_spec="MMD_AT_PLUS_A")  # SuperLU's default pivoting
    assert not np.array_equal(pivoted.perm_r, pivoted.perm_c)
    assert lu.L.nnz + lu.U.nnz < 0.5 * (pivoted.L.nnz + pivoted.U.nnz)
    B = np.random.default_rng(0).standard_normal((H.shape[0], 4))
    np.testing.assert_allclose(lu.solve(B), np.linalg.solve(A.T @ A, B), rtol=1e-6, atol=1e-9)
    with pytest.raises(RuntimeError):  # singular: what variance_components reports
        factor_normal_matrix(sp.csc_matrix(np.diag([1.0, 2.0, 0.0])))


def test_a_few_iterations_recover_the_true_scales() -> None:
    """One robot's odometry declared 3x too loose on rotation and 2x too tight on translation,
    loop closures along its own chain declared 1.5x too tight: after a few iterations the
    estimate lands within 20 % of the truth on every axis the loops check (rotation; the
    closures' every axis)."""
    rng = np.random.default_rng(11)
    true_o = np.array([1 / 3] * 3 + [2.0] * 3)
    n = 150
    truth, odo = [gtsam.Pose3()], []
    for i in range(n - 1):
        D = gtsam.Pose3(gtsam.Rot3.Ypr(0.05 * np.sin(i / 15), 0.01, 0.0),
                        np.array([0.5, 0.0, 0.05]))
        truth.append(truth[-1].compose(D))
        odo.append(D.compose(gtsam.Pose3.Expmap(rng.normal(0, DECLARED * true_o))))
    loops = []
    for _ in range(200):
        i, j = sorted(int(x) for x in rng.choice(n, 2, replace=False))
        loops.append((i, j, truth[i].between(truth[j]).compose(
            gtsam.Pose3.Expmap(rng.normal(0, LOOP_SIGMA * 1.5)))))
    scales = {"o": np.ones(6), "c": np.ones(6)}
    cfg = CalibrationConfig(prior_redundancy=1.0)
    est = gtsam.Values()
    for i, T in enumerate(truth):
        est.insert(_key(0, i), T)
    for _ in range(8):
        g, groups = gtsam.NonlinearFactorGraph(), [None]
        g.add(gtsam.PriorFactorPose3(_key(0, 0), truth[0],
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        for i, D in enumerate(odo):
            g.add(gtsam.BetweenFactorPose3(_key(0, i), _key(0, i + 1), D,
                                           gtsam.noiseModel.Diagonal.Sigmas(
                                               DECLARED * scales["o"])))
            groups.append("o")
        for i, j, Z in loops:
            g.add(gtsam.BetweenFactorPose3(_key(0, i), _key(0, j), Z,
                                           gtsam.noiseModel.Diagonal.Sigmas(
                                               LOOP_SIGMA * scales["c"])))
            groups.append("c")
        est = gtsam.LevenbergMarquardtOptimizer(g, est).optimize()
        for name, comp in variance_components(g, est, groups, cfg).items():
            scales[name] = updated_scale(scales[name], comp, cfg)
    np.testing.assert_allclose(scales["c"], 1.5, rtol=0.2)
    np.testing.assert_allclose(scales["o"][:3], 1 / 3, rtol=0.2)
    assert scales["o"][3] > 1.6 and scales["o"][3:].mean() > 1.3  # translation: too tight


def test_the_standard_error_matches_the_scatter_of_the_estimate() -> None:
    """scale_standard_error against Monte Carlo: one estimate's scales (declared = truth, no
    prior) over 150 draws of the same two-robot graph scatter, axis by axis and group by
    group, as the estimate's own standard error says (rtol 0.3: 150 draws estimate a spread to
    ~6 %; the square root's delta method overstates it by up to ~15 % where r is ~2); the
    simpler 1 / sqrt(2 r) overstates it by up to 1.9x (measured)."""
    cfg = CalibrationConfig(prior_redundancy=0.0, samples=64)
    got: dict[str, list[np.ndarray]] = {"o0": [], "c": []}
    se: dict[str, list[np.ndarray]] = {"o0": [], "c": []}
    for seed in range(150):
        # closures 3x tighter than _world's: they check every axis of the odometry
        truth, odo, pairs = _world(100 + seed, 30, 25, np.ones(6), 1 / 3)
        g, groups = _graph(truth, odo, pairs, {"o0": np.ones(6), "o1": np.ones(6),
                                               "c": np.full(6, 1 / 3)})
        est = gtsam.LevenbergMarquardtOptimizer(g, _initial(truth)).optimize()
        comps = variance_components(g, est, groups, cfg)
        for name in got:
            got[name].append(updated_scale(np.ones(6), comps[name], cfg))
            se[name].append(scale_standard_error(comps[name]))
    for name in got:
        predicted = np.sqrt(np.mean(np.square(se[name]), axis=0))
        assert np.all(predicted > 0.05) and np.all(predicted < 0.5)  # checked, not exactly
        np.testing.assert_allclose(np.std(got[name], axis=0), predicted, rtol=0.3)
    unchecked = Component(redundancy=np.array([0.0, -1e-9, 2.0, 2.0, 2.0, 2.0]),
                          redundancy_sq=np.array([0.0, 0.0, 2.0, 1.0, 5.0, 0.0]))
    se_of = scale_standard_error(unchecked)
    assert np.isinf(se_of[:2]).all()
    # 1 / sqrt(2 r) at most (two terms of weight 1), 0.5 / sqrt(2) for r spread over four
    np.testing.assert_allclose(se_of[2:], [0.5, 0.5 / np.sqrt(2), 0.5, 0.0])


def test_an_axis_nothing_checks_keeps_its_declared_scale() -> None:
    comp = Component(residual=np.zeros(6), redundancy=np.zeros(6), factors=3)
    cfg = CalibrationConfig(prior_redundancy=2.0)
    np.testing.assert_allclose(updated_scale(np.ones(6), comp, cfg), 1.0)
    # with the prior off, an axis without redundancy is not moved either
    np.testing.assert_allclose(updated_scale(np.full(6, 0.7), comp,
                                             CalibrationConfig(prior_redundancy=0.0)), 0.7)
    # and the clamp holds
    big = Component(residual=np.full(6, 1e6), redundancy=np.ones(6))
    np.testing.assert_allclose(updated_scale(np.ones(6), big, cfg), cfg.max_scale)


def test_a_gross_factor_is_left_out() -> None:
    truth, odo, pairs = _world(2, 30, 20, np.ones(6), 1.0)
    i, j, Z = pairs[0]
    pairs[0] = (i, j, Z.compose(gtsam.Pose3(gtsam.Rot3.Yaw(1.0), np.array([5.0, 0, 0]))))
    scales = {"o0": np.ones(6), "o1": np.ones(6), "c": np.ones(6)}
    g, groups = _graph(truth, odo, pairs, scales)
    est = gtsam.LevenbergMarquardtOptimizer(g, _initial(truth)).optimize()
    got = variance_components(g, est, groups, CalibrationConfig())
    assert got["c"].left_out >= 1
    assert got["c"].factors + got["c"].left_out == groups.count("c")


def test_the_pose_graph_calibrates_its_groups() -> None:
    """Through PoseGraph: groups named on add_factor, scales after solves, only the
    configured groups moved, and the factors' covariances as solved come out scaled."""
    true_o0 = np.array([0.5] * 3 + [1.0] * 3)
    _, odo, pairs = _world(5, 80, 120, true_o0, 1.0)
    cfg = GraphConfig(calibration=dict(enabled=True, groups=("odometry",),
                                       prior_redundancy=1.0, resolves=3))
    pg = PoseGraph(anchor="a#0", config=cfg)
    for r in (0, 1):
        for i, D in enumerate(odo[r]):
            pg.add_factor(f"o{r}-{i}", f"{'ab'[r]}#{i}", f"{'ab'[r]}#{i + 1}", D,
                          np.diag(DECLARED**2), known_inlier=True, group=f"odometry:{r}")
    for n, (i, j, Z) in enumerate(pairs):
        pg.add_factor(f"c{n}", f"a#{i}", f"b#{j}", Z, np.diag(CLOSURE_SIGMA**2),
                      group="closures")
    for _ in range(4):
        pg.set_noise_scale("unused", 1.0)  # a change: solve again
        pg.optimize(marginals=False)
    scales = pg.noise_scales
    assert "closures" not in scales  # not a calibrated group
    calibrated = pg.calibrated()  # what the service's status reports
    assert set(calibrated) == {"odometry:0", "odometry:1"}
    for g, (scale, comp) in calibrated.items():
        np.testing.assert_array_equal(scale, scales[g])
        assert comp is not None and np.all(comp.redundancy > 0)
        assert np.all(comp.redundancy_sq > 0) and np.all(comp.redundancy_sq <= comp.redundancy)
    assert 0.3 < scales["odometry:0"][2] < 0.7  # yaw of robot 0: declared 2x too loose
    np.testing.assert_allclose(pg.scaled_covariance("o0-3"),
                               np.diag((DECLARED * scales["odometry:0"]) ** 2), rtol=1e-9)
    np.testing.assert_allclose(pg.scaled_covariance("c0"), np.diag(CLOSURE_SIGMA**2))


def _counted_calibrations(monkeypatch) -> list[int]:
    """The graph sizes of the calibrations run from now on (variance_components wrapped)."""
    import mergesvc.core.graph as graph_module

    calls: list[int] = []
    real = graph_module.variance_components

    def counting(graph, values, groups, cal):
        calls.append(graph.size())
        return real(graph, values, groups, cal)

    monkeypatch.setattr(graph_module, "variance_components", counting)
    return calls


def _two_chains(odo, pairs, closures: range, **calibration) -> PoseGraph:
    """Both robots' odometry (known inliers, a group each) and the closures `closures`."""
    pg = PoseGraph(anchor="a#0", config=GraphConfig(calibration=dict(
        enabled=True, groups=("odometry",), **calibration)))
    for r in (0, 1):
        for i, D in enumerate(odo[r]):
            pg.add_factor(f"o{r}-{i}", f"{'ab'[r]}#{i}", f"{'ab'[r]}#{i + 1}", D,
                          np.diag(DECLARED**2), known_inlier=True, group=f"odometry:{r}")
    _close(pg, pairs, closures)
    return pg


def _close(pg: PoseGraph, pairs, closures: range) -> None:
    for n in closures:
        i, j, Z = pairs[n]
        pg.add_factor(f"c{n}", f"a#{i}", f"b#{j}", Z, np.diag(CLOSURE_SIGMA**2),
                      group="closures")


def test_calibration_runs_again_only_once_the_graph_has_grown(monkeypatch) -> None:
    """A calibration is a pass over the whole graph: solving the same graph again does not
    repeat it; a quarter more factors (`every_growth`) does."""
    calls = _counted_calibrations(monkeypatch)
    _, odo, pairs = _world(6, 60, 60, np.ones(6), 1.0)
    pg = _two_chains(odo, pairs, range(20), resolves=0, every_growth=0.25)
    pg.optimize(marginals=False)
    assert len(calls) == 1
    _close(pg, pairs, range(20, 25))  # 145 -> 150 factors: under a quarter more
    pg.optimize(marginals=False)
    assert len(calls) == 1
    _close(pg, pairs, range(25, 60))  # 185: more than a quarter over the 145 of the last one
    pg.optimize(marginals=False)
    assert len(calls) == 2 and calls[1] >= 1.25 * calls[0]


def test_a_graph_solved_on_restored_scales_calibrates_again_only_once_it_has_grown(
        monkeypatch) -> None:
    """A restarted service restores the scales its last calibration left and solves what it
    restored without calibrating (`calibrating` off): the graph then counts as calibrated at
    that size, so the next solves do not calibrate it again (and again, re-solving) until it
    has grown by `every_growth`; with nothing restored the first solve calibrates."""
    calls = _counted_calibrations(monkeypatch)
    _, odo, pairs = _world(6, 60, 60, np.ones(6), 1.0)

    def restarted(scales: dict[str, np.ndarray]) -> PoseGraph:
        pg = _two_chains(odo, pairs, range(20), resolves=2, every_growth=0.25)
        for group, s in scales.items():
            pg.set_noise_scale(group, s)
        pg.calibrating = False  # as MergeService.restore solves what it restored
        pg.optimize(marginals=False)
        pg.calibrating = True
        pg.set_noise_scale("unused", 1.0)  # a change: solved again, now calibrating
        pg.optimize(marginals=False)
        return pg

    pg = restarted({"odometry:0": np.full(6, 0.8), "odometry:1": np.full(6, 1.2)})
    assert calls == [] and pg.noise_scales["odometry:0"].tolist() == [0.8] * 6
    assert pg.calibrated()["odometry:0"][1] is None  # restored, not estimated: no redundancy
    _close(pg, pairs, range(20, 60))  # 145 -> 185 factors: more than a quarter more
    pg.optimize(marginals=False)
    assert len(calls) >= 1 and calls[0] > 1.2 * 145  # (less what GNC left out)
    calls.clear()
    restarted({})  # nothing restored: the first solve calibrates
    assert len(calls) >= 1


def test_scaling_a_covariance_against_its_definition() -> None:
    """scale_covariance(s) against M C M^T with M = L^-1 diag(s) L (L from `decorrelation`),
    for covariances with and without rotation-translation cross terms, one by one and
    stacked; a scale of ones changes nothing."""
    from mergesvc.core.calibration import decorrelation, scale_covariance, scale_covariances

    rng = np.random.default_rng(5)
    Cs = []
    for k in range(6):
        A = rng.normal(size=(6, 6))
        C = A @ A.T + 0.1 * np.eye(6)
        if k % 2:
            C[3:, :3] = C[:3, 3:] = 0.0
        Cs.append(C)
    s = np.array([0.5, 2.0, 1.3, 0.7, 1.0, 3.0])
    for C in Cs:
        L = decorrelation(C)
        M = np.linalg.inv(L) @ np.diag(s) @ L
        np.testing.assert_allclose(scale_covariance(C, s), M @ C @ M.T, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(scale_covariance(C, np.ones(6)), C, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(scale_covariances(np.stack(Cs), s),
                               np.stack([scale_covariance(C, s) for C in Cs]), rtol=1e-12)
