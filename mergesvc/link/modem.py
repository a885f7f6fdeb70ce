"""Micro-Modem packet rates and their frame error rate against SNR.

Frame error rate vs SNR follows the published Micro-Modem curves (as tabulated in WHOI ros_acomms),
interpolated linearly in dB; a packet is cut at its first bad frame. The table ships as package
data (`mergesvc/data/micromodem_fer.json`).
"""

from __future__ import annotations

import functools
import importlib.resources
import json
from dataclasses import dataclass
from enum import Enum

import numpy as np

from mergesvc.errors import DecodeError
from mergesvc.link.arq import FRAGMENT_HEADER_BYTES


class ModemRate(int, Enum):
    """Micro-Modem PSK packet rates modelled here."""

    RATE1 = 1
    RATE3 = 3
    RATE5 = 5


@dataclass(frozen=True)
class RateSpec:
    """Packet geometry of one modem rate: fixed-length packets of `frames` equal frames."""

    packet_bytes: int
    frames: int
    airtime_s: float

    @property
    def frame_bytes(self) -> int:
        """Bytes per frame (rate 5: 2048 // 7 = 292, so 2044 of the 2048 bytes are usable)."""
        return self.packet_bytes // self.frames

    @property
    def fragment_payload_bytes(self) -> int:
        """Message bytes carried by one frame after the fragment header."""
        return self.frame_bytes - FRAGMENT_HEADER_BYTES


RATE_SPECS: dict[ModemRate, RateSpec] = {
    ModemRate.RATE1: RateSpec(packet_bytes=192, frames=2, airtime_s=3.07),
    ModemRate.RATE3: RateSpec(packet_bytes=512, frames=1, airtime_s=3.07),
    ModemRate.RATE5: RateSpec(packet_bytes=2048, frames=7, airtime_s=3.0),
}


@dataclass(frozen=True)
class FerCurve:
    """Frame error probability against SNR; shapes (n,), SNR strictly increasing."""

    snr_db: np.ndarray
    frame_error_prob: np.ndarray

    def __call__(self, snr_db: float) -> float:
        # Clamped outside the table, as in ros_acomms (np.interp holds the end values).
        return float(np.interp(snr_db, self.snr_db, self.frame_error_prob))


@functools.cache
def fer_curves() -> dict[ModemRate, FerCurve]:
    """The published Micro-Modem FER table shipped as package data (`data/micromodem_fer.json`)."""
    resource = importlib.resources.files("mergesvc") / "data" / "micromodem_fer.json"
    try:
        table = json.loads(resource.read_text(encoding="utf-8"))
        curves = {}
        for rate in ModemRate:
            entry = table[f"rate{rate.value}"]
            snr_db = np.asarray(entry["snr_db"], dtype=float)
            prob = np.asarray(entry["frame_error_prob"], dtype=float)
            if snr_db.shape != prob.shape or snr_db.ndim != 1 or snr_db.size < 2:
                raise ValueError(f"rate {rate.value}: snr_db and frame_error_prob differ in shape")
            if np.any(np.diff(snr_db) <= 0) or np.any((prob < 0) | (prob > 1)):
                raise ValueError(
                    f"rate {rate.value}: SNR not increasing or probability not in [0, 1]"
                )
            curves[rate] = FerCurve(snr_db=snr_db, frame_error_prob=prob)
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise DecodeError(f"invalid Micro-Modem FER table {resource}: {exc}") from exc
    return curves


def frame_error_prob(rate: ModemRate, snr_db: float) -> float:
    """Frame error probability of `rate` at `snr_db` (linear interpolation in dB)."""
    return fer_curves()[ModemRate(rate)](snr_db)


__all__ = [
    "RATE_SPECS",
    "FerCurve",
    "ModemRate",
    "RateSpec",
    "fer_curves",
    "frame_error_prob",
]
