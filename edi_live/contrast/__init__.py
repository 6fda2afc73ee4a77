"""Contrast-threshold (c) estimators for EDI: the protocol the c policy talks to, fixed c, the paper's energy, and
frame-to-frame consistency (the default). Pure numpy/cv2 on the frames' level tables; no state beyond the
estimators' parameters (and a per-pair cache of the consistency set-up)."""

from __future__ import annotations

from edi_live.contrast.consistency import ConsistencyContrast
from edi_live.contrast.energy import EnergyContrast, event_map
from edi_live.contrast.frames import ContrastEstimator, FixedContrast, FrameData, FramePair
from edi_live.contrast.search import golden_section, grid_then_golden

ESTIMATORS = {"consistency": ConsistencyContrast, "energy": EnergyContrast}
DEFAULT_ESTIMATOR = "consistency"
def make_estimator(name: str, **kwargs) -> ContrastEstimator:
    """Estimator by name ('consistency', 'energy'); kwargs go to its constructor."""
    try:
        cls = ESTIMATORS[name]
    except KeyError:
        raise ValueError(f"unknown c estimator {name!r} (choose from {sorted(ESTIMATORS)})") from None
    return cls(**kwargs)



__all__ = ["ConsistencyContrast", "ContrastEstimator", "DEFAULT_ESTIMATOR", "ESTIMATORS", "EnergyContrast",
           "FixedContrast", "FrameData", "FramePair", "event_map", "golden_section", "grid_then_golden",
           "make_estimator"]
