"""Worlds of any size for `bench scale`: a flat street-like layout of n objects with DINO-like
appearance and look-alike twins, and submaps of any size cut from it as a vehicle would see it.

Vectorised and chunked (a million objects in seconds, float32 embeddings). Map objects are
fused estimates (a few views each, isotropic variance s / n_obs); a submap re-observes the
objects nearest a point (new views, positions with noise, in the vehicle's frame: a random
yaw and offset) plus false detections at random places in its window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mergesvc.core.arrays import ObjectArrays
from mergesvc.sim.appearance import class_centroids

_CHUNK = 65_536


@dataclass(frozen=True)
class ScaleWorld:
    """Truth of a large world: appearances (n, d) float32, positions (n, 3), the map built
    from it, and twin_of (n,) the object each look-alike copies (-1 for originals)."""

    truth_nd: np.ndarray
    position_xyz_m: np.ndarray
    map: ObjectArrays
    twin_of: np.ndarray
    spacing_m: float


@dataclass(frozen=True)
class ScaleCase:
    """A submap cut from a ScaleWorld: the arrays and truth (n_sub,) map row or -1."""

    submap: ObjectArrays
    truth: np.ndarray


def _views(truth: np.ndarray, s: np.ndarray, view_noise: float, rng: np.random.Generator
           ) -> np.ndarray:
    """One fused estimate per row of truth (k, d) with noise of per-dimension variance
    view_noise^2 s |x|^2 / d (Appearance.fused's model for one equivalent view)."""
    d = truth.shape[1]
    norm = np.linalg.norm(truth, axis=1, keepdims=True)
    sd = view_noise * np.sqrt(s)[:, None] * norm / np.sqrt(d)
    return (truth + rng.standard_normal(truth.shape, dtype=np.float32) * sd).astype(np.float32)


def scale_world(
    n: int, dim: int, seed: int, dino_kd: np.ndarray | None = None, n_classes: int = 16,
    lookalikes: float = 0.1, spacing_m: float = 8.0, instance_scale: float = 0.6,
    view_noise: float = 1.8,
) -> ScaleWorld:
    """n objects in a square of side sqrt(n) * spacing_m (about spacing_m apart), 1 m of
    height noise; a `lookalikes` share of them twins of another object (its appearance
    perturbed by 0.35 of an instance spread, somewhere else)."""
    rng = np.random.default_rng([seed, 26])
    C = class_centroids(n_classes, dim, rng, dino_kd).astype(np.float32)
    side = np.sqrt(n) * spacing_m
    xyz = np.column_stack([rng.uniform(0, side, n), rng.uniform(0, side, n),
                           rng.normal(0.0, 1.0, n)])
    truth = np.empty((n, dim), dtype=np.float32)
    cls = rng.integers(0, n_classes, n)
    for lo in range(0, n, _CHUNK):
        hi = min(n, lo + _CHUNK)
        x = C[cls[lo:hi]] + instance_scale * rng.standard_normal((hi - lo, dim),
                                                                 dtype=np.float32) / np.sqrt(dim)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        truth[lo:hi] = x * rng.uniform(4.1, 7.7, size=(hi - lo, 1)).astype(np.float32)
    twin_of = np.full(n, -1, dtype=np.int64)
    k = int(lookalikes * n)
    if k:
        copies = rng.choice(n, size=k, replace=False)
        sources = rng.choice(np.setdiff1d(np.arange(n), copies), size=k)
        pert = 0.35 * instance_scale * rng.standard_normal((k, dim), dtype=np.float32)
        base = truth[sources]
        x = base / np.linalg.norm(base, axis=1, keepdims=True) + pert / np.sqrt(dim)
        truth[copies] = x / np.linalg.norm(x, axis=1, keepdims=True) * np.linalg.norm(
            base, axis=1, keepdims=True)
        twin_of[copies] = sources
    n_obs = rng.integers(2, 8, n)
    s = rng.uniform(0.05, 0.3, n) / n_obs
    emb = np.empty_like(truth)
    for lo in range(0, n, _CHUNK):
        hi = min(n, lo + _CHUNK)
        emb[lo:hi] = _views(truth[lo:hi], s[lo:hi], view_noise, rng)
    arr = ObjectArrays([f"m{i}" for i in range(n)], xyz, emb, s, n_obs)
    return ScaleWorld(truth, xyz, arr, twin_of, spacing_m)


def cut_submap(world: ScaleWorld, n_sub: int, seed: int, n_false: int | None = None,
               position_sigma_m: float = 0.2, view_noise: float = 1.8) -> ScaleCase:
    """The n_sub objects nearest a random map object, seen again (new views, positions with
    noise), in a vehicle frame (random yaw and offset), plus n_false false detections (default
    one per ten objects, at least one from 4 objects on) among them."""
    rng = np.random.default_rng([seed, 27, n_sub])
    m = world.map
    centre = world.position_xyz_m[rng.integers(m.n)]
    _, rows = m.kdtree.query(centre, k=min(n_sub, m.n))
    rows = np.sort(np.atleast_1d(rows))
    if n_false is None:
        n_false = 0 if n_sub < 4 else max(1, n_sub // 10)
    s = rng.uniform(0.05, 0.4, len(rows))
    emb = _views(world.truth_nd[rows], s, view_noise, rng)
    xyz = world.position_xyz_m[rows] + rng.normal(0.0, position_sigma_m, (len(rows), 3))
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    fake = rng.uniform(lo, hi, (n_false, 3))
    fake_truth = world.truth_nd[rng.integers(m.n, size=n_false)]
    fake_truth = fake_truth + 0.6 * rng.standard_normal(fake_truth.shape).astype(
        np.float32) * np.linalg.norm(fake_truth, axis=1, keepdims=True) / np.sqrt(m.dim)
    fs = rng.uniform(0.05, 0.4, n_false)
    emb = np.vstack([emb, _views(fake_truth.astype(np.float32), fs, view_noise, rng)])
    xyz = np.vstack([xyz, fake])
    truth = np.concatenate([rows, np.full(n_false, -1)])
    order = rng.permutation(len(truth))
    yaw = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                  [0.0, 0.0, 1.0]])
    local = (xyz[order] - xyz.mean(axis=0)) @ R.T + rng.normal(0.0, 20.0, 3)
    sub = ObjectArrays([f"s{i}" for i in range(len(order))], local, emb[order],
                       np.concatenate([s, fs])[order], np.ones(len(order), dtype=np.int64))
    return ScaleCase(sub, truth[order])


__all__ = ["ScaleCase", "ScaleWorld", "cut_submap", "scale_world"]
