"""Configuration of the uncertainty head: `UncertaintyConfig`, its architecture and training
(the `uncertainty` section of the settings tree)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from mergesvc.errors import ConfigError

# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


class UncertaintyConfig(BaseModel):
    """Architecture and training of the uncertainty head (one section, as the other stages)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    hidden_sizes: tuple[int, ...] = Field(
        default=(128,), description="units of each hidden layer (empty: a linear head)"
    )
    activation: Literal["gelu", "relu"] = Field(
        default="gelu", description="hidden activation (GELU is the tanh approximation)"
    )
    margin: float = Field(
        default=1.0, gt=0.0, description="ranking margin m, in units of the raw score u"
    )
    learning_rate: float = Field(default=1e-3, gt=0.0, description="Adam step size")
    epochs: int = Field(default=40, ge=1, description="maximum passes over the training set")
    batch_size: int = Field(
        default=256,
        ge=2,
        le=4096,
        description="minibatch size; all pairs within a minibatch are used (memory ~ batch^2)",
    )
    weight_decay: float = Field(
        default=1e-4, ge=0.0, description="decoupled (AdamW) decay of the weight matrices"
    )
    output_range: tuple[float, float] = Field(
        default=(0.05, 0.5), description="(low, high) of the predicted uncertainty s"
    )
    validation_fraction: float = Field(
        default=0.1, ge=0.0, lt=1.0, description="held out for early stopping (0: none)"
    )
    patience: int = Field(
        default=6, ge=1, description="epochs without a better validation score before stopping"
    )
    early_stopping_metric: Literal["spearman", "accuracy"] = Field(
        default="spearman", description="validation score that selects the kept weights"
    )

    @model_validator(mode="after")
    def _check(self) -> UncertaintyConfig:
        if any(h < 1 for h in self.hidden_sizes):
            raise ValueError("hidden_sizes must all be >= 1")
        low, high = self.output_range
        if not (0.0 < low < high and math.isfinite(high)):
            raise ValueError("output_range must satisfy 0 < low < high < inf")
        return self


def _as_config(config: UncertaintyConfig | Mapping[str, Any] | None) -> UncertaintyConfig:
    if config is None:
        return UncertaintyConfig()
    if isinstance(config, UncertaintyConfig):
        return config
    if isinstance(config, Mapping):
        try:
            return UncertaintyConfig.model_validate(dict(config))
        except ValidationError as exc:
            fields = ", ".join(".".join(map(str, e["loc"])) for e in exc.errors())
            raise ConfigError(f"invalid uncertainty config ({fields}): {exc}") from exc
    raise ConfigError(f"config must be an UncertaintyConfig, got {type(config).__name__}")


__all__ = ["UncertaintyConfig"]
