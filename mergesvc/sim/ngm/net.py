"""The NGM network in torch, for training only: the computation of the numpy forward pass in
core/solvers/ngm.py (tests check one against the other) on a batch of problems at once, with
parameters named as pygmtools and that module name them. torch comes from the `train` extra
and is handed in by the caller.

A batch is its problems side by side: K block-diagonal (sparse), the pairs of all problems in
one vector, and Sinkhorn's line and column sums taken per line and column of each problem.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mergesvc.core.solvers.ngm import EDGE_MIN, SK_ITERS, SK_TAU


def make_net(torch: Any, channels: tuple[int, ...] = (16, 16, 16), sk_emb: int = 1) -> Any:
    """pygmtools' NGM_Net as a torch module (default initialisation, seeded by the caller)."""
    nn = torch.nn

    def mlp(n_in: int, n_out: int) -> Any:
        return nn.Sequential(nn.Linear(n_in, n_out), nn.ReLU(), nn.Linear(n_out, n_out),
                             nn.ReLU())

    class Layer(nn.Module):
        def __init__(self, n_in: int, n_out: int) -> None:
            super().__init__()
            self.n_func = mlp(n_in, n_out)
            self.n_self_func = mlp(n_in, n_out)
            self.classifier = nn.Linear(n_out, sk_emb)

    class Net(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            width = 1
            for i, c in enumerate(channels):
                setattr(self, f"gnn_layer_{i}", Layer(width, c))
                width = c + sk_emb
            self.classifier = nn.Linear(width, 1)
            self.n_layers = len(channels)

        def forward(self, b: dict[str, Any]) -> Any:
            """b: a batch (see batch()). Returns the soft assignment of every pair (M,)."""
            x = b["x0"]
            for i in range(self.n_layers):
                layer = getattr(self, f"gnn_layer_{i}")
                x2 = b["inv_deg"] * (b["K"] @ layer.n_func(x)) + layer.n_self_func(x)
                x_sk = sinkhorn(torch, layer.classifier(x2)[:, 0], b)
                x = torch.cat([x2, x_sk[:, None]], dim=1)
            return sinkhorn(torch, self.classifier(x)[:, 0], b)

    return Net()


def sinkhorn(torch: Any, s: Any, b: dict[str, Any], tau: float = SK_TAU,
             iters: int = SK_ITERS) -> Any:
    """core/solvers/ngm.sinkhorn on every problem of the batch: s (M,) -> (M,)."""
    line, col = b["line"], b["col"]
    S = s / tau
    top = torch.full((b["n_lines"],), -torch.inf, dtype=S.dtype).scatter_reduce(
        0, line, S.detach(), reduce="amax")  # cancelled by the first line step: no gradient
    X = torch.exp(S - top[line])
    d = b["dummy_init"]
    for it in range(iters):
        if it % 2 == 0:
            X = X / torch.zeros(b["n_lines"], dtype=X.dtype).index_add(0, line, X)[line]
            d = d / torch.zeros(b["n_problems"], dtype=X.dtype).index_add(
                0, b["col_problem"], d)[b["col_problem"]]
        else:
            c = torch.zeros(b["n_cols"], dtype=X.dtype).index_add(0, col, X) \
                + b["col_dummies"] * d
            X = X / c[col]
            d = d / c
    return X


def batch(torch: Any, problems: Sequence[Any]) -> dict[str, Any]:
    """Problems (K (m, m), rows, cols, n1, n2 each) side by side as the network takes them.

    Sinkhorn's lines are each problem's shorter side (pygmtools transposes when n1 > n2).
    The first embedding is diag(K) scaled to mean 1 per problem, as the numpy pass does."""
    ki, kj, kv, inv_deg, x0 = [], [], [], [], []
    line, col, col_problem, col_dummies, dummy_init = [], [], [], [], []
    at = n_lines = n_cols = 0
    for k, p in enumerate(problems):
        K = np.asarray(p.K, dtype=np.float32)
        i, j = np.nonzero(np.abs(K) >= EDGE_MIN)  # the numpy pass's association graph
        ki.append(i + at)
        kj.append(j + at)
        kv.append(K[i, j])
        deg = np.bincount(i, minlength=p.m)
        inv_deg.append(np.divide(1.0, deg, out=np.zeros(p.m), where=deg > 0))
        x = np.diag(K).astype(np.float64)
        mean = float(x.mean())
        x0.append(x / mean if mean > 1e-12 else np.ones(p.m))
        short, long_ = (p.rows, p.cols) if p.n1 <= p.n2 else (p.cols, p.rows)
        n_short, n_long = min(p.n1, p.n2), max(p.n1, p.n2)
        line.append(short + n_lines)
        col.append(long_ + n_cols)
        col_problem.append(np.full(n_long, k))
        col_dummies.append(np.full(n_long, float(n_long - n_short)))
        dummy_init.append(np.full(n_long, 1.0 / n_long))
        at, n_lines, n_cols = at + p.m, n_lines + n_short, n_cols + n_long

    def t(parts: list[np.ndarray], dtype: Any) -> Any:
        return torch.from_numpy(np.concatenate(parts)).to(dtype)

    idx = torch.stack([t(ki, torch.int64), t(kj, torch.int64)])
    K = torch.sparse_coo_tensor(idx, t(kv, torch.float32), (at, at),
                                check_invariants=False).coalesce()  # built valid above
    return {
        "K": K, "inv_deg": t(inv_deg, torch.float32)[:, None],
        "x0": t(x0, torch.float32)[:, None],
        "line": t(line, torch.int64), "col": t(col, torch.int64),
        "col_problem": t(col_problem, torch.int64), "col_dummies": t(col_dummies, torch.float32),
        "dummy_init": t(dummy_init, torch.float32),
        "n_lines": n_lines, "n_cols": n_cols, "n_problems": len(problems),
    }


def state_arrays(net: Any) -> dict[str, np.ndarray]:
    """The network's parameters as numpy arrays by name (what NGMWeights takes)."""
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in net.state_dict().items()}


def load_arrays(torch: Any, net: Any, arrays: dict[str, np.ndarray]) -> None:
    net.load_state_dict({k: torch.from_numpy(np.asarray(v, dtype=np.float32))
                         for k, v in arrays.items()})


__all__ = ["batch", "load_arrays", "make_net", "sinkhorn", "state_arrays"]
