"""Tests of mergesvc.sim.uncertainty: ranking loss and MLP gradients against finite differences,
learning on a synthetic degradation model (and not from shuffled labels), determinism, files."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.stats import spearmanr

from mergesvc.errors import ConfigError, DecodeError, InputError, SchemaError
from mergesvc.sim.uncertainty import (
    FORMAT_VERSION,
    FitHistory,
    UncertaintyConfig,
    UncertaintyHead,
    evaluate,
    fit,
    ranking_loss,
    ranking_metrics,
)

D = 384

# --------------------------------------------------------------------------------------------
# Synthetic degradation model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class World:
    """Class prototypes (with a shared component) and a 'murky water' direction b, both (., d)."""

    prototypes_cd: np.ndarray
    murky_d: np.ndarray


def make_world(rng: np.random.Generator, n_classes: int = 10, d: int = D) -> World:
    shared = rng.normal(size=d)
    shared *= 0.62 / np.linalg.norm(shared)
    protos = rng.normal(size=(n_classes, d))
    protos /= np.linalg.norm(protos, axis=1, keepdims=True)
    murky = rng.normal(size=d)
    return World(shared + protos, 5.5 * murky / np.linalg.norm(murky))


def observe(world: World, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n observations (n, d) of random objects and their task loss |obs - x| (n,).

    x = prototype + instance offset, scaled to norm 4-7; a hidden degradation level in [0, 1]
    blends the view towards b (a = level / 2) and adds noise of norm (0.05 + 0.6 level) |x|.
    """
    n_classes, d = world.prototypes_cd.shape
    x = world.prototypes_cd[rng.integers(n_classes, size=n)]
    x = x + rng.normal(size=(n, d)) * 0.55 / np.sqrt(d)
    x *= rng.uniform(4.1, 7.7, size=(n, 1)) / np.linalg.norm(x, axis=1, keepdims=True)
    level = rng.uniform(0.0, 1.0, size=n)
    a = 0.5 * level
    noise = rng.normal(size=(n, d))
    noise *= ((0.05 + 0.6 * level) * np.linalg.norm(x, axis=1))[:, None] / np.linalg.norm(
        noise, axis=1, keepdims=True
    )
    obs = (1.0 - a)[:, None] * x + a[:, None] * world.murky_d + noise
    return obs, np.linalg.norm(obs - x, axis=1)


LEARN_CONFIG = UncertaintyConfig(hidden_sizes=(64,), epochs=15)


@pytest.fixture(scope="module")
def data() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    world = make_world(rng)
    x_train, l_train = observe(world, 3000, rng)
    x_test, l_test = observe(world, 1000, rng)
    return {"x_train": x_train, "l_train": l_train, "x_test": x_test, "l_test": l_test}


@pytest.fixture(scope="module")
def trained(data: dict[str, np.ndarray]) -> tuple[UncertaintyHead, FitHistory]:
    return fit(data["x_train"], data["l_train"], LEARN_CONFIG, np.random.default_rng(1))


# --------------------------------------------------------------------------------------------
# Ranking loss and gradients
# --------------------------------------------------------------------------------------------


def brute_ranking_loss(u: np.ndarray, loss: np.ndarray, m: float) -> float:
    terms = [
        max(0.0, -np.sign(loss[i] - loss[j]) * (u[i] - u[j]) + m)
        for i, j in combinations(range(len(u)), 2)
        if loss[i] != loss[j]
    ]
    return float(np.mean(terms))


def test_ranking_loss_values() -> None:
    # Correct order by more than the margin: no loss; reversed order: margin + gap.
    assert ranking_loss(np.array([2.0, 0.0]), np.array([1.0, 0.0]), 1.0)[0] == 0.0
    loss, grad = ranking_loss(np.array([0.0, 2.0]), np.array([1.0, 0.0]), 1.0)
    assert loss == pytest.approx(3.0)
    np.testing.assert_allclose(grad, [-1.0, 1.0])  # raise the high-loss score, lower the other
    # Ties in the task loss carry no order.
    assert ranking_loss(np.array([0.0, 5.0]), np.array([1.0, 1.0]), 1.0)[0] == 0.0
    rng = np.random.default_rng(3)
    u, l_n = rng.normal(size=9), rng.integers(0, 4, size=9).astype(float)
    assert ranking_loss(u, l_n, 0.7)[0] == pytest.approx(brute_ranking_loss(u, l_n, 0.7))


def test_ranking_loss_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(4)
    u, l_n = rng.normal(size=12), rng.normal(size=12)
    _, grad = ranking_loss(u, l_n, 0.5)
    eps = 1e-6
    numeric = [
        (ranking_loss(u + eps * e, l_n, 0.5)[0] - ranking_loss(u - eps * e, l_n, 0.5)[0])
        / (2 * eps)
        for e in np.eye(len(u))
    ]
    np.testing.assert_allclose(grad, numeric, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    ("hidden", "activation"), [((6, 5), "gelu"), ((6, 5), "relu"), ((7,), "gelu"), ((), "gelu")]
)
def test_head_gradients_match_finite_differences(hidden: tuple[int, ...], activation: str) -> None:
    rng = np.random.default_rng(5)
    config = UncertaintyConfig(hidden_sizes=hidden, activation=activation, margin=2.0)
    emb = rng.normal(size=(10, 8)) + 0.5
    task_loss = rng.normal(size=10)
    # Non-trivial feature standardisation so the whole input path is exercised.
    head = UncertaintyHead.initialise(
        8, config, rng, rng.normal(size=9) * 0.1, rng.uniform(0.5, 2.0, size=9)
    )
    for p in head.parameters:  # non-zero biases too
        p += rng.normal(size=p.shape) * 0.3
    loss, grads = head.gradients(emb, task_loss)
    assert loss > 0.0  # the margin keeps pairs active: the check is not vacuous
    eps = 1e-6
    for p, g in zip(head.parameters, grads, strict=True):
        assert g.shape == p.shape
        numeric = np.zeros_like(p)
        for idx in np.ndindex(p.shape):
            saved = p[idx]
            p[idx] = saved + eps
            plus = head.gradients(emb, task_loss)[0]
            p[idx] = saved - eps
            minus = head.gradients(emb, task_loss)[0]
            p[idx] = saved
            numeric[idx] = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(g, numeric, rtol=1e-5, atol=1e-8)


def test_ranking_metrics_accuracy_matches_brute_force() -> None:
    rng = np.random.default_rng(6)
    for _ in range(5):
        pred = rng.integers(0, 5, size=40).astype(float)  # many ties on both sides
        target = rng.integers(0, 6, size=40).astype(float)
        good = total = 0.0
        for i, j in combinations(range(40), 2):
            if target[i] == target[j]:
                continue
            total += 1
            agree = np.sign(pred[i] - pred[j]) * np.sign(target[i] - target[j])
            good += 1.0 if agree > 0 else (0.5 if agree == 0 else 0.0)
        assert ranking_metrics(pred, target)["accuracy"] == pytest.approx(good / total)
    assert ranking_metrics(np.zeros(5), np.arange(5.0))["accuracy"] == 0.5
    assert ranking_metrics(np.arange(5.0), np.arange(5.0))["accuracy"] == 1.0


# --------------------------------------------------------------------------------------------
# Learning
# --------------------------------------------------------------------------------------------


def test_learns_to_rank_held_out_task_loss(
    data: dict[str, np.ndarray], trained: tuple[UncertaintyHead, FitHistory]
) -> None:
    head, history = trained
    metrics = evaluate(head, data["x_test"], data["l_test"])
    # Measured: spearman 0.948, kendall 0.80, accuracy 0.90 (world seeds 0-2: 0.944-0.948).
    assert metrics["spearman"] > 0.8
    assert metrics["accuracy"] > 0.8
    # Trivial baseline: the embedding norm (measured spearman ~0.1) is far behind.
    baseline = spearmanr(np.linalg.norm(data["x_test"], axis=1), data["l_test"]).statistic
    assert metrics["spearman"] > abs(baseline) + 0.5
    assert history.n_val == 300 and history.n_train == 2700
    assert history.epochs[-1]["train_loss"] < history.epochs[0]["train_loss"]
    s = head.predict(data["x_test"])
    low, high = LEARN_CONFIG.output_range
    assert np.all((s > low) & (s < high))
    # The output map spreads the scores over the range and keeps their order.
    assert np.quantile(s, 0.9) - np.quantile(s, 0.1) > 0.5 * (high - low)
    order = np.argsort(head.score(data["x_test"]))
    assert np.all(np.diff(s[order]) >= 0.0)


def test_shuffled_labels_teach_nothing(data: dict[str, np.ndarray]) -> None:
    rng = np.random.default_rng(2)
    config = LEARN_CONFIG.model_copy(update={"epochs": 30, "patience": 3})
    shuffled = rng.permutation(data["l_train"])
    head, history = fit(data["x_train"], shuffled, config, np.random.default_rng(1))
    # Measured spearman 0.04 (world seeds 0-2: -0.08 to 0.05); the trained head: 0.94.
    assert abs(evaluate(head, data["x_test"], data["l_test"])["spearman"]) < 0.25
    # Validation on shuffled labels never improves for long: early stopping with best weights.
    assert history.stopped_early
    assert len(history.epochs) == history.best_epoch + 1 + config.patience
    val = [e["val_spearman"] for e in history.epochs]
    assert val[history.best_epoch] == max(val)


# --------------------------------------------------------------------------------------------
# Determinism, callback, configuration
# --------------------------------------------------------------------------------------------


def small_problem(seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    emb = rng.normal(size=(200, 16)) + 1.0
    return emb, np.linalg.norm(emb[:, :4], axis=1)


def test_same_seed_same_weights_and_history() -> None:
    emb, loss = small_problem()
    config = {"hidden_sizes": [16, 8], "epochs": 5, "batch_size": 32}
    seen: list[tuple[int, dict[str, float]]] = []
    a, hist_a = fit(
        emb, loss, config, np.random.default_rng(11), on_epoch=lambda e, m: seen.append((e, m))
    )
    b, hist_b = fit(emb, loss, config, np.random.default_rng(11))
    c, _ = fit(emb, loss, config, np.random.default_rng(12))
    for pa, pb in zip(a.parameters, b.parameters, strict=True):
        np.testing.assert_array_equal(pa, pb)
    assert hist_a == hist_b
    assert not all(np.array_equal(pa, pc) for pa, pc in zip(a.parameters, c.parameters))
    assert [e for e, _ in seen] == list(range(len(hist_a.epochs)))
    assert set(seen[0][1]) == {"train_loss", "val_spearman", "val_kendall", "val_accuracy"}


def test_without_validation_runs_every_epoch() -> None:
    emb, loss = small_problem()
    config = UncertaintyConfig(hidden_sizes=(8,), epochs=3, validation_fraction=0.0)
    _, history = fit(emb, loss, config, np.random.default_rng(0))
    assert len(history.epochs) == 3 and history.best_epoch == 2 and history.n_val == 0
    assert set(history.epochs[0]) == {"train_loss"}


def test_config_validation() -> None:
    with pytest.raises(ValidationError):
        UncertaintyConfig(hidden=(3,))  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        UncertaintyConfig(output_range=(0.5, 0.05))
    with pytest.raises(ValidationError):
        UncertaintyConfig(hidden_sizes=(0,))
    emb, loss = small_problem()
    with pytest.raises(ConfigError):
        fit(emb, loss, {"margin": -1.0}, np.random.default_rng(0))
    with pytest.raises(InputError):
        fit(emb[:3], loss[:3], None, np.random.default_rng(0))  # too few for a validation split


# --------------------------------------------------------------------------------------------
# Bad input, files
# --------------------------------------------------------------------------------------------


def test_bad_embeddings_are_schema_errors(trained: tuple[UncertaintyHead, FitHistory]) -> None:
    head, _ = trained
    good = np.ones((2, D))
    with pytest.raises(SchemaError, match="dimension 383"):
        head.predict(np.ones((2, D - 1)))
    with pytest.raises(SchemaError, match="shape"):
        head.predict(np.ones(D))
    for bad_value in (np.nan, np.inf):
        bad = good.copy()
        bad[1, 5] = bad_value
        with pytest.raises(SchemaError, match="non-finite"):
            head.predict(bad)
    with pytest.raises(SchemaError, match="zero-norm"):
        head.predict(np.zeros((1, D)))
    emb, loss = small_problem()
    emb[3, 0] = np.nan
    with pytest.raises(SchemaError, match="non-finite"):
        fit(emb, loss, None, np.random.default_rng(0))
    emb, loss = small_problem()
    loss[0] = np.inf
    with pytest.raises(SchemaError, match="task_loss_n"):
        fit(emb, loss, None, np.random.default_rng(0))


def test_save_load_round_trip(
    tmp_path: Path, data: dict[str, np.ndarray], trained: tuple[UncertaintyHead, FitHistory]
) -> None:
    head, _ = trained
    path = tmp_path / "head.weights"  # no .npz suffix: saved exactly where asked
    head.save(path)
    assert path.exists() and list(tmp_path.iterdir()) == [path]
    loaded = UncertaintyHead.load(path, expected_dim=D)
    assert loaded.config == head.config and loaded.input_dim == D
    np.testing.assert_array_equal(loaded.predict(data["x_test"]), head.predict(data["x_test"]))


def test_load_errors(tmp_path: Path, trained: tuple[UncertaintyHead, FitHistory]) -> None:
    head, _ = trained
    path = tmp_path / "head.npz"
    head.save(path)
    raw = path.read_bytes()

    def expect(exc_type: type[Exception], target: Path, **kwargs: int) -> None:
        with pytest.raises(exc_type) as info:
            UncertaintyHead.load(target, **kwargs)
        assert "\n" not in str(info.value)

    expect(DecodeError, tmp_path / "missing.npz")
    (tmp_path / "garbage.npz").write_bytes(b"not a zip file at all")
    expect(DecodeError, tmp_path / "garbage.npz")
    (tmp_path / "truncated.npz").write_bytes(raw[: len(raw) // 2])
    expect(DecodeError, tmp_path / "truncated.npz")
    expect(SchemaError, path, expected_dim=512)

    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}

    def variant(name: str, **changes: np.ndarray) -> Path:
        target = tmp_path / name
        with target.open("wb") as fh:
            np.savez(fh, **{**arrays, **changes})
        return target

    expect(SchemaError, variant("v.npz", format_version=np.array(FORMAT_VERSION + 1)))
    expect(SchemaError, variant("dim.npz", input_dim=np.array(D + 1)))
    expect(SchemaError, variant("cfg.npz", config_json=np.array('{"margin": -1}')))
    missing = {k: v for k, v in arrays.items() if k != "weight_0"}
    target = tmp_path / "partial.npz"
    with target.open("wb") as fh:
        np.savez(fh, **missing)
    expect(DecodeError, target)
