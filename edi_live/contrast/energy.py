"""The paper's energy estimator of c (Pan et al. 2019, Sec. 4.2): minimise TV(L) - lambda * xcorr(Sobel|L|, Sobel|M|)
by golden-section search, M the time-decayed signed event map around f. Both terms are normalised by their value
at L = B. Measured to end on a bound of its range on our scenes (docs/accuracy.md); kept for comparison."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

import edi_live.edi as edi
from edi_live.contrast.frames import FrameData
from edi_live.contrast.search import golden_section, three_point_fit


def event_map(events: np.ndarray, width: int, height: int, ref_t_us: int, t0: int, t1: int,
              tau_us: float) -> np.ndarray:
    """M(f) = sum over events in [t0, t1] of polarity * exp(-|t - f| / tau), (H, W) float32."""
    sel = events[(events["t"] >= t0) & (events["t"] <= t1)]
    sel = sel[(sel["x"] < width) & (sel["y"] < height)]
    w = np.exp(-np.abs(sel["t"] - ref_t_us) / max(tau_us, 1.0)) * np.where(sel["p"], 1.0, -1.0)
    idx = sel["y"].astype(np.int64) * width + sel["x"]
    return np.bincount(idx, weights=w, minlength=width * height).reshape(height, width).astype(np.float32)


def _grad_mag(img: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def _phases(img: np.ndarray, mosaic: bool) -> list[np.ndarray]:
    """The image, or on a Bayer mosaic its four same-channel sub-images (every other row and column), so that the
    spatial terms never difference two colour channels."""
    if not mosaic:
        return [img]
    return [np.ascontiguousarray(img[dy::2, dx::2]) for dy in (0, 1) for dx in (0, 1)]


def _tv(img: np.ndarray) -> float:
    dx = np.abs(np.diff(img, axis=1)).sum()
    dy = np.abs(np.diff(img, axis=0)).sum()
    return float(dx + dy)


@dataclass
class EnergyContrast:
    """The paper's energy: TV(L)/TV(B) - lam * <|grad L|, |grad M|> / <|grad B|, |grad M|>, golden-section search."""

    lam: float = 1.0
    c_min: float = 0.03
    c_max: float = 1.0
    tol: float = 2e-3
    fit_step: float = 0.1
    name: str = "energy"
    needs_pair: bool = False
    separate: bool = False
    needs_full_image: bool = True
    fit_z: float = 1.0  # misfit() is all or nothing: 0 (three-point fit holds) or inf
    info_z: float = 0.0
    mosaic: bool = False  # the frames are Bayer mosaics (a colour sensor): spatial terms per channel phase

    def _energy_fn(self, cur: FrameData) -> Callable[[float], float] | None:
        if cur.event_map is None or cur.table.n_active == 0:
            return None
        ems = [_grad_mag(p) for p in _phases(cur.event_map, self.mosaic)]
        b = np.maximum(cur.blurry, edi.DARK_FLOOR)
        phases = lambda img: _phases(img, self.mosaic)  # noqa: E731
        tv = lambda img: sum(_tv(p) for p in phases(img))  # noqa: E731
        xc = lambda img: sum(float((_grad_mag(p) * e).sum()) for p, e in zip(phases(img), ems))  # noqa: E731
        tv_b = max(tv(b), 1e-6)
        xc_b = max(xc(b), 1e-6)

        def energy(c: float) -> float:
            lat = np.exp(edi.deblur_log(b, cur.table, c, informative=cur.informative))
            np.clip(lat, 0.0, 4 * 255.0, out=lat)
            return tv(lat) / tv_b - self.lam * xc(lat) / xc_b

        return energy

    def estimate(self, cur, pairs, c_init):
        fn = self._energy_fn(cur)
        if fn is None:
            return None
        c = golden_section(fn, self.c_min, self.c_max, tol=self.tol)[0]
        return c, c

    def misfit(self, cur, pairs, c):
        fn = self._energy_fn(cur)
        return 0.0 if fn is None or three_point_fit(fn, c[0], self.fit_step) else math.inf

    def still_misfit(self, cur, pairs, floor, cached):
        return self.misfit(cur, pairs, floor)

    def confirm_still(self, pairs, c, floor):
        return None

    def information(self, pairs, c):
        return None


