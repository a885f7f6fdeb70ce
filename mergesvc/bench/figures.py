"""Figures of the benchmark (matplotlib, no display): a map with a submap's correspondences
drawn (green right, red wrong) and node accuracy against subgraph size.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from mergesvc.core.pipeline import MatchOutcome
from mergesvc.core.verify import transform_points
from mergesvc.sim import Scenario


def save_figure(fig: Any, path: Path) -> Path:
    """Lay out, write `path` (its folder made) and free the figure; returns `path`."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_correspondences(
    sc: Scenario, outcome: MatchOutcome, path: Path, title: str = "",
    trajectory_xy_m: np.ndarray | None = None,
) -> Path:
    """Top view of the map (grey), the submap placed by the estimated transform (blue; by the
    true one when rejected), and each returned match as a line: green right, red wrong."""
    m = sc.map.arrays()
    s = sc.submap.arrays()
    fig, ax = plt.subplots(figsize=(8, 6), dpi=110)
    if trajectory_xy_m is not None:
        ax.plot(*trajectory_xy_m.T, color="0.8", lw=0.8, label="vehicle path", zorder=0)
    ax.scatter(*m.position_xyz_m[:, :2].T, s=6, c="0.55", label=f"map ({m.n} objects)")
    fit = outcome.fit
    if fit is not None and fit.T_map_submap is not None and outcome.result.accepted:
        placed = transform_points(fit.T_map_submap, s.position_xyz_m)
        how = "estimated"
    else:
        placed = s.position_xyz_m @ sc.R_map_submap.T + sc.t_map_submap
        how = "true"
    ax.scatter(*placed[:, :2].T, s=22, facecolors="none", edgecolors="tab:blue",
               label=f"submap ({s.n}), {how} transform")
    index = {oid: k for k, oid in enumerate(m.ids)}
    sub_index = {oid: k for k, oid in enumerate(s.ids)}
    n_ok = n_bad = 0
    for match in outcome.result.matches:
        a = placed[sub_index[match.submap_object], :2]
        b = m.position_xyz_m[index[match.map_object], :2]
        ok = sc.is_correct(match.submap_object, match.map_object)
        n_ok += ok
        n_bad += not ok
        ax.plot([a[0], b[0]], [a[1], b[1]], color="tab:green" if ok else "tab:red", lw=1.4)
    ax.plot([], [], color="tab:green", label=f"right ({n_ok})")
    ax.plot([], [], color="tab:red", label=f"wrong ({n_bad})")
    pad = 0.25 * max(float(np.ptp(placed[:, :2], axis=0).max()), 1.0) + 2.0 * m.median_spacing_m
    lo, hi = placed[:, :2].min(axis=0) - pad, placed[:, :2].max(axis=0) + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    verdict = outcome.result.reason.value
    ax.set_title(f"{title} ({verdict})" if title else verdict)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_accuracy_vs_size(
    series: Mapping[str, Mapping[int, float]], path: Path, title: str = "",
    sizes: Sequence[int] | None = None,
) -> Path:
    """Node accuracy (y) against subgraph size (x), one line per labelled series."""
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for label, by_size in series.items():
        xs = sorted(by_size) if sizes is None else [k for k in sizes if k in by_size]
        ax.plot(xs, [by_size[k] for k in xs], marker="o", label=label)
    ax.set_xlabel("submap size (objects)")
    ax.set_ylabel("node accuracy")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(fontsize=8)
    return save_figure(fig, path)
