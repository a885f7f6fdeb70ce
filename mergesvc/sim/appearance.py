"""Appearance of the generalization worlds (worlds.py): class centroids with the structure of
real DINO centroids in any dimension, object instances, views of varying quality fused as a
tracker would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# ============================================================================================
# Appearance: class centroids with DINO structure in any dimension, instances, fused views
# ============================================================================================


def class_centroids(
    n_classes: int, dim: int, rng: np.random.Generator, dino_kd: np.ndarray | None = None
) -> np.ndarray:
    """(n_classes, dim) unit class centroids. From real centroids (k, d0): their exact pairwise
    cosines carried into `dim` dimensions by a random orthonormal embedding of their span;
    classes beyond k are mixtures of two real ones plus a fresh direction. Without real data:
    a shared direction plus random prototypes (pairwise cosine ~0.3)."""
    if dino_kd is None:
        shared = rng.normal(size=dim)
        shared /= np.linalg.norm(shared)
        raw = 0.6 * shared + rng.normal(size=(n_classes, dim)) / np.sqrt(dim)
        return raw / np.linalg.norm(raw, axis=1, keepdims=True)
    U = dino_kd / np.linalg.norm(dino_kd, axis=1, keepdims=True)
    k = len(U)
    Q, _ = np.linalg.qr(U.T)  # (d0, k) orthonormal basis of their span
    A = U @ Q  # (k, k) coordinates: A A^T = U U^T, the real cosines
    E, _ = np.linalg.qr(rng.normal(size=(dim, k)))  # (dim, k) random orthonormal embedding
    base = A @ E.T  # (k, dim)
    if n_classes <= k:
        return base[rng.permutation(k)[:n_classes]]
    extra = []
    for _ in range(n_classes - k):
        i, j = rng.choice(k, size=2, replace=False)
        w = rng.uniform(0.2, 0.8)
        fresh = rng.normal(size=dim)
        fresh /= np.linalg.norm(fresh)
        v = w * base[i] + (1 - w) * base[j] + rng.uniform(0.5, 1.2) * fresh
        extra.append(v / np.linalg.norm(v))
    return np.vstack([base, np.array(extra)])


@dataclass(frozen=True)
class Appearance:
    """How objects look: class centroids, instance spread, view noise (per unit of s)."""

    centroids_cd: np.ndarray  # (c, dim) unit
    instance_scale: float = 0.6  # relative norm of an instance's offset from its class
    view_noise: float = 1.8  # noise norm of a view of quality s: view_noise * sqrt(s) * |x|

    @property
    def dim(self) -> int:
        return self.centroids_cd.shape[1]

    def instances(self, classes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(n, dim) true appearances, norms 4.1-7.7 like the real DINO centroids."""
        n, d = len(classes), self.dim
        x = self.centroids_cd[classes] + self.instance_scale * rng.normal(size=(n, d)) / np.sqrt(d)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        return x * rng.uniform(4.1, 7.7, size=(n, 1))

    def fused(
        self, truth_d: np.ndarray, s_views: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, float]:
        """Views of one object with qualities s_views (n,), fused by inverse-variance weights.
        Each view's noise has per-dimension variance view_noise^2 s |x|^2 / dim; the tracked
        variance is 1 / sum(1 / s) (s / n for n views of equal s). Returns (mean (dim,), var)."""
        d = self.dim
        norm = float(np.linalg.norm(truth_d))
        gain = rng.uniform(0.85, 1.15, size=(len(s_views), 1))
        sd = self.view_noise * np.sqrt(s_views)[:, None] * norm / np.sqrt(d)
        views = gain * truth_d + rng.normal(size=(len(s_views), d)) * sd
        w = 1.0 / s_views
        return (w[:, None] * views).sum(axis=0) / w.sum(), float(1.0 / w.sum())


def view_quality(range_frac: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Image uncertainty s (n,) in [0.04, 0.6]: worse far away, occasionally bad anyway."""
    r = np.asarray(range_frac, dtype=np.float64)
    return np.clip(0.04 + 0.3 * r + 0.25 * rng.beta(1.5, 6.0, size=r.shape), 0.04, 0.6)


__all__ = ["Appearance", "class_centroids", "view_quality"]
