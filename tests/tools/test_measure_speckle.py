"""tools.measure_speckle: the outlier test (a pixel more than the threshold away from its 3x3 median) and the
event drop of the speckle experiment, against small hand-made cases."""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import EVENT_DTYPE
from tools.measure_speckle import drop_events, outliers


def test_an_isolated_dot_is_an_outlier_an_edge_is_not_and_borders_are_left_out():
    img = np.full((8, 10), 50, np.uint8)
    img[3, 4] = 80  # a dot: 30 DN above its neighbourhood's median
    img[5, 6] = 65  # 15 DN: below the threshold
    img[:, 8:] = 200  # an edge: the median follows it
    img[0, 2] = 255  # on the border
    out = outliers(img, 20)
    assert out.sum() == 1 and out[3, 4]


def test_only_unsupported_events_at_the_chosen_pixels_are_dropped():
    rows = [(1_000, 2, 2), (1_500, 3, 2),  # two neighbours within 5 ms: supported
            (20_000, 2, 2),  # alone at the chosen pixel: dropped
            (40_000, 6, 1)]  # alone elsewhere: kept unless every pixel is chosen
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, (t, x, y) in enumerate(rows):
        ev[i] = (t, x, y, True)
    chosen = np.zeros((4, 8), bool)
    chosen[2, 2] = True
    assert drop_events(ev, 8, 4, chosen, True)["t"].tolist() == [1_000, 1_500, 40_000]
    assert drop_events(ev, 8, 4, None, True)["t"].tolist() == [1_000, 1_500]
    assert drop_events(ev, 8, 4, chosen, False)["t"].tolist() == [1_500, 40_000]
