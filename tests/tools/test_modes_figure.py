"""tools.modes_figure's interval picture and speckle figure, on frames built here."""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import Frame
from tools.modes_figure import interval_row, speckle_line


def _flat(t: int, dots: int = 0, value: int = 100) -> Frame:
    img = np.full((40, 60), value, np.uint8)
    img.reshape(-1)[np.arange(dots) * 37 + 61] = 250  # isolated bright pixels, away from the border
    return Frame(img, t, t)


def test_the_speckle_share_counts_the_isolated_dots_of_the_frames_after_each_exposure():
    aps = [Frame(np.full((40, 60), 100, np.uint8), k * 40_000, k * 40_000 + 20_000) for k in range(4)]
    # latent frames every ms; the ones 10 ms after an exposure end carry 6 dots, 20 ms: 12, 30 ms: none
    frames = [_flat(t, dots={10_000: 6, 20_000: 12}.get((t - 20_000) % 40_000, 0)) for t in range(0, 160_000, 1000)]
    line = speckle_line(frames, aps, "causal")
    pixels = 40 * 60
    assert line == (f"causal: +10 ms {600 / pixels:.3f} %, +20 ms {1200 / pixels:.3f} %, +30 ms 0.000 % "
                    "speckle pixels")


def test_the_interval_row_shows_five_times_cropped_to_where_the_frames_change():
    aps = [Frame(np.full((120, 160), 100, np.uint8), 0, 20_000), Frame(np.full((120, 160), 100, np.uint8), 40_000, 60_000)]
    aps[1].image[50:60, 70:80] = 10  # a dark square appeared: the crop is around it
    frames = [_flat(t) for t in range(0, 60_000, 500)]
    row = interval_row(frames, aps, 0, "fused", 1.0)
    assert row.ndim >= 2 and row.shape[0] == 200 and row.shape[1] > 5 * 100
