"""The uncertainty head: input checks and features, the pairwise ranking loss, and
`UncertaintyHead` (the MLP, its map of the score to an uncertainty s, its weight file)."""

from __future__ import annotations

import math
import os
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from mergesvc.errors import ConfigError, DecodeError, SchemaError
from mergesvc.sim.uncertainty.config import UncertaintyConfig, _as_config

#: Version of the .npz weight file written by `UncertaintyHead.save`.
FORMAT_VERSION = 1

# Norms at or below this are a zero embedding (no direction to normalise).
_TINY_NORM = 1e-12
# sqrt(2 / pi), for the tanh approximation of GELU.
_GELU_C = math.sqrt(2.0 / math.pi)


# --------------------------------------------------------------------------------------------
# Input validation and features
# --------------------------------------------------------------------------------------------


def _check_embeddings(value: Any, name: str, dim: int | None = None) -> np.ndarray:
    """Float64 (n, d) copy; SchemaError for a wrong shape or dimension, NaN/inf or zero rows."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{name} must be numeric: {exc}") from exc
    if arr.ndim != 2 or arr.shape[1] == 0:
        raise SchemaError(f"{name} must have shape (n, d) with d >= 1, got {arr.shape}")
    if dim is not None and arr.shape[1] != dim:
        raise SchemaError(f"{name} has dimension {arr.shape[1]}, the head expects {dim}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise SchemaError(f"{name} has non-finite values (NaN/inf) in {int(bad.sum())} row(s)")
    zero = np.linalg.norm(arr, axis=1) <= _TINY_NORM
    if zero.any():
        raise SchemaError(f"{name} has {int(zero.sum())} zero-norm row(s)")
    return arr


def _check_task_loss(value: Any, n: int) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"task_loss_n must be numeric: {exc}") from exc
    if arr.shape != (n,):
        raise SchemaError(f"task_loss_n must have shape ({n},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise SchemaError("task_loss_n has non-finite values (NaN/inf)")
    return arr


def embedding_features(embeddings_nd: np.ndarray) -> np.ndarray:
    """Scale-free input features: [e / |e|, ln |e|], (n, d + 1).

    The unit direction carries the appearance and the log-norm the overall magnitude (which
    brightness and degradation change); together they lose nothing of e. Rows must be non-zero.
    """
    norm_n = np.linalg.norm(embeddings_nd, axis=1)
    return np.concatenate([embeddings_nd / norm_n[:, None], np.log(norm_n)[:, None]], axis=1)


# --------------------------------------------------------------------------------------------
# Ranking loss
# --------------------------------------------------------------------------------------------


def ranking_loss(
    score_n: np.ndarray, task_loss_n: np.ndarray, margin: float
) -> tuple[float, np.ndarray]:
    """Mean pairwise ranking loss over all pairs of a minibatch, and its gradient (n,).

    L_ij = max(0, -sign(l_i - l_j) * (u_i - u_j) + m) (Yoo & Kweon eq. 2; Kirchhof et al.):
    the score u must exceed the other's by the margin m when its task loss l is larger. Pairs
    with equal task loss carry no order and are skipped. Returns (0, zeros) when no pair is
    ordered.
    """
    sign_nn = np.sign(task_loss_n[:, None] - task_loss_n[None, :])  # antisymmetric, 0 on ties
    n_pairs = int(np.count_nonzero(sign_nn))  # ordered pairs (each unordered pair twice)
    if n_pairs == 0:
        return 0.0, np.zeros_like(score_n)
    hinge_nn = margin - sign_nn * (score_n[:, None] - score_n[None, :])
    active_nn = (hinge_nn > 0.0) & (sign_nn != 0.0)  # symmetric
    loss = float(np.sum(hinge_nn, where=active_nn) / n_pairs)
    # dL/du_k = -(1/P) sum_j a_kj s_kj + (1/P) sum_i a_ik s_ik = -(2/P) sum_j a_kj s_kj,
    # since a is symmetric and s antisymmetric.
    grad_n = -2.0 / n_pairs * np.sum(np.where(active_nn, sign_nn, 0.0), axis=1)
    return loss, grad_n


# --------------------------------------------------------------------------------------------
# Head
# --------------------------------------------------------------------------------------------


def _activate(kind: str, z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Activation h(z) and, for GELU, t = tanh(c (z + 0.044715 z^3)) reused by the gradient."""
    if kind == "relu":
        return np.maximum(z, 0.0), None
    t = np.tanh(_GELU_C * (z + 0.044715 * z * z * z))
    return 0.5 * z * (1.0 + t), t


def _activate_grad(kind: str, z: np.ndarray, t: np.ndarray | None) -> np.ndarray:
    """dh/dz given z and the t returned by `_activate`."""
    if kind == "relu" or t is None:
        return (z > 0.0).astype(z.dtype)
    return 0.5 * (1.0 + t) + 0.5 * z * (1.0 - t * t) * _GELU_C * (1.0 + 3 * 0.044715 * z * z)


class UncertaintyHead:
    """MLP u(e) on embedding features, and the map of the score u to an uncertainty s.

    Layers: standardised features (d + 1,) -> [Linear -> activation] x len(hidden_sizes) ->
    Linear -> scalar score u. The ranking loss acts on u. `predict` maps u monotonically onto
    the configured output range: s = low + (high - low) * sigmoid((u - center) / scale), where
    center and scale are set after training so the 10 % / 90 % training-score quantiles land at
    10 % / 90 % of the range. The ranking is therefore exactly that of u; the absolute level of s
    is a spread-out rank score, not a calibrated variance.

    weights: list of (fan_in, fan_out) matrices; biases: list of (fan_out,) vectors;
    feature_mean_f / feature_std_f: (d + 1,) standardisation of the features.
    """

    def __init__(
        self,
        input_dim: int,
        config: UncertaintyConfig,
        weights: list[np.ndarray],
        biases: list[np.ndarray],
        feature_mean_f: np.ndarray,
        feature_std_f: np.ndarray,
        score_center: float = 0.0,
        score_scale: float = 1.0,
    ) -> None:
        try:
            weights = [np.asarray(w, dtype=np.float64) for w in weights]
            biases = [np.asarray(b, dtype=np.float64) for b in biases]
            feature_mean_f = np.asarray(feature_mean_f, dtype=np.float64)
            feature_std_f = np.asarray(feature_std_f, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise SchemaError(f"head parameters must be numeric arrays: {exc}") from exc
        sizes = [input_dim + 1, *config.hidden_sizes, 1]
        if len(weights) != len(sizes) - 1 or len(biases) != len(sizes) - 1:
            raise SchemaError(
                f"head needs {len(sizes) - 1} layers for hidden_sizes {config.hidden_sizes}, "
                f"got {len(weights)} weight and {len(biases)} bias arrays"
            )
        for k, (w, b) in enumerate(zip(weights, biases)):
            if w.shape != (sizes[k], sizes[k + 1]) or b.shape != (sizes[k + 1],):
                raise SchemaError(
                    f"layer {k}: expected weight {(sizes[k], sizes[k + 1])} and bias "
                    f"{(sizes[k + 1],)}, got {w.shape} and {b.shape}"
                )
        f = input_dim + 1
        if feature_mean_f.shape != (f,) or feature_std_f.shape != (f,):
            raise SchemaError(f"feature statistics must have shape ({f},)")
        arrays = [*weights, *biases, feature_mean_f, feature_std_f]
        if not all(np.isfinite(a).all() for a in arrays):
            raise SchemaError("head parameters have non-finite values")
        if not (np.all(feature_std_f > 0.0) and score_scale > 0.0 and math.isfinite(score_center)):
            raise SchemaError("feature std and score scale must be > 0, score center finite")
        self.input_dim = int(input_dim)
        self.config = config
        self.weights = [w.copy() for w in weights]
        self.biases = [b.copy() for b in biases]
        self.feature_mean_f = feature_mean_f.copy()
        self.feature_std_f = feature_std_f.copy()
        self.score_center = float(score_center)
        self.score_scale = float(score_scale)

    @classmethod
    def initialise(
        cls,
        input_dim: int,
        config: UncertaintyConfig | Mapping[str, Any] | None,
        rng: np.random.Generator,
        feature_mean_f: np.ndarray | None = None,
        feature_std_f: np.ndarray | None = None,
    ) -> UncertaintyHead:
        """Random head: He-normal weights (Glorot for the output layer), zero biases."""
        config = _as_config(config)
        if input_dim < 1:
            raise ConfigError(f"input_dim must be >= 1, got {input_dim}")
        sizes = [input_dim + 1, *config.hidden_sizes, 1]
        weights, biases = [], []
        for k in range(len(sizes) - 1):
            fan_in, fan_out = sizes[k], sizes[k + 1]
            last = k == len(sizes) - 2
            std = math.sqrt((2.0 / (fan_in + fan_out)) if last else (2.0 / fan_in))
            weights.append(rng.normal(scale=std, size=(fan_in, fan_out)))
            biases.append(np.zeros(fan_out))
        f = input_dim + 1
        mean = np.zeros(f) if feature_mean_f is None else feature_mean_f
        std = np.ones(f) if feature_std_f is None else feature_std_f
        return cls(input_dim, config, weights, biases, mean, std)

    # ---- parameters ---------------------------------------------------------------------

    @property
    def parameters(self) -> list[np.ndarray]:
        """The trainable arrays in the order of `gradients` (W0, b0, W1, b1, ...): the head's own
        arrays, so updating them in place updates the head."""
        return [p for wb in zip(self.weights, self.biases) for p in wb]

    # ---- forward / backward on standardised features ------------------------------------

    def _standardise(self, embeddings_nd: np.ndarray) -> np.ndarray:
        return (embedding_features(embeddings_nd) - self.feature_mean_f) / self.feature_std_f

    def _forward(self, x_nf: np.ndarray) -> tuple[np.ndarray, list[tuple[Any, ...]]]:
        """Score u (n,) and, per hidden layer, the cache (input, pre-activation, GELU tanh)."""
        cache: list[tuple[Any, ...]] = []
        h = x_nf
        for w, b in zip(self.weights[:-1], self.biases[:-1]):
            z = h @ w + b
            h_next, t = _activate(self.config.activation, z)
            cache.append((h, z, t))
            h = h_next
        cache.append((h,))
        u = h @ self.weights[-1] + self.biases[-1]
        return u[:, 0], cache

    def _backward(self, cache: list[tuple[Any, ...]], grad_u_n: np.ndarray) -> list[np.ndarray]:
        """Gradients of a loss with dL/du = grad_u_n, in the order of `parameters`."""
        n_layers = len(self.weights)
        grads: list[np.ndarray] = [np.empty(0)] * (2 * n_layers)
        delta = grad_u_n[:, None]  # dL/d(pre-activation of layer k), (n, fan_out)
        for k in range(n_layers - 1, -1, -1):
            h_in = cache[k][0]
            grads[2 * k] = h_in.T @ delta
            grads[2 * k + 1] = delta.sum(axis=0)
            if k > 0:
                _, z, t = cache[k - 1]
                delta = (delta @ self.weights[k].T) * _activate_grad(self.config.activation, z, t)
        return grads

    # ---- public inference ---------------------------------------------------------------

    def score(self, embeddings_nd: Any) -> np.ndarray:
        """Raw ranking score u(e), (n,): larger means a larger expected task loss."""
        emb = _check_embeddings(embeddings_nd, "embeddings_nd", self.input_dim)
        return self._forward(self._standardise(emb))[0]

    def predict(self, embeddings_nd: Any) -> np.ndarray:
        """Uncertainty s of each embedding, (n,), within config.output_range.

        embeddings_nd: (n, d) with d == input_dim; SchemaError on a wrong dimension, NaN/inf or
        zero rows.
        """
        return self._score_to_s(self.score(embeddings_nd))

    def _score_to_s(self, score_n: np.ndarray) -> np.ndarray:
        low, high = self.config.output_range
        t = (score_n - self.score_center) / self.score_scale
        # Stable sigmoid: exp of a non-positive number only.
        e = np.exp(-np.abs(t))
        sig = np.where(t >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
        return low + (high - low) * sig

    def gradients(
        self, embeddings_nd: Any, task_loss_n: Any, margin: float | None = None
    ) -> tuple[float, list[np.ndarray]]:
        """Ranking loss over all pairs of the batch and its gradients w.r.t. `parameters`.

        embeddings_nd: (n, d); task_loss_n: (n,); margin defaults to config.margin. Weight decay
        is decoupled (applied by the optimiser) and not part of this loss.
        """
        emb = _check_embeddings(embeddings_nd, "embeddings_nd", self.input_dim)
        loss_n = _check_task_loss(task_loss_n, emb.shape[0])
        m = self.config.margin if margin is None else float(margin)
        u, cache = self._forward(self._standardise(emb))
        loss, grad_u = ranking_loss(u, loss_n, m)
        return loss, self._backward(cache, grad_u)

    # ---- persistence --------------------------------------------------------------------

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the head to `path` as .npz (format version, input dimension, config, arrays).

        The file is written to a temporary name and renamed, so a reader never sees half a file.
        """
        path = Path(path)
        arrays: dict[str, np.ndarray] = {
            "format_version": np.array(FORMAT_VERSION, dtype=np.int64),
            "input_dim": np.array(self.input_dim, dtype=np.int64),
            "config_json": np.array(self.config.model_dump_json()),
            "n_layers": np.array(len(self.weights), dtype=np.int64),
            "feature_mean_f": self.feature_mean_f,
            "feature_std_f": self.feature_std_f,
            "score_center": np.array(self.score_center),
            "score_scale": np.array(self.score_scale),
        }
        for k, (w, b) in enumerate(zip(self.weights, self.biases)):
            arrays[f"weight_{k}"] = w
            arrays[f"bias_{k}"] = b
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: str | os.PathLike[str], expected_dim: int | None = None) -> UncertaintyHead:
        """Read a head written by `save`.

        DecodeError: the file is missing, not an .npz, truncated or lacks arrays. SchemaError:
        another format version, an invalid config, inconsistent shapes, or an input dimension
        other than `expected_dim` (when given).
        """
        try:
            with np.load(path, allow_pickle=False) as npz:
                data = {key: npz[key] for key in npz.files}
        except FileNotFoundError as exc:
            raise DecodeError(f"uncertainty head file not found: {path}") from exc
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise DecodeError(f"not a readable uncertainty head file: {path} ({exc})") from exc
        try:
            version = int(data["format_version"])
            input_dim = int(data["input_dim"])
            config_json = str(data["config_json"])
            n_layers = int(data["n_layers"])
            weights = [data[f"weight_{k}"] for k in range(n_layers)]
            biases = [data[f"bias_{k}"] for k in range(n_layers)]
            mean, std = data["feature_mean_f"], data["feature_std_f"]
            center, scale = float(data["score_center"]), float(data["score_scale"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DecodeError(f"uncertainty head file {path} lacks or garbles {exc}") from exc
        if version != FORMAT_VERSION:
            raise SchemaError(
                f"uncertainty head file {path} has format version {version}, "
                f"this build reads {FORMAT_VERSION}"
            )
        if expected_dim is not None and input_dim != expected_dim:
            raise SchemaError(
                f"uncertainty head file {path} takes {input_dim}-d embeddings, "
                f"expected {expected_dim}"
            )
        try:
            config = UncertaintyConfig.model_validate_json(config_json)
        except ValidationError as exc:
            raise SchemaError(f"uncertainty head file {path} has an invalid config") from exc
        return cls(input_dim, config, weights, biases, mean, std, center, scale)


__all__ = ["FORMAT_VERSION", "UncertaintyHead", "embedding_features", "ranking_loss"]
