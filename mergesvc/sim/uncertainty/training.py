"""Evaluation and training of the uncertainty head: ranking metrics (Spearman, Kendall,
pairwise accuracy), `evaluate`, and `fit` (AdamW on the ranking loss, early stopping, output
calibration)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mergesvc.errors import InputError
from mergesvc.sim.uncertainty.config import UncertaintyConfig, _as_config
from mergesvc.sim.uncertainty.head import (
    UncertaintyHead,
    _check_embeddings,
    _check_task_loss,
    embedding_features,
    ranking_loss,
)

log = logging.getLogger(__name__)

# Feature standard deviations below this are treated as constant features (scaled by 1).
_TINY_STD = 1e-12
# Adam constants (Kingma & Ba defaults).
_ADAM_BETA1 = 0.9
_ADAM_BETA2 = 0.999
_ADAM_EPS = 1e-8
# Output calibration: the 10 % and 90 % training-score quantiles land at 10 % and 90 % of the
# output range, i.e. at sigmoid(-ln 9) and sigmoid(+ln 9).
_CALIB_QUANTILES = (0.1, 0.9)
_LN9 = math.log(9.0)


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------


def _pairwise_accuracy(pred_n: np.ndarray, target_n: np.ndarray, tau_b: float) -> float:
    """Fraction of pairs with distinct targets that the prediction orders like the target
    (prediction ties count one half), exact in O(n log n) through Kendall's tau-b:
    C - D = tau_b sqrt((n0 - n1)(n0 - n2)) and C + D = n0 - n1 - n2 + n3."""

    def tied(*cols: np.ndarray) -> int:
        _, counts = np.unique(np.stack(cols, axis=1), axis=0, return_counts=True)
        return int(np.sum(counts * (counts - 1) // 2))

    n = len(pred_n)
    n0 = n * (n - 1) // 2
    n1, n2, n3 = tied(target_n), tied(pred_n), tied(target_n, pred_n)
    ordered = n0 - n1  # pairs with distinct targets
    if ordered == 0:
        return float("nan")
    pred_only_ties = n2 - n3  # tied prediction, distinct target
    if n0 == n2:  # constant prediction: every ordered pair is a tie
        return 0.5
    c_minus_d = tau_b * math.sqrt(float(ordered) * float(n0 - n2))
    c_plus_d = n0 - n1 - n2 + n3
    concordant = 0.5 * (c_plus_d + c_minus_d)
    return float((concordant + 0.5 * pred_only_ties) / ordered)


def ranking_metrics(pred_n: np.ndarray, target_n: np.ndarray) -> dict[str, float]:
    """Spearman rho, Kendall tau-b and pairwise ranking accuracy of pred against target, (n,).

    A constant prediction scores rho = tau = 0 and accuracy 0.5; accuracy is NaN when every
    target is equal (no pair has an order).
    """
    if len(pred_n) < 2:
        raise InputError("ranking metrics need at least 2 samples")
    if np.ptp(pred_n) == 0.0 or np.ptp(target_n) == 0.0:
        rho = tau = 0.0  # undefined; a constant ranking carries no order
    else:
        from scipy.stats import kendalltau, spearmanr  # scipy.stats costs ~0.5 s to import

        rho = float(spearmanr(pred_n, target_n).statistic)
        tau = float(kendalltau(pred_n, target_n).statistic)
    return {
        "spearman": rho,
        "kendall": tau,
        "accuracy": _pairwise_accuracy(pred_n, target_n, tau),
        "n": float(len(pred_n)),
    }


def evaluate(head: UncertaintyHead, embeddings_nd: Any, task_loss_n: Any) -> dict[str, float]:
    """How well the head ranks samples by task loss: spearman, kendall, accuracy, n.

    embeddings_nd: (n, d); task_loss_n: (n,). Uses the raw score u (same order as s, no ties
    from sigmoid saturation). accuracy: fraction of pairs with distinct task loss ordered
    correctly (0.5 is chance).
    """
    score_n = head.score(embeddings_nd)
    loss_n = _check_task_loss(task_loss_n, len(score_n))
    return ranking_metrics(score_n, loss_n)


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------


@dataclass
class FitHistory:
    """What `fit` did: per-epoch metrics, the epoch whose weights were kept, early stop."""

    epochs: list[dict[str, float]] = field(default_factory=list)
    best_epoch: int = -1
    stopped_early: bool = False
    n_train: int = 0
    n_val: int = 0


class _Adam:
    """Adam with decoupled weight decay (AdamW) on the selected parameters."""

    def __init__(self, params: list[np.ndarray], lr: float, decay: list[float]) -> None:
        self.params = params
        self.lr = lr
        self.decay = decay
        self.m = [np.zeros_like(p) for p in params]
        self.v = [np.zeros_like(p) for p in params]
        self.t = 0

    def step(self, grads: list[np.ndarray]) -> None:
        self.t += 1
        c1 = 1.0 - _ADAM_BETA1**self.t
        c2 = 1.0 - _ADAM_BETA2**self.t
        for p, g, m, v, wd in zip(self.params, grads, self.m, self.v, self.decay):
            m *= _ADAM_BETA1
            m += (1.0 - _ADAM_BETA1) * g
            v *= _ADAM_BETA2
            v += (1.0 - _ADAM_BETA2) * g * g
            update = (m / c1) / (np.sqrt(v / c2) + _ADAM_EPS)
            if wd > 0.0:
                update = update + wd * p
            p -= self.lr * update  # in place: p is a view of the head's arrays


def fit(
    embeddings_nd: Any,
    task_loss_n: Any,
    config: UncertaintyConfig | Mapping[str, Any] | None,
    rng: np.random.Generator,
    on_epoch: Callable[[int, dict[str, float]], None] | None = None,
) -> tuple[UncertaintyHead, FitHistory]:
    """Train an uncertainty head to rank embeddings by their task loss.

    embeddings_nd: (n, d) frozen embeddings; task_loss_n: (n,) the backbone's loss on each
    (e.g. distance of the observed embedding from the object's true appearance). rng drives the
    validation split, the initial weights and the minibatch order, so a seed fixes the result.
    With validation_fraction > 0 the weights of the epoch with the best validation score are
    kept and training stops after `patience` epochs without improvement. on_epoch(epoch,
    metrics) is called after each epoch with train_loss and, with validation, val_spearman,
    val_kendall, val_accuracy.
    """
    config = _as_config(config)
    emb = _check_embeddings(embeddings_nd, "embeddings_nd")
    n, d = emb.shape
    loss_n = _check_task_loss(task_loss_n, n)

    # Validation split.
    if n < 2:
        raise InputError(f"training needs at least 2 samples, got {n}")
    n_val = round(config.validation_fraction * n)
    if config.validation_fraction > 0.0 and (n_val < 2 or n - n_val < 2):
        raise InputError(
            f"{n} samples cannot be split into training and validation sets of >= 2 each "
            f"(validation_fraction {config.validation_fraction})"
        )
    order = rng.permutation(n)
    val_idx, train_idx = order[:n_val], order[n_val:]

    # Feature standardisation from the training set only.
    feat_all = embedding_features(emb)
    mean_f = feat_all[train_idx].mean(axis=0)
    std_f = feat_all[train_idx].std(axis=0)
    std_f = np.where(std_f > _TINY_STD, std_f, 1.0)
    x_all = (feat_all - mean_f) / std_f
    x_train, l_train = x_all[train_idx], loss_n[train_idx]
    x_val, l_val = x_all[val_idx], loss_n[val_idx]

    head = UncertaintyHead.initialise(d, config, rng, mean_f, std_f)
    decay = [config.weight_decay if p.ndim == 2 else 0.0 for p in head.parameters]
    opt = _Adam(head.parameters, config.learning_rate, decay)

    history = FitHistory(n_train=len(train_idx), n_val=n_val)
    best_score = -math.inf
    best_params: list[np.ndarray] | None = None
    stale = 0
    n_train = len(train_idx)
    for epoch in range(config.epochs):
        perm = rng.permutation(n_train)
        total, batches = 0.0, 0
        for start in range(0, n_train, config.batch_size):
            batch = perm[start : start + config.batch_size]
            if len(batch) < 2:
                continue  # a lone sample has no pair
            u, cache = head._forward(x_train[batch])
            loss, grad_u = ranking_loss(u, l_train[batch], config.margin)
            opt.step(head._backward(cache, grad_u))
            total += loss
            batches += 1
        metrics: dict[str, float] = {"train_loss": total / max(batches, 1)}
        if n_val:
            val = ranking_metrics(head._forward(x_val)[0], l_val)
            metrics.update({f"val_{k}": v for k, v in val.items() if k != "n"})
            score = val[config.early_stopping_metric]
            if score > best_score:
                best_score, stale = score, 0
                best_params = [p.copy() for p in head.parameters]
                history.best_epoch = epoch
            else:
                stale += 1
        else:
            history.best_epoch = epoch
        history.epochs.append(metrics)
        log.debug("uncertainty head epoch %d: %s", epoch, metrics)
        if on_epoch is not None:
            on_epoch(epoch, dict(metrics))
        if n_val and stale >= config.patience:
            history.stopped_early = True
            break

    if best_params is not None:
        for p, best in zip(head.parameters, best_params):
            p[...] = best

    # Spread the training scores over the output range (monotone, ranking unchanged).
    q_lo, q_hi = np.quantile(head._forward(x_train)[0], _CALIB_QUANTILES)
    if q_hi - q_lo > 1e-12:
        head.score_center = float(0.5 * (q_lo + q_hi))
        head.score_scale = float((q_hi - q_lo) / (2.0 * _LN9))
    else:
        head.score_center, head.score_scale = float(q_lo), 1.0
    return head, history


__all__ = ["FitHistory", "evaluate", "fit", "ranking_metrics"]
