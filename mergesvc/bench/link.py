"""Link benchmark (`mergesvc bench link`): wire profile x modem rate x SNR, bytes, airtime,
delivery over the acoustic link and node accuracy after decoding.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from mergesvc.bench.scoring import _fmt, check_count, score_case
from mergesvc.core.config import MatchConfig
from mergesvc.core.pipeline import match
from mergesvc.sim import Family, make_scenario

if TYPE_CHECKING:
    from mergesvc.link import LinkConfig


def run_link_bench(
    seeds: int = 5,
    submap_objects: int = 20,
    period_s: float = 300.0,
    duration_s: float = 3600.0,
    seed: int = 0,
    echo: Callable[[str], Any] = print,
    base: MatchConfig | None = None,
    link_config: LinkConfig | None = None,
) -> dict[str, Any]:
    """Profile x modem rate x SNR: bytes per object, bytes and airtime of one 20-object submap,
    delivery ratio and mean time to deliver (3 vehicles sharing the TDMA cycle, one submap each
    every period_s), and node accuracy after decoding (the submap decoded, the map as is).
    Matching uses `base` (default: the defaults); the sweep starts from `link_config` (default:
    LinkConfig()) with each rate and SNR set. InputError for seeds below 1."""
    check_count("seeds", seeds)
    from mergesvc.link import (
        DEFAULT_SWEEP_SNR_DB,
        RATE_SPECS,
        ModemRate,
        Workload,
        frame_error_prob,
        sweep_link,
    )
    from mergesvc.wire import Profile, Projection, decode_message, encode_message

    profiles: dict[str, dict[str, float]] = {}
    for prof in Profile:
        acc, nbytes, nobj = [], 0, 0
        for s in range(seeds):
            sc = make_scenario(Family.UNDERWATER, seed + s, n_map=40, n_sub=submap_objects,
                               n_outliers=2)
            proj = Projection.fit(sc.map.arrays().embeddings_nd) if prof is Profile.COMPACT \
                else None  # the fleet's projection: learned from map data, not the submap
            data = encode_message(sc.submap, prof, sc.submap.robot_id, 0, projection=proj)
            _, decoded = decode_message(data, proj)
            nbytes += len(data)
            nobj += len(sc.submap.objects)
            acc.append(score_case(sc, match(sc.map, decoded, base))["accuracy"])
        profiles[prof.value] = {"bytes_per_object": nbytes / nobj,
                                "bytes_per_submap": nbytes / seeds,
                                "node_accuracy": float(np.mean(acc))}
    rows = []
    for prof, p in profiles.items():
        size = round(p["bytes_per_submap"])
        wl = Workload(uplink_bytes=size, period_s=period_s, duration_s=duration_s)
        for rate in ModemRate:
            spec = RATE_SPECS[rate]
            fragments = -(-(size + 4) // spec.fragment_payload_bytes)
            airtime = -(-fragments // spec.frames) * spec.airtime_s
            for r in sweep_link((rate,), DEFAULT_SWEEP_SNR_DB[rate], workload=wl,
                                base_config=link_config, seed=seed):
                row = {
                    "profile": prof, "rate": rate.value, "snr_db": r.snr_db,
                    "frame_error": frame_error_prob(rate, r.snr_db),
                    "bytes_per_object": p["bytes_per_object"], "bytes_per_submap": size,
                    "airtime_s": airtime, "delivery_ratio": r.delivery_ratio,
                    "latency_p50_s": r.latency_p50_s, "node_accuracy": p["node_accuracy"],
                }
                rows.append(row)
    lines = ["| profile | rate | SNR dB | FER | B/object | B/submap | airtime s | delivered | "
             "time to deliver s (median) | node accuracy |", "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['profile']} | {r['rate']} | {r['snr_db']:.1f} | {r['frame_error']:.3f} | "
            f"{r['bytes_per_object']:.0f} | {r['bytes_per_submap']} | {r['airtime_s']:.1f} | "
            f"{r['delivery_ratio']:.2f} | {_fmt(r['latency_p50_s'])} | "
            f"{r['node_accuracy']:.3f} |")
    md = "\n".join(lines)
    echo(md)
    return {"profiles": profiles, "rows": rows, "markdown": md,
            "workload": {"vehicles": 3, "submap_objects": submap_objects, "period_s": period_s,
                         "duration_s": duration_s}}


__all__ = ["run_link_bench"]
