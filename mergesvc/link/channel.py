"""The physical layer: `AcousticChannel` (airtime, propagation delay, per-packet frame losses).

Bottom of the stack: the simulator hands it the frames of one packet and gets back those the
receiver decodes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mergesvc.link.config import ChannelConfig, SnrModel, _split_link_key
from mergesvc.link.modem import RATE_SPECS, ModemRate, frame_error_prob


class AcousticChannel:
    """Physical layer: per-packet SNR draw, per-frame Bernoulli errors, cut at the first bad frame.

    All randomness comes from the injected generator, consumed in a fixed pattern per packet
    (one SNR draw if spread > 0, then one uniform per frame of the rate) so runs are repeatable.
    """

    def __init__(self, config: ChannelConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.spec = RATE_SPECS[config.rate]
        self._rng = rng
        self._snr = {_split_link_key(k): v for k, v in config.link_snr.items()}
        self._range_m: dict[tuple[str, str], float] = {}
        for key, range_m in config.link_range_m.items():
            a, b = _split_link_key(key)
            self._range_m[(a, b)] = self._range_m[(b, a)] = range_m

    def range_m(self, a: str, b: str) -> float:
        return self._range_m.get((a, b), self.config.range_m)

    def propagation_delay_s(self, a: str, b: str) -> float:
        return self.range_m(a, b) / self.config.sound_speed_mps

    def snr_model(self, src: str, dst: str) -> SnrModel:
        return self._snr.get((src, dst), self.config.snr)

    def draw_snr_db(self, src: str, dst: str) -> float:
        model = self.snr_model(src, dst)
        if model.spread_db == 0.0:
            return model.mean_db
        return model.mean_db + model.spread_db * float(self._rng.standard_normal())

    def frame_error_prob(self, snr_db: float) -> float:
        if self.config.fixed_fer is not None:
            return self.config.fixed_fer
        return frame_error_prob(self.config.rate, snr_db)

    def transmit_packet(self, src: str, dst: str, frames: Sequence[bytes]) -> list[bytes]:
        """Frames decoded by `dst`: those before the first bad frame (a packet is cut there).

        The bad frame itself is passed up with corrupted bytes with probability
        `corrupt_bad_frame_prob` (a modem-level check that missed), otherwise dropped.
        """
        if not 0 < len(frames) <= self.spec.frames:
            raise ValueError(
                f"a rate-{self.config.rate.value} packet holds 1..{self.spec.frames} frames"
            )
        p_bad = self.frame_error_prob(self.draw_snr_db(src, dst))
        bad = self._rng.random(self.spec.frames)[: len(frames)] < p_bad
        n_good = int(np.argmax(bad)) if bad.any() else len(frames)
        received = list(frames[:n_good])
        corrupt_p = self.config.corrupt_bad_frame_prob
        if n_good < len(frames) and corrupt_p > 0.0 and self._rng.random() < corrupt_p:
            received.append(self._corrupt(frames[n_good]))
        return received

    def transmit_miniframe(self, src: str, dst: str) -> bool:
        """Whether an ack mini-frame gets through (rate-1 curve unless `miniframe_fer` is set)."""
        snr_db = self.draw_snr_db(src, dst)
        if self.config.miniframe_fer is not None:
            p_bad = self.config.miniframe_fer
        else:
            p_bad = frame_error_prob(ModemRate.RATE1, snr_db)
        return bool(self._rng.random() >= p_bad)

    def _corrupt(self, frame: bytes) -> bytes:
        data = bytearray(frame)
        n_flips = 1 + int(self._rng.integers(0, 4))
        for pos in self._rng.integers(0, len(data), size=n_flips):
            data[int(pos)] ^= int(self._rng.integers(1, 256))
        return bytes(data)


__all__ = [
    "AcousticChannel",
]
