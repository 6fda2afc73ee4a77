"""What a c estimator works on (one frame's data, a pair of consecutive frames) and what it must offer (the
ContrastEstimator protocol), plus the trivial estimator for a c given by the user."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np

import edi_live.edi as edi


@dataclass
class FrameData:
    """One APS frame as the estimators see it: B (8-bit scale, float32), which pixels are informative, its
    level table, and the signed event map M around f (for the energy estimator; None when not needed). `raw`: the
    APS values before a black level was taken off (8-bit scale), when one was: pixels at or below it are clipped
    out of B, and the black-level fit needs them to correct a value set too high."""

    blurry: np.ndarray
    informative: np.ndarray
    table: edi.LevelTable
    event_map: np.ndarray | None = None
    raw: np.ndarray | None = None


@dataclass
class FramePair:
    """Two consecutive frames and the ON/OFF event counts per pixel from f_prev to f_cur (flat int arrays)."""

    prev: FrameData
    cur: FrameData
    n_on: np.ndarray
    n_off: np.ndarray
    mask: np.ndarray | None = None  # flat bool: pixels to ignore (hot)
    # estimators may keep their per-pair setup here (a pair is immutable once built; it serves several frames)
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def has_tables(self) -> bool:
        """Both frames' level tables are built (a settled calibration builds them only where they are read)."""
        return self.prev.table is not None and self.cur.table is not None


class ContrastEstimator(Protocol):
    """What the c policy (edi_live.c_policy) asks of an estimator. z values are "standard errors by which one c
    explains the frames better than another" (> 0: the alternative is better); None means the data say nothing."""

    name: str
    needs_pair: bool  # estimates need consecutive-frame pairs (and can confirm a still scene on the next pair)
    separate: bool  # estimates c_on and c_off apart (the level tables then need ON/OFF segments)
    needs_full_image: bool  # works on the whole frame rather than the reconstructor's pixel sample
    c_min: float  # bottom of the search range; an estimate there means "the events explain nothing"
    fit_z: float  # misfit z at which the cached c fails the fit test
    info_z: float  # information z below which an estimate is judged flat (no information about c)

    def estimate(self, cur: FrameData, pairs: Sequence[FramePair], c_init: tuple[float, float]) \
            -> tuple[float, float] | None:
        """(c_on, c_off) for `cur`, or None when the data say nothing about c (keep the current value).
        `pairs`: recent consecutive-frame pairs, newest last (empty for the first frame)."""
        ...

    def misfit(self, cur: FrameData, pairs: Sequence[FramePair], c: tuple[float, float]) -> float | None:
        """Cheap fit test (a few evaluations): z of the best neighbour of c against c."""
        ...

    def still_misfit(self, cur: FrameData, pairs: Sequence[FramePair], floor: tuple[float, float],
                     cached: tuple[float, float]) -> float | None:
        """While events are ignored (a still scene, c at `floor`): z of the cached c against the floor, i.e. how
        clearly the events explain the frames again."""
        ...

    def confirm_still(self, pairs: Sequence[FramePair], c: tuple[float, float],
                      floor: tuple[float, float]) -> float | None:
        """z of the floor against c on a new pair: confirms a "still scene" verdict (needs_pair estimators)."""
        ...

    def information(self, pairs: Sequence[FramePair], c: tuple[float, float]) -> float | None:
        """How clearly an estimate c beats c*(1 -+ step), in standard errors; None when not measurable."""
        ...


@dataclass
class FixedContrast:
    c_on: float
    c_off: float
    name: str = "fixed"
    needs_pair: bool = False
    separate: bool = True
    needs_full_image: bool = False
    c_min: float = 0.0
    fit_z: float = math.inf
    info_z: float = 0.0

    def estimate(self, cur, pairs, c_init):
        return self.c_on, self.c_off

    def misfit(self, cur, pairs, c):
        return None

    def still_misfit(self, cur, pairs, floor, cached):
        return None

    def confirm_still(self, pairs, c, floor):
        return None

    def information(self, pairs, c):
        return None


