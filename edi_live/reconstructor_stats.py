"""What the stats map says about the reconstructor: c, the camera values in use, the ignored pixels and the
per-pixel noise statistics, with the keys, units and rounding of the wire protocol's stats message (docs/node.md).
The worker adds these to its own counters; safe to call from any thread (it reads plain values)."""

from __future__ import annotations

from typing import Any

# keys of the reconstructor's own stats() that the stats map passes on unchanged
PASSED_ON = ("clock_offset_estimated", "clock_offset_physical_us", "black_level_estimated", "deblurs_ahead",
             "black_level_from_calibration", "clock_offset_from_calibration",
             "flicker_pixels", "noise_hz_p50", "noise_hz_p99", "noise_on_hz_p50", "noise_off_hz_p50", "noisy_pixels",
             "bayer_pattern")  # colour only; the node's summary reads it, the wire's stats map leaves it out


def reconstructor_stats(rec: Any, current: bool = False) -> dict[str, Any]:
    c_on, c_off = float(rec.c_on), float(rec.c_off)
    return {
        "c": round((c_on + c_off) / 2, 4), "c_on": round(c_on, 4), "c_off": round(c_off, 4),
        "reestimations": int(rec.reestimations), "hot_pixels": int(rec.hot_pixels),
        "unreliable_pixels": int(rec.unreliable_pixels), "black_level_dn": round(float(rec.black_level), 2),
        "clock_offset_us": int(rec.clock_offset_us), "aps_gamma": float(rec.aps_gamma),
        **{k: v for k, v in rec.stats(current).items() if k in PASSED_ON},
    }
