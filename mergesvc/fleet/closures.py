"""Which inter-robot factors the pose graph may trust: per pair of sessions, the largest set that
agree pairwise with each other along the two odometry chains (core/pcm.py), tested on the
factors' own covariances (inflated by `inflation`) before any of them is solved; GNC then judges
the trusted ones as before. A factor outside the set is held: stored, not solved, not sent, and
trusted later if the set grows to take it in; a trusted factor the set drops is withdrawn.

Only the `window` latest factors of a pair are weighed again; older ones keep their verdict,
so the cost per factor stays bounded on a long mission. Pure bookkeeping: the caller supplies
the odometry chains and acts on the verdicts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from mergesvc.core.chi2 import chi2_quantile
from mergesvc.core.factors import factor_frames
from mergesvc.core.model import Factor
from mergesvc.core.pcm import loop_nees, max_clique
from mergesvc.core.poses import inverse_with_covariance, pose3_from_model
from mergesvc.fleet.config import ConsistencyConfig

# chains(frame, from_keyframe, to_keyframes) -> {to: (T_from_to, covariance)} along odometry
Chains = Callable[[str, int, set[int]], dict[int, tuple[gtsam.Pose3, np.ndarray]]]


@dataclass
class _Pair:
    ids: list[str] = field(default_factory=list)  # in arrival order
    keys: dict[str, tuple[int, int]] = field(default_factory=dict)  # id -> (k on a, k on b)
    meas: dict[str, tuple[gtsam.Pose3, np.ndarray]] = field(default_factory=dict)  # a -> b
    trusted: set[str] = field(default_factory=set)
    ok: dict[tuple[str, str], bool] = field(default_factory=dict)  # consistency, both orders


@dataclass(frozen=True)
class Verdict:
    """What one offered factor changed: factors to solve and send now, factors to withdraw."""

    trusted: list[str]
    withdrawn: list[str]

    @property
    def changed(self) -> bool:
        return bool(self.trusted or self.withdrawn)


class ClosureSets:
    """Per pair of sessions, the factors the graph trusts (module docstring)."""

    def __init__(self, config: ConsistencyConfig, chains: Chains) -> None:
        self.config = config
        self.chains = chains
        self._pairs: dict[tuple[str, str], _Pair] = {}
        self._pair_of: dict[str, tuple[str, str]] = {}
        self._threshold = chi2_quantile(config.quantile, 6)

    def pair_key(self, factor: Factor) -> tuple[str, str]:
        """The pair of sessions a factor belongs to (its consistency set)."""
        fa, fb = (str(x) for x in factor_frames(factor))
        return (fa, fb) if fa <= fb else (fb, fa)

    def pair_state(self, key: tuple[str, str]) -> _Pair | None:
        """A pair's state (copy it to restore it with `set_pair_state`)."""
        return self._pairs.get(key)

    def set_pair_state(self, key: tuple[str, str], state: _Pair | None) -> None:
        """A pair's state as it was (a unit of work that could not be committed)."""
        now = self._pairs.pop(key, None)
        for fid in (now.ids if now is not None else ()):
            self._pair_of.pop(fid, None)
        if state is not None:
            self._pairs[key] = state
            for fid in state.ids:
                self._pair_of[fid] = key

    def is_trusted(self, factor_id: str) -> bool:
        key = self._pair_of.get(factor_id)
        return key is not None and factor_id in self._pairs[key].trusted

    def held(self) -> list[str]:
        """Every factor offered and not trusted now (not forgotten)."""
        return [f for p in self._pairs.values() for f in p.ids if f not in p.trusted]

    def forget(self, factor_id: str) -> None:
        """Take a factor out of consideration for good (GNC rejected it)."""
        key = self._pair_of.pop(factor_id, None)
        if key is None:
            return
        p = self._pairs[key]
        p.ids.remove(factor_id)
        p.keys.pop(factor_id, None)
        p.meas.pop(factor_id, None)
        p.trusted.discard(factor_id)
        for other in p.ids:
            p.ok.pop((factor_id, other), None)
            p.ok.pop((other, factor_id), None)

    def offer(self, factor: Factor, trusted: bool | None = None) -> Verdict:
        """Weigh a new factor with its pair's latest ones. `trusted` (a restart replaying the
        verdicts it had) sets the factor's verdict without weighing anything."""
        fa = str(factor_frames(factor)[0])
        key = self.pair_key(factor)
        T = pose3_from_model(factor.T_a_b)
        C = np.asarray(factor.covariance, dtype=np.float64)
        ka, kb = factor.keyframe_a or 0, factor.keyframe_b or 0
        if key[0] != fa:  # held in the pair's direction
            T, C = inverse_with_covariance(T, C)
            ka, kb = kb, ka
        p = self._pairs.setdefault(key, _Pair())
        fid = factor.factor_id
        if fid in p.keys:
            return Verdict([], [])
        p.ids.append(fid)
        p.keys[fid] = (ka, kb)
        p.meas[fid] = (T, C * self.config.inflation)
        self._pair_of[fid] = key
        if trusted is not None or not self.config.enabled:
            if trusted is not False:
                p.trusted.add(fid)
            return Verdict([fid] if trusted is not False else [], [])
        window = _recent(p, self.config.window)
        self._test(key, p, fid, [g for g in window if g != fid])
        inside = set(window)
        for old in [g for g in p.keys if g not in inside]:  # keeps its verdict, not its data
            del p.meas[old], p.keys[old]
            for g in window:
                p.ok.pop((old, g), None)
                p.ok.pop((g, old), None)
        adj = np.array([[g == h or p.ok.get((g, h), True) for h in window] for g in window])
        keep = {window[i] for i in max_clique(adj, [g in p.trusted for g in window])}
        before = {g for g in window if g in p.trusted}
        p.trusted = (p.trusted - set(window)) | keep
        return Verdict([g for g in window if g in keep - before],
                       [g for g in window if g in before - keep])

    def _test(self, key: tuple[str, str], p: _Pair, fid: str, others: list[str]) -> None:
        """Consistency of `fid` with each of `others` (untestable pairs: consistent)."""
        i, j = p.keys[fid]
        on_a = self.chains(key[0], i, {p.keys[g][0] for g in others})
        from_j = self.chains(key[1], j, {p.keys[g][1] for g in others})
        for g in others:
            k, m = p.keys[g]
            ca, cb = on_a.get(k), from_j.get(m)
            if cb is not None:  # walked from j: the loop needs T_{B m, j}
                cb = inverse_with_covariance(*cb)
            ok = True
            if ca is not None and cb is not None:
                ok = loop_nees(p.meas[fid], p.meas[g], ca, cb) < self._threshold
            p.ok[(fid, g)] = p.ok[(g, fid)] = ok


def _recent(p: _Pair, n: int) -> list[str]:
    """The pair's last `n` factors that still hold their test data, oldest first (a factor
    forgotten in between does not bring one whose data went back into the window)."""
    out: list[str] = []
    for g in reversed(p.ids):
        if g in p.keys:
            out.append(g)
            if len(out) == n:
                break
    return out[::-1]


__all__ = ["Chains", "ClosureSets", "Verdict"]
