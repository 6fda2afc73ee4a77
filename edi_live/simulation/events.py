"""The event model: ESIM threshold crossings of each pixel's log intensity, the refractory period, and
the events without scene information (background activity, light-dependent shot noise, hot pixels).

Owns how events are drawn; the engine (engine.py) calls it once per render step and once at the end.
"""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import EVENT_DTYPE
from edi_live.simulation.config import SceneConfig


def signal_events(ref: np.ndarray, l0: np.ndarray, l1: np.ndarray, con: np.ndarray, coff: np.ndarray,
                   t0_s: float, dt_s: float, refractory_s: float, last_t: np.ndarray):
    """ESIM crossings of the log level moving linearly l0 -> l1 over [t0_s, t0_s + dt_s].

    Updates `ref` (and `last_t` for the refractory period) in place; returns (pixel index, time s, polarity).
    """
    d = l1 - ref
    idx = np.flatnonzero((d >= con) | (d <= -coff))
    if idx.size == 0:
        return idx, np.zeros(0), np.zeros(0, bool)
    di = d[idx]
    on = di > 0
    n = np.where(on, np.floor(di / con[idx]), np.floor(-di / coff[idx])).astype(np.int64)
    keep_px = n > 0
    idx, on, n = idx[keep_px], on[keep_px], n[keep_px]
    counts = n
    step = np.where(on, con[idx], -coff[idx])
    total = int(counts.sum())
    pix = np.repeat(idx, counts)
    k = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    levels = ref[pix] + k * np.repeat(step, counts)
    dl = l1[pix] - l0[pix]
    frac = np.clip((levels - l0[pix]) / np.where(dl == 0, 1.0, dl), 0.0, 1.0)
    t = t0_s + frac.astype(np.float64) * dt_s  # float64 seconds: µs-exact over long recordings
    pol = np.repeat(on, counts)
    ref[idx] += counts * step
    if refractory_s > 0:
        # within one step a pixel's crossings are evenly spaced by s; keep the greedy subset analytically
        s = np.repeat(np.abs(step) / np.maximum(np.abs(l1[idx] - l0[idx]), 1e-12) * dt_s, counts)
        t_first = np.repeat(t[np.cumsum(counts) - counts], counts)
        allowed = last_t[pix] + refractory_s
        k0 = np.maximum(1, np.ceil((allowed - t_first) / np.maximum(s, 1e-15) - 1e-9) + 1)
        m = np.maximum(1, np.ceil(refractory_s / np.maximum(s, 1e-15) - 1e-9))
        keep = (k >= k0) & (((k - k0) % m) == 0)
        pix, t, pol = pix[keep], t[keep], pol[keep]
        np.maximum.at(last_t, pix, t)
    return pix, t, pol


def noise_events(cfg: SceneConfig, rng: np.random.Generator, duration_s: float):
    w, h = cfg.width, cfg.height
    n_bg = rng.poisson(cfg.noise_rate_hz * w * h * duration_s) if cfg.noise_rate_hz > 0 else 0
    pix = [rng.integers(0, w * h, n_bg)]
    t = [rng.random(n_bg) * duration_s]
    pol = [rng.random(n_bg) < 0.5]
    hot = rng.choice(w * h, size=min(cfg.hot_pixels, w * h), replace=False) if cfg.hot_pixels else np.zeros(0, int)
    for p in hot:
        n = rng.poisson(cfg.hot_rate_hz * duration_s)
        pix.append(np.full(n, p))
        t.append(rng.random(n) * duration_s)
        pol.append(rng.random(n) < rng.uniform(0.2, 0.8))
    xy = np.stack([hot % w, hot // w], axis=1) if hot.size else np.zeros((0, 2), int)
    return np.concatenate(pix), np.concatenate(t), np.concatenate(pol), xy


def to_events(pix: np.ndarray, t_us: np.ndarray, pol: np.ndarray, width: int) -> np.ndarray:
    ev = np.empty(pix.size, EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"] = pix % width
    ev["y"] = pix // width
    ev["p"] = pol
    return ev


def shot_noise_events(cfg: SceneConfig, rng: np.random.Generator, log_frame: np.ndarray, t0_s: float,
                      dt_s: float):
    """Light-dependent background events in [t0_s, t0_s + dt_s): per pixel a Poisson rate of
    shot_noise_hz * min(1, shot_noise_dark / I), I the pixel's linear intensity at the step's start (fraction
    of full scale), drawn by thinning a uniform process at the full rate. Polarity is even."""
    n_px = log_frame.size
    n = rng.poisson(cfg.shot_noise_hz * n_px * dt_s)
    pix = rng.integers(0, n_px, n)
    accept = rng.random(n) * np.exp(log_frame[pix].astype(np.float64)) < cfg.shot_noise_dark
    t = t0_s + rng.random(n) * dt_s
    pol = rng.random(n) < 0.5
    return pix[accept], t[accept], pol[accept]
