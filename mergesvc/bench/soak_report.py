"""The soak's judge: the `Ledger` of what every robot sent and was answered (counted from the
monitor's subscriptions), the report built from it and from the store read through
`StoreReader` once the service has stopped (lost, duplicated, failed, pending submaps;
latency and throughput per time bin; RSS growth without the clients' shared memory), its
summary for people and its figure.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import re
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np

from mergesvc.bench.soak_world import FLOOD_ROBOT, HOSTILE_ROBOTS, LARGE_ROBOT, SoakPlan
from mergesvc.core.model import ErrorMessage
from mergesvc.errors import MergeError
from mergesvc.store import CONFLICTS_KEPT, StoreReader
from mergesvc.wire import decode_message

RSS_TARGET_MB = 100.0
FINAL_OUTCOMES = frozenset({"processed", "no_match", "failed"})
RETRY_BACKOFF_S = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)  # as the agent's
_FACTOR_ID = re.compile(r"^(?P<ra>[^.]+)\.(?P<sa>[^-]+)-(?P<rb>[^.]+)\.(?P<sb>[^-]+)-(?P<seq>\d+)$")


# ------------------------------------------------------------------------------ the ledger


@dataclass
class Ledger:
    """What was sent and what came back, shared by the driver's threads."""

    t0: float = field(default_factory=time.time)
    valid: dict[tuple[str, str, int], float] = field(default_factory=dict)  # key -> sent at
    mismatch: dict[tuple[str, str, int], float] = field(default_factory=dict)
    hostile: list[tuple[float, str]] = field(default_factory=list)  # (sent at, kind)
    hostile_planned: int = 0  # the attacker's quota (bench/soak_world.py hostile_schedule)
    errors: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    factors: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))
    first_factor_at: dict[tuple[str, str, int], float] = field(default_factory=dict)
    results: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    first_result_at: dict[tuple[str, str, int], float] = field(default_factory=dict)
    bytes_valid: int = 0
    flood_at: float | None = None  # wall time the conflict flood began
    flood_s: float = 0.0  # how long sending it took
    flood_sent: int = 0  # variants sent (after the one valid payload)
    large_at: float | None = None  # wall time the large submap was sent (its last try)
    # the disk-full episode: what each valid robot sent (its key and bytes, for a retry),
    # when a valid submap was answered `store` (not now) and each final result it got
    payloads: dict[tuple[str, str, int], tuple[str, bytes]] = field(default_factory=dict)
    resend: Callable[[str, bytes], Any] | None = None  # set by the driver
    store_answers: dict[tuple[str, str, int], list[float]] = field(
        default_factory=lambda: defaultdict(list))
    store_details: Counter = field(default_factory=Counter)
    finals: dict[tuple[str, str, int], list[tuple[float, str]]] = field(
        default_factory=lambda: defaultdict(list))
    resent: int = 0
    episode: dict[str, Any] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def unanswered(self) -> bool:
        """Whether a hostile payload or a flood variant sent is not answered yet (a kill then
        would lose its answer: neither is stored)."""
        with self.lock:
            return (sum(sum(self.errors[r].values()) for r in HOSTILE_ROBOTS) < len(self.hostile)
                    or sum(self.errors[FLOOD_ROBOT].values()) < self.flood_sent)

    def on_error(self, sample: Any) -> None:
        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            msg = decode_message(sample.payload.to_bytes())[1]
            code = msg.code if isinstance(msg, ErrorMessage) else "?"
        except MergeError:
            code = "undecodable"
        with self.lock:
            self.errors[robot][code] += 1

    def on_result(self, sample: Any) -> None:
        """The service's result of one submap (JSON on result/{robot}): counted per outcome."""
        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        now = time.time()
        try:
            doc = json.loads(sample.payload.to_bytes())
            outcome, code = str(doc["outcome"]), doc.get("code")
            k = (robot, doc.get("session"), doc.get("seq"))
        except (ValueError, KeyError, TypeError):
            outcome, code, k = "unreadable", None, None
        retry = None
        with self.lock:
            self.results[robot][outcome] += 1
            if k is not None and k[1] is not None and k[2] is not None:
                key = (k[0], str(k[1]), int(k[2]))
                self.first_result_at.setdefault(key, now)
                if outcome in FINAL_OUTCOMES:
                    self.finals[key].append((now, outcome))
                elif outcome == "refused" and code == "store" and key in self.payloads:
                    self.store_answers[key].append(now)
                    self.store_details[str(doc.get("detail", ""))[:80]] += 1
                    retry = key, len(self.store_answers[key]) - 1
        if retry is not None:
            self._retry(*retry)

    def _retry(self, key: tuple[str, str, int], attempt: int) -> None:
        """Send a submap answered `store` again after a backoff, as the agent does
        (fleet/agent.py RETRY_BACKOFF_S)."""
        if self.resend is None or attempt >= len(RETRY_BACKOFF_S):
            return
        zkey, data = self.payloads[key]

        def send() -> None:
            with self.lock:
                self.resent += 1
            with contextlib.suppress(Exception):  # the session may be closing
                self.resend(zkey, data)

        timer = threading.Timer(RETRY_BACKOFF_S[attempt], send)
        timer.daemon = True
        timer.start()

    def on_factor(self, sample: Any) -> None:
        parts = str(sample.key_expr).rsplit("/", 2)
        robot, fid = parts[-2], parts[-1]
        now = time.time()
        with self.lock:
            self.factors[robot].add(fid)
            m = _FACTOR_ID.match(fid)
            if m is not None:
                k = (unquote(m["rb"]), unquote(m["sb"]), int(m["seq"]))
                self.first_factor_at.setdefault(k, now)


# ------------------------------------------------------------------------------ the report


def _pct(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else None


def _others_p99(valid: dict[tuple[str, str, int], float],
                row_of: dict[tuple[str, str, int], tuple[Any, ...]], t: float, w: float
                ) -> tuple[float | None, float | None]:
    """The valid robots' p99 latency (sent -> processed, ms) of what they sent in the window
    of w s before t and in the one after (None with fewer than 3 submaps)."""
    def p99(lo: float, hi: float) -> float | None:
        ms = [(row_of[k][2] - sent) * 1e3 for k, sent in valid.items()
              if lo <= sent < hi and k in row_of and row_of[k][2] is not None]
        return _pct(ms, 99) if len(ms) >= 3 else None

    return p99(t - w, t), p99(t, t + w)


def _large(plan: SoakPlan, ledger: Ledger, valid: dict[tuple[str, str, int], float],
           row_of: dict[tuple[str, str, int], tuple[Any, ...]]) -> dict[str, Any]:
    """The large submap: given a final result (processed or no match), and the other robots'
    p99 latency in the window after it was sent at most 2x the window before."""
    if ledger.large_at is None:
        return {"sent": False, "ok": not plan.large_objects}
    t, w = ledger.large_at, plan.large_window_s
    row = next((v for k, v in row_of.items() if k[0] == LARGE_ROBOT), None)
    before, during = _others_p99(valid, row_of, t, w)
    ratio = during / before if before and during is not None else None
    status = None if row is None else row[0]
    return {"sent": True, "objects": plan.large_objects, "at_s": t - ledger.t0,
            "status": status,
            "latency_s": None if row is None or row[2] is None else row[2] - t,
            "others_p99_before_ms": before, "others_p99_during_ms": during,
            "others_p99_ratio": ratio, "window_s": w,
            "ok": status in ("processed", "no_match") and (ratio is None or ratio <= 2.0)}


def _flood(plan: SoakPlan, ledger: Ledger, valid: dict[tuple[str, str, int], float],
           row_of: dict[tuple[str, str, int], tuple[Any, ...]], errors: dict[str, dict],
           kept: int, kept_bytes: int) -> dict[str, Any]:
    """The conflict flood: every variant answered (conflict, or rate_limited once its robot's
    burst is spent), at most CONFLICTS_KEPT hashes kept and no payload, and the other robots'
    p99 latency (sent -> processed) in the window after it at most 2x the window before."""
    if ledger.flood_at is None:
        return {"sent": 0, "ok": not plan.flood_variants}
    t, w = ledger.flood_at, plan.flood_window_s

    before, during = _others_p99(valid, row_of, t, w)
    codes = errors.get(FLOOD_ROBOT, {})
    answered = sum(codes.values())
    ratio = during / before if before and during is not None else None
    return {"sent": ledger.flood_sent, "send_s": ledger.flood_s, "answered": answered,
            "codes": dict(codes), "hashes_kept": kept, "bytes_kept": kept_bytes,
            "others_p99_before_ms": before, "others_p99_during_ms": during,
            "others_p99_ratio": ratio, "window_s": w,
            "ok": (answered == ledger.flood_sent and kept <= CONFLICTS_KEPT and kept_bytes == 0
                   and set(codes) <= {"conflict", "rate_limited"}
                   and (ratio is None or ratio <= 2.0))}


def _disk_full(plan: SoakPlan, ledger: Ledger,
               row_of: dict[tuple[str, str, int], tuple[Any, ...]]) -> dict[str, Any]:
    """The disk-full episode: the valid submaps answered `store` (not now) while it lasted,
    none of them given a final result before its last such answer or two different ones, and
    every one processed once the disk had room (the robots sent them again)."""
    ep = dict(ledger.episode)
    if not plan.disk_full_at or not ep:
        return {"ran": False, "ok": not plan.disk_full_at}
    lo, hi = ep["from_t"], ep["to_t"]
    with ledger.lock:
        answered = {k: list(ts) for k, ts in ledger.store_answers.items()}
        finals = {k: list(v) for k, v in ledger.finals.items()}
    during = sorted(k for k, ts in answered.items() if any(lo <= t <= hi for t in ts))
    final_before = [k for k in during if any(t < max(answered[k]) for t, _ in finals.get(k, []))]
    two_finals = [k for k in during if len({o for _, o in finals.get(k, [])}) > 1]
    done = [k for k in during if k in row_of and row_of[k][0] in ("processed", "no_match")]
    out = {"ran": True, "at_s": lo - ledger.t0, "held_s": hi - lo,
           "limit_bytes": ep.get("limit_bytes"), "largest_file_bytes": ep.get("largest_bytes"),
           "store_answers": sum(len(ts) for ts in answered.values()),
           "submaps_answered_store": len(during), "final_before_store_answer": len(final_before),
           "two_final_results": len(two_finals), "processed_after": len(done),
           "resent": ledger.resent, "details": dict(ledger.store_details.most_common(4))}
    out["ok"] = (len(during) > 0 and not final_before and not two_finals
                 and len(done) == len(during))
    return out


def _status_latency(samples: list[dict[str, Any]], restarts: list[dict[str, float]]
                    ) -> dict[str, Any]:
    """Status round trips (query -> reply at the monitor): p50/p99 over the run, and p99 in
    the minute after each restart came back (its first, cold solve of the restored graph)."""
    ms = [x["status_ms"] for x in samples if "status_ms" in x]
    cold = [x["status_ms"] for x in samples if "status_ms" in x and any(
        0.0 <= x["t_s"] - (r["killed_at_s"] + r["down_s"]) < 60.0 for r in restarts)]
    return {"p50": _pct(ms, 50), "p99": _pct(ms, 99), "n": len(ms),
            "after_restart_p99": _pct(cold, 99), "after_restart_n": len(cold)}


def build_report(plan: SoakPlan, store: Path, ledger: Ledger, samples: list[dict[str, Any]],
            rss: list[tuple[float, float, int, float]], restarts: list[dict[str, float]],
            rates: list[float], *, drained: bool, drain_s: float, exit_code: int | None,
            log_text: str, probed: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    with StoreReader(store) as db:
        rows = db.submap_rows()
        conflicts_of = db.conflicts_by_robot()
        conflict_bytes = db.conflict_bytes()
        factor_rows = db.factor_counts()
        integrity = db.integrity()
    t0 = ledger.t0
    count = Counter((r, s, int(q)) for r, s, q, *_ in rows)
    row_of = {(r, s, int(q)): (st, rec, proc) for r, s, q, st, rec, proc in rows}
    valid = ledger.valid
    stored_valid = [k for k in valid if k in row_of]
    status_counts = Counter(row_of[k][0] for k in stored_valid)
    foreign = [k for k in row_of if k not in valid and k[0] not in (FLOOD_ROBOT, LARGE_ROBOT)]
    conflicts = sum(n for r, n in conflicts_of.items() if r != FLOOD_ROBOT)
    # end-to-end latency (sent -> processed) and the store's delay (stored -> processed)
    e2e = [(row_of[k][2] - t0, (row_of[k][2] - valid[k]) * 1e3) for k in stored_valid
           if row_of[k][2] is not None and row_of[k][0] != "pending"]
    end_s = max([plan.duration_s] + [t for t, _ in e2e])
    bin_s = plan.bin_s or max(1.0, round(end_s / 40.0))
    edges = np.arange(0.0, end_s + bin_s, bin_s)
    series: dict[str, list] = {"t_s": [], "published_per_s": [], "processed_per_s": [],
                               "e2e_p50_ms": [], "e2e_p99_ms": []}
    sent_t = np.asarray([t - t0 for t in valid.values()])
    for lo, hi in itertools.pairwise(edges):
        lat = [ms for t, ms in e2e if lo <= t < hi]
        series["t_s"].append(float(lo))
        series["published_per_s"].append(float(np.sum((sent_t >= lo) & (sent_t < hi)) / bin_s))
        series["processed_per_s"].append(len(lat) / bin_s)
        series["e2e_p50_ms"].append(_pct(lat, 50))
        series["e2e_p99_ms"].append(_pct(lat, 99))
    rss_mb = [mb for _, mb, _, _ in rss]
    own_mb = [mb - shm for _, mb, _, shm in rss]  # without the clients' shared memory
    first = next((mb for _, mb, inc, _ in rss if inc == 1), None)
    # baseline: the first process once warm (its imports and first matches done), the sample
    # nearest to min(30 s, 10 % of the run) that precedes the first kill
    warm_s = min(30.0, 0.1 * plan.duration_s)
    warm = [(abs(t - warm_s), mb, mb - shm) for t, mb, inc, shm in rss if inc == 1]
    baseline = min(warm)[1] if warm else None
    own_baseline = min(warm)[2] if warm else None
    growth = (max(own_mb) - own_baseline) if own_mb and own_baseline is not None else None
    growth_total = (max(rss_mb) - baseline) if rss_mb and baseline is not None else None
    per_inc = {}
    for inc in sorted({r[2] for r in rss}):
        mbs = [mb for _, mb, i, _ in rss if i == inc]
        own = [mb for (_, _, i, _), mb in zip(rss, own_mb) if i == inc]
        per_inc[str(inc)] = {"first_mb": mbs[0], "max_mb": max(mbs), "last_mb": mbs[-1],
                             "max_own_mb": max(own), "last_own_mb": own[-1]}
    with ledger.lock:
        errors = {r: dict(c) for r, c in ledger.errors.items()}
        factors = {r: len(f) for r, f in ledger.factors.items()}
        first_factor = dict(ledger.first_factor_at)
        results = {r: dict(c) for r, c in ledger.results.items()}
        first_result = dict(ledger.first_result_at)
        hostile = list(ledger.hostile)
        mismatch = dict(ledger.mismatch)
    answer_ms = [(first_factor[k] - valid[k]) * 1e3 for k in valid if k in first_factor]
    result_ms = [(first_result[k] - valid[k]) * 1e3 for k in valid if k in first_result]
    for r in restarts:  # what the service could only get back from the publishers' caches
        down = (r["killed_at_s"] + t0, r["killed_at_s"] + r["down_s"] + t0)
        r["valid_sent_while_down"] = sum(1 for t in valid.values() if down[0] <= t < down[1])
    hostile_answers = sum(sum(errors.get(r, {}).values()) for r in HOSTILE_ROBOTS)
    mismatch_robots = sorted({r for r, _, _ in mismatch})
    valid_robots = sorted({r for r, _, _ in valid})
    # a valid robot may only be told `store` (not now), and only by a full disk
    valid_errors = {r: e for r in valid_robots if r in errors
                    and (e := {c: n for c, n in errors[r].items()
                               if not (c == "store" and plan.disk_full_at)})}
    lost = len(valid) - len(stored_valid)
    duplicated = sum(1 for k, n in count.items() if n > 1) + conflicts
    failed = status_counts.get("failed", 0)
    pending = status_counts.get("pending", 0)
    mismatch_refused = all(errors.get(r, {}).get("embedding_dim", 0) >= 1
                           for r in mismatch_robots)
    flood = _flood(plan, ledger, valid, row_of, errors, conflicts_of.get(FLOOD_ROBOT, 0),
                   conflict_bytes)
    report: dict[str, Any] = {
        "plan": {k: (v.value if isinstance(v, Enum) else v) for k, v in asdict(plan).items()},
        "robot_rates_hz": rates,
        "restarts": restarts,
        "drained": drained, "drain_s": drain_s, "service_exit_code": exit_code,
        "valid": {"sent": len(valid), "stored": len(stored_valid), "lost": lost,
                  "duplicated": duplicated, "conflicts": conflicts,
                  "processed": status_counts.get("processed", 0),
                  "no_match": status_counts.get("no_match", 0), "failed": failed,
                  "pending": pending, "bytes_sent": ledger.bytes_valid,
                  "errors_answered": valid_errors},
        "mismatch": {"robots": mismatch_robots, "sent": len(mismatch),
                     "stored": sum(1 for k in row_of if k[0] in mismatch_robots),
                     "answers": {r: errors.get(r, {}) for r in mismatch_robots}},
        "hostile": {"planned": ledger.hostile_planned, "sent": len(hostile),
                    "by_kind": dict(Counter(k for _, k in hostile)),
                    "answered": hostile_answers,
                    "codes": dict(sum((Counter(errors.get(r, {})) for r in HOSTILE_ROBOTS),
                                      Counter())),
                    "stored": sum(1 for k in row_of if k[0] in HOSTILE_ROBOTS)},
        "foreign_rows": len(foreign),
        "flood": flood,
        "large": _large(plan, ledger, valid, row_of),
        "factors": {"stored": {str(k): int(v) for k, v in factor_rows.items()},
                    "messages_per_robot": factors,
                    "answered_submaps": len(answer_ms),
                    "answer_ms": {"p50": _pct(answer_ms, 50), "p99": _pct(answer_ms, 99)}},
        "latency_ms": {"e2e_p50": _pct([ms for _, ms in e2e], 50),
                       "e2e_p99": _pct([ms for _, ms in e2e], 99),
                       "store_delay_p50": _pct([(row_of[k][2] - row_of[k][1]) * 1e3
                                                for k in stored_valid if row_of[k][2]], 50),
                       "store_delay_p99": _pct([(row_of[k][2] - row_of[k][1]) * 1e3
                                                for k in stored_valid if row_of[k][2]], 99)},
        "results": {"valid_answered": len(result_ms),
                    "answer_ms": {"p50": _pct(result_ms, 50), "p99": _pct(result_ms, 99)},
                    "per_robot": results},
        "series": series,
        "status_samples": samples,
        "status_probe_samples": probed or [],  # {t_s, status_ms}: when the slow ones came
        # the status probe's (a process of its own: the target's), and the driver's monitor's
        # (its round trips wait on the driver's own threads too)
        "status_ms": _status_latency(probed if probed else samples, restarts),
        "status_ms_monitor": _status_latency(samples, restarts),
        "rss": {"t_s": [r[0] for r in rss], "mb": rss_mb, "incarnation": [r[2] for r in rss],
                "shmem_mb": [r[3] for r in rss], "first_mb": first, "baseline_mb": baseline,
                "baseline_at_s": warm_s, "max_mb": max(rss_mb) if rss_mb else None,
                "own_baseline_mb": own_baseline, "max_own_mb": max(own_mb) if own_mb else None,
                # the target's: RSS without shared memory (module docstring)
                "growth_mb": growth, "growth_total_mb": growth_total,
                "per_incarnation": per_inc},
        "store_integrity": integrity,
        "service_log": {"tracebacks": log_text.count("Traceback (most recent call last)"),
                        "lines": log_text.count("\n")},
    }
    report["targets"] = {
        "valid_none_lost_failed_pending": lost == 0 and failed == 0 and pending == 0,
        "valid_none_duplicated": duplicated == 0,
        "hostile_all_refused_and_answered": (report["hostile"]["stored"] == 0
                                             and hostile_answers == len(hostile)),
        "mismatch_refused_others_not": (report["mismatch"]["stored"] == 0 and mismatch_refused
                                        and not valid_errors),
        "rss_growth_under_100mb": growth is not None and growth < RSS_TARGET_MB,
        "store_integrity_ok": integrity == "ok",
        "status_p99_le_100ms": (report["status_ms"]["p99"] or 0.0) <= 100.0,
    }
    if plan.flood_variants:
        report["targets"]["flood_answered_bounded_others_p99_le_2x"] = flood["ok"]
    if plan.large_objects:
        report["targets"]["large_submap_answered_others_p99_le_2x"] = report["large"]["ok"]
    report["disk_full"] = _disk_full(plan, ledger, row_of)
    with ledger.lock:
        report["results_contradictory"] = sum(
            len({o for _, o in v}) > 1 for k, v in ledger.finals.items() if k in valid)
    report["targets"]["no_contradictory_results"] = report["results_contradictory"] == 0
    if plan.disk_full_at:
        report["targets"]["disk_full_retryable_none_final_all_processed"] = (
            report["disk_full"]["ok"])
    report["ok"] = all(report["targets"].values())
    return report


def _flood_line(f: dict[str, Any]) -> str:
    if not f.get("sent"):
        return "conflict flood: none"
    ratio = f["others_p99_ratio"]

    def ms(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    tail = f"x{ratio:.2f}" if ratio is not None else "too few submaps to compare"
    return (f"conflict flood: {f['sent']} variants in {f['send_s']:.1f} s, {f['answered']} "
            f"answered {json.dumps(f['codes'], sort_keys=True)}, {f['hashes_kept']} hashes kept "
            f"({f['bytes_kept']} payload bytes); others' p99 {f['window_s']:.0f} s before / "
            f"after it: {ms(f['others_p99_before_ms'])} / {ms(f['others_p99_during_ms'])} ms "
            f"({tail})")


def _large_line(g: dict[str, Any]) -> str:
    if not g.get("sent"):
        return "large submap: none"

    def num(x: float | None, unit: str) -> str:
        return "-" if x is None else f"{x:.1f} {unit}" if unit == "s" else f"{x:.0f} {unit}"

    ratio = g["others_p99_ratio"]
    tail = f"x{ratio:.2f}" if ratio is not None else "too few submaps to compare"
    return (f"large submap: {g['objects']} objects at {g['at_s']:.0f} s, {g['status']} after "
            f"{num(g['latency_s'], 's')}; others' p99 {g['window_s']:.0f} s before / after it: "
            f"{num(g['others_p99_before_ms'], 'ms')} / {num(g['others_p99_during_ms'], 'ms')} "
            f"({tail})")


def _disk_full_line(d: dict[str, Any]) -> str:
    if not d.get("ran"):
        return "disk full: none"
    return (f"disk full: at {d['at_s']:.0f} s for {d['held_s']:.0f} s (file size limit "
            f"{d['limit_bytes']} bytes), {d['store_answers']} `store` answers to "
            f"{d['submaps_answered_store']} valid submaps ({d['resent']} sent again); final "
            f"before their `store` answer {d['final_before_store_answer']}, two final results "
            f"{d['two_final_results']}, processed after {d['processed_after']}; "
            f"{json.dumps(d['details'])}")


def soak_summary(report: dict[str, Any]) -> str:
    """The report's numbers for people: a few lines, the targets last."""
    v, h, m, r = report["valid"], report["hostile"], report["mismatch"], report["rss"]
    lat = report["latency_ms"]
    plan = report["plan"]

    def ms(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    lines = [
        f"soak: {plan['robots']} robots, {plan['duration_s']:.0f} s, "
        f"{len(report['restarts'])} kill -9 restarts, hostile {plan['hostile_fraction']:.0%}, "
        f"{len(m['robots'])} robot(s) of another model",
        f"valid submaps: {v['sent']} sent, {v['stored']} stored, lost {v['lost']}, duplicated "
        f"{v['duplicated']}, failed {v['failed']}, pending {v['pending']} "
        f"({v['processed']} with factors, {v['no_match']} without); drained in "
        f"{report['drain_s']:.1f} s",
        f"latency sent -> processed: p50 {ms(lat['e2e_p50'])} ms, p99 {ms(lat['e2e_p99'])} ms; "
        f"stored -> processed p50 {ms(lat['store_delay_p50'])} ms, p99 "
        f"{ms(lat['store_delay_p99'])} ms; first factor back p50 "
        f"{ms(report['factors']['answer_ms']['p50'])} ms ({report['factors']['answered_submaps']} "
        f"submaps)",
        f"hostile: {h['sent']} sent of {h['planned']} planned, {h['answered']} answered, "
        f"{h['stored']} stored; codes {json.dumps(h['codes'], sort_keys=True)}",
        f"another model: {m['sent']} sent, {m['stored']} stored, answers "
        f"{json.dumps(m['answers'], sort_keys=True)}; errors to valid robots: "
        f"{json.dumps(v['errors_answered'], sort_keys=True)}",
        _flood_line(report["flood"]),
        _large_line(report.get("large", {})),
        _disk_full_line(report["disk_full"]),
        f"status round trip (probe process): p50 {ms(report['status_ms']['p50'])} ms, p99 "
        f"{ms(report['status_ms']['p99'])} ms ({report['status_ms']['n']} queries); in the minute "
        f"after each restart p99 {ms(report['status_ms']['after_restart_p99'])} ms; from the "
        f"driver's monitor p50 {ms(report['status_ms_monitor']['p50'])} ms, p99 "
        f"{ms(report['status_ms_monitor']['p99'])} ms",
        f"RSS: first {ms(r['first_mb'])} MB, at {r['baseline_at_s']:.0f} s "
        f"{ms(r['baseline_mb'])} MB, max {ms(r['max_mb'])} MB (without shared memory: at "
        f"{r['baseline_at_s']:.0f} s {ms(r['own_baseline_mb'])} MB, max {ms(r['max_own_mb'])} "
        f"MB); growth (max - at {r['baseline_at_s']:.0f} s) {ms(r['growth_mb'])} MB without "
        f"shared memory, {ms(r['growth_total_mb'])} MB with; store integrity "
        f"{report['store_integrity']}; tracebacks in the service log: "
        f"{report['service_log']['tracebacks']}",
        "targets: " + ", ".join(f"{k} {'ok' if ok else 'MISSED'}"
                                for k, ok in report["targets"].items()),
    ]
    return "\n".join(lines)


def plot_soak(report: dict[str, Any], path: Path) -> Path:
    """Throughput, latency (end to end and the service's own), and RSS over time, with the
    kills marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mergesvc.bench.figures import save_figure

    s = report["series"]
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), dpi=110, sharex=True)
    ax = axes[0]
    ax.step(s["t_s"], s["published_per_s"], where="post", label="valid sent", color="0.5")
    ax.step(s["t_s"], s["processed_per_s"], where="post", label="processed", color="tab:blue")
    ax.set_ylabel("submaps / s")
    ax = axes[1]

    def nan(xs: list) -> list[float]:
        return [np.nan if x is None else x for x in xs]

    ax.plot(s["t_s"], nan(s["e2e_p50_ms"]), "o-", ms=3, label="sent -> processed p50")
    ax.plot(s["t_s"], nan(s["e2e_p99_ms"]), "o-", ms=3, label="sent -> processed p99")
    st = report["status_samples"]
    if st:
        t = [x["t_s"] for x in st]
        ax.plot(t, nan([(x["latency_ms"] or {}).get("p50") for x in st]), ":", color="k",
                label="status latency_ms p50 (processing)")
        ax.plot(t, nan([(x["latency_ms"] or {}).get("p99") for x in st]), "--", color="k",
                label="status latency_ms p99")
    ax.set_yscale("log")
    ax.set_ylabel("ms")
    ax = axes[2]
    ax.plot(report["rss"]["t_s"], report["rss"]["mb"], color="tab:green", label="service RSS")
    ax.plot(report["rss"]["t_s"], np.subtract(report["rss"]["mb"], report["rss"]["shmem_mb"]),
            color="tab:olive", label="without shared memory")
    ax.set_ylabel("MB")
    ax.set_xlabel("s since start")
    for ax in axes:
        for r in report["restarts"]:
            ax.axvline(r["killed_at_s"], color="tab:red", lw=0.8, alpha=0.7)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    plan = report["plan"]
    v = report["valid"]
    axes[0].set_title(
        f"soak: {plan['robots']} robots, {plan['duration_s']:.0f} s, {len(report['restarts'])} "
        f"kill -9 (red), {plan['hostile_fraction']:.0%} hostile; {v['sent']} valid sent, lost "
        f"{v['lost']}, failed {v['failed']}, pending {v['pending']}", fontsize=9)
    return save_figure(fig, path)


__all__ = ["RSS_TARGET_MB", "Ledger", "build_report", "plot_soak", "soak_summary"]
