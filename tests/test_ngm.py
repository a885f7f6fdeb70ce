"""The neural solver (NGM): the numpy forward pass against pygmtools' own NGM and a loop-based
reference, the torch training network against the numpy pass, the shipped weights, the
solver in both pipeline modes, and a seeded training smoke test (only with torch)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pygmtools as pygm
import pytest
from pygmtools.numpy_backend import NGM_Net

from mergesvc.core.affinity import edge_scales, paper_K, paper_node_affinity
from mergesvc.core.config import match_config
from mergesvc.core.pipeline import match
from mergesvc.core.solvers import ngm
from mergesvc.core.solvers.problem import AssignmentProblem
from mergesvc.errors import SolverError
from mergesvc.sim import Family, make_scenario

CHANNELS = (16, 16, 16)
CLI = [sys.executable, "-m", "mergesvc.cli"]


def random_arrays(rng: np.random.Generator, channels: tuple[int, ...] = CHANNELS,
                  scale: float = 0.5) -> dict[str, np.ndarray]:
    """NGM parameters of the right shapes, random."""
    out, width = {}, 1
    for i, c in enumerate(channels):
        p = f"gnn_layer_{i}."
        for f in ("n_func", "n_self_func"):
            out[p + f + ".0.weight"] = rng.normal(size=(c, width)) * scale
            out[p + f + ".0.bias"] = rng.normal(size=c) * scale
            out[p + f + ".2.weight"] = rng.normal(size=(c, c)) * scale
            out[p + f + ".2.bias"] = rng.normal(size=c) * scale
        out[p + "classifier.weight"] = rng.normal(size=(1, c)) * scale
        out[p + "classifier.bias"] = rng.normal(size=1) * scale
        width = c + 1
    out["classifier.weight"] = rng.normal(size=(1, width)) * scale
    out["classifier.bias"] = rng.normal(size=1) * scale
    return out


def pygmtools_net(arrays: dict[str, np.ndarray]) -> NGM_Net:
    """pygmtools' numpy NGM_Net holding these parameters (nothing downloaded)."""
    net = NGM_Net(CHANNELS, 1)
    for i in range(net.gnn_layer):
        layer = net.dict[f"gnn_layer_{i}"]
        mods = {"n_func.0": layer.n_func.getitem(0), "n_func.2": layer.n_func.getitem(2),
                "n_self_func.0": layer.n_self_func.getitem(0),
                "n_self_func.2": layer.n_self_func.getitem(2), "classifier": layer.classifier}
        for name, mod in mods.items():
            mod.weight = arrays[f"gnn_layer_{i}.{name}.weight"]
            mod.bias = arrays[f"gnn_layer_{i}.{name}.bias"]
    net.classifier.weight, net.classifier.bias = arrays["classifier.weight"], \
        arrays["classifier.bias"]
    return net


def pygmtools_ngm(K: np.ndarray, n1: int, n2: int, arrays: dict[str, np.ndarray]) -> np.ndarray:
    """pygmtools' numpy NGM on column-major K, first embedding diag(K). (n1, n2)."""
    x0 = np.diag(K).reshape(n2, n1).T[None]
    return pygm.ngm(K[None], np.array([n1]), np.array([n2]), x0=x0,
                    network=pygmtools_net(arrays), pretrain=False, backend="numpy")[0]


def random_K(m: int, rng: np.random.Generator, density: float = 0.4) -> np.ndarray:
    K = rng.random((m, m)) * (rng.random((m, m)) < density)
    K = (K + K.T) / 2
    np.fill_diagonal(K, rng.random(m))
    return K


@pytest.mark.parametrize(("n1", "n2"), [(3, 5), (4, 4), (6, 3), (8, 20)])
def test_forward_pass_is_pygmtools_ngm(n1: int, n2: int) -> None:
    """All pairs: the same soft matrix as pygmtools' own numpy NGM with the same weights,
    submap smaller than, equal to and larger than the map."""
    rng = np.random.default_rng(n1 * 100 + n2)
    arrays = random_arrays(rng)
    K = random_K(n1 * n2, rng)
    got = ngm.solve_dense(K, n1, n2, ngm.NGMWeights(arrays))
    np.testing.assert_allclose(got, pygmtools_ngm(K, n1, n2, arrays), atol=1e-10)


def test_shipped_weights_on_a_paper_mode_K_match_pygmtools() -> None:
    sc = make_scenario(Family.UNDERWATER, seed=3, n_map=25, n_sub=5)
    sub, map_ = sc.submap.arrays(), sc.map.arrays()
    cfg = match_config(mode="paper", affinity={"edge_radius_m": 2.0})
    sigma, radius = edge_scales(map_, cfg.affinity)
    K = paper_K(paper_node_affinity(sub, map_, cfg.affinity), sub, map_, sigma, radius)
    got = ngm.solve_dense(K, sub.n, map_.n)
    K_ref = np.where(np.abs(K) < ngm.EDGE_MIN, 0.0, K)  # what the association graph keeps
    ref = pygmtools_ngm(K_ref, sub.n, map_.n, dict(ngm.packaged_weights().arrays))
    np.testing.assert_allclose(got, ref, atol=1e-9)


def test_affinities_below_edge_min_are_no_edges() -> None:
    """Edge affinities that underflow (subnormal float64 included) are not edges: the result is
    the one without them, and they do not count in a pair's degree."""
    rng = np.random.default_rng(11)
    n1, n2 = 4, 6
    K = random_K(n1 * n2, rng)
    tiny = K.copy()
    off = ~np.eye(n1 * n2, dtype=bool) & (K == 0)
    tiny[off & (rng.random(K.shape) < 0.5)] = 1e-310  # a subnormal, as exp(-(...)) gives
    assert np.array_equal(ngm.association_graph(tiny).toarray(), K)
    np.testing.assert_array_equal(ngm.solve_dense(tiny, n1, n2), ngm.solve_dense(K, n1, n2))


@pytest.mark.parametrize(("n1", "n2", "steps"), [(3, 7, 20), (5, 2, 20), (4, 4, 7)])
def test_sinkhorn_is_pygmtools_sinkhorn_with_dummy_rows(n1: int, n2: int, steps: int) -> None:
    rng = np.random.default_rng(n1 + 10 * n2)
    s = rng.normal(size=(n1, n2)) * 0.3
    rows, cols = np.divmod(np.arange(n1 * n2), n2)
    got = ngm.sinkhorn(s.ravel(), rows, cols, n1, n2, tau=0.05, iters=steps)
    ref = pygm.sinkhorn(s, n1, n2, dummy_row=True, max_iter=steps, tau=0.05, backend="numpy")
    np.testing.assert_allclose(got.reshape(n1, n2), ref, atol=1e-10)


def _loop_reference(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, n1: int, n2: int,
                    arrays: dict[str, np.ndarray]) -> np.ndarray:
    """NGM written out with loops over pairs: messages averaged over the non-zero K[p, q]; the
    Sinkhorn in the log domain on the full (n1, n2) matrix (absent pairs -inf) with its dummy
    rows materialised, as pygmtools pads them (submap no larger than the map here)."""
    m = len(rows)

    def lin(name, v):
        return [sum(arrays[name + ".weight"][o, i] * v[i] for i in range(len(v)))
                + arrays[name + ".bias"][o] for o in range(len(arrays[name + ".bias"]))]

    def mlp(name, v):
        h = [max(0.0, a) for a in lin(name + ".0", v)]
        return [max(0.0, a) for a in lin(name + ".2", h)]

    def sk(vals):
        L = np.full((n2, n2), -np.inf)  # n2 - n1 dummy rows below the real ones
        L[n1:, :] = -100.0
        for p in range(m):
            L[rows[p], cols[p]] = vals[p] / ngm.SK_TAU
        for it in range(ngm.SK_ITERS):
            for r in range(n2) if it % 2 == 0 else []:
                L[r] -= np.logaddexp.reduce(L[r])
            for c in range(n2) if it % 2 == 1 else []:
                L[:, c] -= np.logaddexp.reduce(L[:, c])
        return [math.exp(L[rows[p], cols[p]]) for p in range(m)]

    diag = [K[p, p] for p in range(m)]
    x = [[d / (sum(diag) / m)] for d in diag]
    n_layers = sum(1 for k in arrays if k.endswith(".n_func.0.weight"))
    for i in range(n_layers):
        pre = f"gnn_layer_{i}."
        x1 = [mlp(pre + "n_func", v) for v in x]
        x2 = []
        for p in range(m):
            nbrs = [q for q in range(m) if K[p, q] != 0]
            msg = [sum(K[p, q] * x1[q][c] for q in nbrs) / len(nbrs) for c in range(len(x1[0]))]
            x2.append([a + b for a, b in zip(msg, mlp(pre + "n_self_func", x[p]))])
        emb = sk([lin(pre + "classifier", v)[0] for v in x2])
        x = [[*v, e] for v, e in zip(x2, emb)]
    return np.array(sk([lin("classifier", v)[0] for v in x]))


def test_candidate_forward_pass_matches_a_loop_reference() -> None:
    """Only some pairs present (verified mode's candidates): absent pairs carry no mass and
    no messages."""
    rng = np.random.default_rng(7)
    n1, n2 = 4, 7
    rows = np.repeat(np.arange(n1), 3)
    cols = np.concatenate([rng.choice(n2, size=3, replace=False) for _ in range(n1)])
    m = len(rows)
    K = random_K(m, rng, density=0.5)
    K[(rows[:, None] == rows[None]) & ~np.eye(m, dtype=bool)] = 0.0
    arrays = random_arrays(rng, channels=(4, 4), scale=0.8)
    got = ngm.ngm_soft(K, rows, cols, n1, n2, ngm.NGMWeights(arrays))
    np.testing.assert_allclose(got, _loop_reference(K, rows, cols, n1, n2, arrays), atol=1e-9)


def test_weights_round_trip_through_the_module_text() -> None:
    arrays = random_arrays(np.random.default_rng(1))
    shapes, data = ngm.encode_weights(arrays)
    back = ngm.decode_weights(shapes, data)
    for k, v in arrays.items():
        np.testing.assert_array_equal(back[k], v.astype(np.float32))
    namespace: dict = {}
    exec(ngm.weights_module_source(arrays, {"seed": 0}), namespace)  # the module as written
    assert namespace["TRAINING"] == {"seed": 0}
    assert set(ngm.decode_weights(namespace["SHAPES"], namespace["DATA"])) == set(arrays)


def test_shipped_weights_are_small_and_well_formed() -> None:
    from mergesvc.core.solvers import ngm_weights

    w = ngm.packaged_weights()
    assert w.n_layers == 3 and set(w.arrays) == set(ngm.param_names(3))
    assert len(ngm_weights.DATA) < 5 * 2**20
    assert ngm_weights.TRAINING["command"].startswith("mergesvc solver train")


def test_bad_weights_are_refused() -> None:
    arrays = random_arrays(np.random.default_rng(2))
    with pytest.raises(SolverError):
        ngm.NGMWeights({k: v for k, v in arrays.items() if k != "classifier.bias"})
    bad = dict(arrays)
    bad["gnn_layer_1.n_func.0.weight"] = np.zeros((16, 5))
    with pytest.raises(SolverError):
        ngm.NGMWeights(bad)
    bad = dict(arrays)
    bad["classifier.weight"] = np.full((1, 17), np.nan)
    with pytest.raises(SolverError):
        ngm.NGMWeights(bad)
    shapes, data = ngm.encode_weights(arrays)
    with pytest.raises(SolverError):
        ngm.decode_weights(shapes, data[: len(data) // 2])


def test_edge_scale_rescales_only_the_edges() -> None:
    rng = np.random.default_rng(3)
    n1, n2 = 3, 4
    K = random_K(n1 * n2, rng)
    p = AssignmentProblem.dense(K, n1, n2)
    scaled = AssignmentProblem.dense(K * 0.1 + np.diag(np.diag(K) * 0.9), n1, n2)
    np.testing.assert_allclose(ngm.solve(scaled, edge_scale=10.0), ngm.solve(p), atol=1e-9)


@pytest.mark.parametrize("mode", ["paper", "verified"])
def test_ngm_in_the_pipeline_finds_the_true_matches(mode: str) -> None:
    """The shipped weights on seeded drives' scenarios (not their training worlds): most
    submap objects matched right in both modes."""
    right = total = 0
    for seed in (0, 1, 2):
        sc = make_scenario(Family.KITTI, seed=seed, n_map=80, n_sub=10, n_outliers=1)
        out = match(sc.map, sc.submap, match_config(mode=mode, solver={"name": "ngm"},
                                                    affinity={"edge_radius_m": 100.0}))
        got = {m.submap_object: m.map_object for m in out.result.matches}
        for sid, mid in sc.truth.items():
            if mid is not None:
                total += 1
                right += got.get(sid) == mid
    assert right / total >= 0.8, (right, total)


# ------------------------------------------------------------------ training (torch only)


def test_training_network_is_the_numpy_forward_pass() -> None:
    torch = pytest.importorskip("torch", reason="the train extra (torch) is not installed")
    from mergesvc.sim.ngm.net import batch, make_net, state_arrays
    from mergesvc.sim.ngm.problems import problems

    torch.manual_seed(0)
    net = make_net(torch)
    it = problems(3, {"uw-scenario": 1.0, "kitti-scenario": 1.0}, max_pairs=400)
    ps = [next(it) for _ in range(6)]
    with torch.no_grad():
        got = net(batch(torch, ps)).numpy()
    w = ngm.NGMWeights(state_arrays(net))
    ref = np.concatenate([ngm.ngm_soft(p.K.astype(np.float64), p.rows, p.cols, p.n1, p.n2, w)
                          for p in ps])
    np.testing.assert_allclose(got, ref, atol=2e-5)


def test_training_is_seeded_and_reproducible() -> None:
    pytest.importorskip("torch", reason="the train extra (torch) is not installed")
    from mergesvc.sim.ngm import TrainConfig, train

    cfg = TrainConfig(seed=5, n_train=6, n_val=3, epochs=2, batch=3, max_pairs=300,
                      sources={"uw-scenario": 1.0})
    a, b = train(cfg), train(cfg)
    assert set(a.arrays) == set(ngm.param_names(3))
    for k in a.arrays:
        np.testing.assert_array_equal(a.arrays[k], b.arrays[k])
    assert len(a.report["history"]) == 2
    assert 0.0 <= a.report["val_accuracy"]["all"] <= 1.0
    ngm.NGMWeights(a.arrays)  # the numpy pass takes what training writes


def _without_torch(tmp_path) -> dict[str, str]:
    """An environment whose `import torch` fails, as on a machine without the train extra."""
    shadow = tmp_path / "shadow"
    shadow.mkdir(exist_ok=True)
    (shadow / "torch.py").write_text("raise ImportError('no torch here')\n")
    return {**os.environ, "PYTHONPATH": str(shadow)}


def test_solver_train_without_torch_is_one_line(tmp_path) -> None:
    """Without the train extra, `solver train` says how to install it (exit 1)."""
    r = subprocess.run([*CLI, "solver", "train", "--quick", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120, env=_without_torch(tmp_path))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        "error: training the NGM solver needs torch: pip install 'mergesvc[train]'"]


def test_match_with_ngm_needs_no_torch(tmp_path) -> None:
    """`mergesvc match --solver ngm` in both modes on a machine without torch."""
    sc = make_scenario(Family.UNDERWATER, 4)  # what `mergesvc example --seed 4` writes
    (tmp_path / "ex").mkdir()
    (tmp_path / "ex" / "map.json").write_text(sc.map.model_dump_json())
    (tmp_path / "ex" / "submap.json").write_text(sc.submap.model_dump_json())
    truth = sc.truth
    for mode in ("paper", "verified"):
        r = subprocess.run([*CLI, "match", "--map", str(tmp_path / "ex" / "map.json"),
                            "--submap", str(tmp_path / "ex" / "submap.json"), "--mode", mode,
                            "--solver", "ngm", "--json"], capture_output=True, text=True,
                           timeout=120, env=_without_torch(tmp_path))
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout)
        assert out["accepted"], out
        right = [m for m in out["matches"] if truth[m["submap_object"]] == m["map_object"]]
        assert len(right) >= 4, out["matches"]  # 5 objects and a false detection
