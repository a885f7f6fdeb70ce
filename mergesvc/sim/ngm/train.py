"""Training the NGM solver (`mergesvc solver train`): problems from the project's generators
(problems.py), NGM's permutation loss (binary cross-entropy of the soft assignment against the
truth), Adam, the epoch with the best validation accuracy kept.

Seeded and reproducible: every random draw comes from the seed, torch runs on `threads` threads
(one by default: results then do not depend on the machine's thread pool) with deterministic
algorithms. Needs torch (the `train` extra); ConfigError says how to install it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from mergesvc.core.config import MatchConfig, match_config
from mergesvc.errors import ConfigError, InputError
from mergesvc.sim.ngm.net import batch, make_net, state_arrays
from mergesvc.sim.ngm.problems import SOURCES, NGMProblem, problems

INSTALL_HINT = "pip install 'mergesvc[train]'"


@dataclass(frozen=True)
class TrainConfig:
    """What `solver train` does. `quick` is a smoke test (seconds)."""

    seed: int = 0
    n_train: int = 900  # training problems
    n_val: int = 150  # validation problems, from worlds the training never sees
    epochs: int = 20
    batch: int = 16  # problems per optimiser step
    lr: float = 3e-3
    lr_decay_at: float = 0.6  # fraction of the epochs after which the rate drops tenfold
    max_pairs: int = 1600  # paper formulation: the map cropped to this many pairs
    p_paper: float = 0.5  # share of problems in the paper formulation (else verified)
    channels: tuple[int, ...] = (16, 16, 16)  # pygmtools' NGM
    threads: int = 1
    # relative frequency of each kind of world; a pool run yields 8 problems, a drive or a
    # harbour pool 4, a drawn scenario 1: about 25 % pool runs, 12 % drives, 6 % drawn pool
    # scenarios, 31 % drawn street scenarios (look-alikes, maps up to 1,000), 25 % harbours
    sources: dict[str, float] = field(default_factory=lambda: {
        "uw-run": 1.0, "drive": 1.0, "uw-scenario": 2.0, "kitti-scenario": 10.0, "pool": 2.0})

    @classmethod
    def quick(cls, seed: int = 0) -> TrainConfig:
        return cls(seed=seed, n_train=24, n_val=8, epochs=2, batch=8, max_pairs=600,
                   sources={"uw-run": 1.0, "uw-scenario": 1.0, "kitti-scenario": 1.0,
                            "pool": 1.0})

    def check(self) -> None:
        for name in ("n_train", "n_val", "epochs", "batch", "max_pairs", "threads"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        unknown = set(self.sources) - set(SOURCES)
        if unknown or not self.sources or min(self.sources.values()) < 0:
            raise InputError(f"sources must weigh some of {', '.join(SOURCES)}")


@dataclass
class TrainResult:
    arrays: dict[str, np.ndarray]  # the best epoch's parameters (NGMWeights takes them)
    report: dict[str, Any]


def require_torch() -> Any:
    """The torch module, or ConfigError saying how to install it."""
    try:
        import torch
    except ImportError as exc:
        raise ConfigError(f"training the NGM solver needs torch: {INSTALL_HINT}") from exc
    return torch


def draw(cfg: TrainConfig, n: int, stream: int, base: MatchConfig | None = None
         ) -> list[NGMProblem]:
    """n problems with at least one true match among their pairs, formulated with `base`'s
    matching settings (default: the defaults)."""
    it = problems(cfg.seed, cfg.sources, cfg.p_paper, cfg.max_pairs, base, stream)
    out: list[NGMProblem] = []
    while len(out) < n:
        p = next(it)
        if p.matchable:
            out.append(p)
    return out


def accuracy(p: NGMProblem, soft_m: np.ndarray) -> float:
    """Hungarian on the soft assignment, every row matched (paper mode's hardening): right
    rows over rows whose true match is among the pairs."""
    W = np.full((p.n1, p.n2), -1e9)
    W[p.rows, p.cols] = soft_m
    r, c = linear_sum_assignment(W, maximize=True)
    T = np.zeros((p.n1, p.n2))
    T[p.rows, p.cols] = p.target
    return float(T[r, c].sum() / max(p.matchable, 1))


def _evaluate(torch: Any, net: Any, ps: Sequence[NGMProblem], size: int) -> list[float]:
    accs = []
    with torch.no_grad():
        for k in range(0, len(ps), size):
            chunk = ps[k : k + size]
            out = net(batch(torch, chunk)).numpy()
            at = 0
            for p in chunk:
                accs.append(accuracy(p, out[at : at + p.m]))
                at += p.m
    return accs


def _by(ps: Sequence[NGMProblem], accs: Sequence[float]) -> dict[str, float]:
    groups: dict[str, list[float]] = {}
    for p, a in zip(ps, accs):
        groups.setdefault(f"{p.kind}/{p.source}", []).append(a)
        groups.setdefault(p.kind, []).append(a)
    return {k: round(float(np.mean(v)), 4) for k, v in sorted(groups.items())}


def train(cfg: TrainConfig, echo: Callable[[str], Any] = lambda _m: None,
          base: MatchConfig | None = None) -> TrainResult:
    """Generate the problems (formulated with `base`'s matching settings, default: the
    defaults), train, keep the best epoch. See the module docstring."""
    cfg.check()
    torch = require_torch()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    torch.use_deterministic_algorithms(True)
    torch.set_flush_denormal(True)  # Sinkhorn's tiny masses otherwise slow every layer down
    t0 = time.perf_counter()
    train_ps, val_ps = draw(cfg, cfg.n_train, 0, base), draw(cfg, cfg.n_val, 1, base)
    t_gen = time.perf_counter() - t0
    echo(f"{len(train_ps)} training and {len(val_ps)} validation problems in {t_gen:.0f} s")
    node_only = [accuracy(p, np.diag(p.K)) for p in val_ps]  # node affinity + Hungarian
    net = make_net(torch, cfg.channels)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    decay = max(1, round(cfg.epochs * cfg.lr_decay_at))
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=decay, gamma=0.1)
    rng = np.random.default_rng([cfg.seed, 28, 2])
    batches = [train_ps[k : k + cfg.batch] for k in range(0, len(train_ps), cfg.batch)]
    tensors = [(batch(torch, b), torch.from_numpy(np.concatenate([p.target for p in b])),
                sum(p.matchable for p in b)) for b in batches]
    history, best = [], (-1.0, None, -1)
    for epoch in range(cfg.epochs):
        net.train()
        losses = []
        for k in rng.permutation(len(tensors)):
            b, target, rows = tensors[k]
            soft = net(b).clamp(1e-7, 1 - 1e-7)
            loss = torch.nn.functional.binary_cross_entropy(soft, target, reduction="sum") / rows
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        sched.step()
        net.eval()
        val = float(np.mean(_evaluate(torch, net, val_ps, cfg.batch)))
        history.append({"epoch": epoch, "loss": round(float(np.mean(losses)), 5),
                        "val_accuracy": round(val, 4)})
        echo(f"epoch {epoch}: loss {np.mean(losses):.4f}, validation accuracy {val:.4f}")
        if val > best[0]:
            best = (val, state_arrays(net), epoch)
    arrays = best[1]
    net.load_state_dict({k: torch.from_numpy(v) for k, v in arrays.items()})
    net.eval()
    val_accs = _evaluate(torch, net, val_ps, cfg.batch)
    report = {
        "config": {**asdict(cfg), "channels": list(cfg.channels)},
        "settings": match_config(base).model_dump(mode="json"),
        "torch": torch.__version__,
        "problems": {"train": _counts(train_ps), "val": _counts(val_ps)},
        "history": history,
        "best_epoch": best[2],
        "val_accuracy": _by(val_ps, val_accs) | {"all": round(float(np.mean(val_accs)), 4)},
        "val_accuracy_node_only": _by(val_ps, node_only)
        | {"all": round(float(np.mean(node_only)), 4)},
        "generate_s": round(t_gen, 1),
        "elapsed_s": round(time.perf_counter() - t0, 1),
    }
    return TrainResult(arrays, report)


def _counts(ps: Sequence[NGMProblem]) -> dict[str, int]:
    out: dict[str, int] = {}
    for p in ps:
        out[f"{p.kind}/{p.source}"] = out.get(f"{p.kind}/{p.source}", 0) + 1
    return dict(sorted(out.items()))


__all__ = ["INSTALL_HINT", "TrainConfig", "TrainResult", "accuracy", "draw", "require_torch",
           "train"]
