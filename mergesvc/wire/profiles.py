"""What every codec stage shares: message types, quantisation profiles, encoder settings,
decoder limits, and the record of a decoded envelope.

`compact` is for acoustic links: every field is bounded as in DCCL, and embeddings are
transform-coded on a fleet-shared PCA `Projection` (bits given to components by greedy reverse
water-filling; `embedding_bits`, 400, per object). What each profile carries per object
(fixed-point positions: 1 cm by default, the range per axis taken from the data and carried;
the bit-level layout: docs/wire.md §4-§5):

    profile   embedding                        variance                       position
    full      float32                          float32, as given              float64
    f16       float16                          log2, 16 bits, as given        fixed point
    int8      int8 + float32 scale per vector  log2, 8 bits, as given         fixed point
    compact   PCA coefficients, 0-8 bits each  mean only, log2, <= 1.1 %      fixed point
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from mergesvc.core.model import MAX_EMBEDDING_DIM
from mergesvc.wire.names import MessageType, Profile


@dataclass(frozen=True)
class CodecLimits:
    """What a decoder accepts. Larger messages are refused before anything is allocated;
    the encoder refuses to produce what a decoder with the default limits would refuse.

    max_values bounds objects x dims (4 M: a 10 000-object map of 384-d embeddings), which
    bounds the memory a small compact message can expand into (decompression bombs).
    """

    max_message_bytes: int = 16 * 2**20
    max_objects: int = 20_000
    max_dim: int = MAX_EMBEDDING_DIM
    max_values: int = 4_000_000
    max_correspondences: int = 10_000


DEFAULT_LIMITS = CodecLimits()


class CodecSettings(BaseModel):
    """Encoder settings; every choice the decoder needs is carried in the message."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    position_resolution_m: float = Field(
        0.01, ge=1e-6, le=1000, description="fixed-point step of object positions"
    )
    embedding_bits: int = Field(
        400, ge=0, le=65535, description="compact: bits per object for the PCA coefficients"
    )
    coef_step_scale: float = Field(
        1.5, gt=0, le=15, description="compact: quantiser step in units of Max's Gaussian step"
    )
    translation_resolution_m: float = Field(
        0.001, ge=1e-6, le=1000, description="compact factors: fixed-point step of T_a_b"
    )


@dataclass(frozen=True)
class Envelope:
    """What the envelope of a decoded message said."""

    schema_version: int
    msg_type: MessageType
    sender: str
    seq: int
    profile: Profile
    n_bytes: int
    projection_id: str | None = None


__all__ = [
    "DEFAULT_LIMITS",
    "CodecLimits",
    "CodecSettings",
    "Envelope",
    "MessageType",
    "Profile",
]
