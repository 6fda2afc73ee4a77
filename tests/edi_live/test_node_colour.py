"""The node hands a colour source's Bayer pattern to the reconstructor, and --gray through to it."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.config import NodeConfig
from edi_live.datatypes import Packet, SourceInfo
from edi_live.node import Node, default_reconstructor
from edi_live.simulation import SceneConfig, simulate
from tests.edi_live.test_node import BurstSource


def _packets(sim) -> list[Packet]:
    out, lo = [], -1
    for f in sim.frames:
        ev = sim.events[(sim.events["t"] > lo) & (sim.events["t"] <= f.exposure_end_us)]
        out.append(Packet(events=ev, frames=[f]))
        lo = f.exposure_end_us
    return out


@pytest.mark.parametrize("gray, mode", [(False, "causal"), (True, "causal"), (False, "nearest"), (False, "fused")])
def test_a_colour_source_gives_colour_frames_unless_gray(gray, mode):
    sim = simulate(SceneConfig(width=32, height=24, duration_s=0.2, color_filter="GBRG", velocity_px_s=(100.0, 20.0)))
    # the source says colour; its frames here carry no pattern, so only the node's hand-over can make them colour
    frames_plain = [type(f)(f.image, f.exposure_start_us, f.exposure_end_us) for f in sim.frames]
    sim.frames[:] = frames_plain
    source = BurstSource(_packets(sim), width=32, height=24)
    source.info = SourceInfo(32, 24, "colour burst", kind="usb", color_filter="GBRG")
    made = []

    def factory(w, h, edi):
        made.append(default_reconstructor(w, h, edi))
        return made[-1]

    options = {"device": "auto", "no_publish": True, "every": 200, "mode": mode, **({"gray": True} if gray else {})}
    Node(NodeConfig.from_options(options), source, reconstructor_factory=factory).run()
    rec = made[-1]
    assert rec.settings.color_filter == "GBRG" and rec.settings.gray == gray
    assert rec.render().image.shape == ((24, 32) if gray else (24, 32, 3))
    assert np.asarray(rec.render().image).dtype == np.uint8


def test_bayer_pattern_option_reads_a_grey_stored_mosaic_as_colour(caplog):
    """A raw mosaic stored as grey frames (a recording that lost its pattern) becomes colour with --bayer-pattern;
    the user's pattern wins over the source's, said aloud when they differ (a typo gave wrong colours unsaid)."""
    sim = simulate(SceneConfig(width=32, height=24, duration_s=0.2, color_filter="GRBG", velocity_px_s=(100.0, 20.0)))
    sim.frames[:] = [type(f)(f.image, f.exposure_start_us, f.exposure_end_us) for f in sim.frames]
    made = []

    def factory(w, h, edi):
        made.append(default_reconstructor(w, h, edi))
        return made[-1]

    for source_pattern in (None, "BGGR", "GRBG"):
        source = BurstSource(_packets(sim), width=32, height=24)
        source.info = SourceInfo(32, 24, "raw burst", kind="usb", color_filter=source_pattern)
        options = {"device": "auto", "no_publish": True, "every": 200, "bayer_pattern": "grbg"}
        caplog.clear()
        with caplog.at_level("WARNING", logger="edi_live"):
            Node(NodeConfig.from_options(options), source, reconstructor_factory=factory).run()
        assert made[-1].settings.color_filter == "GRBG"
        assert made[-1].render().image.shape == (24, 32, 3)
        said = [r.getMessage() for r in caplog.records if "--bayer-pattern" in r.getMessage()]
        assert said == (["--bayer-pattern GRBG replaces the BGGR pattern raw burst names: its colours will be wrong "
                         "unless the source is mistaken"] if source_pattern == "BGGR" else []), said


def test_an_unknown_bayer_pattern_is_a_usage_error():
    from edi_live.errors import ConfigError
    with pytest.raises(ConfigError, match="bayer-pattern must be one of RGGB, GRBG, GBRG, BGGR"):
        NodeConfig.from_options({"device": "auto", "bayer_pattern": "RGBG"})


def test_a_source_of_bgr_frames_that_names_no_pattern_is_summarised_as_colour():
    """DV's demosaiced recordings name no pattern: their BGR frames turn the reconstructor colour at the first frame.
    The summary's camera line went by the source's pattern only, so such a run never said it was colour."""
    from edi_live.cli import colour_line
    from edi_live.colour import demosaic

    sim = simulate(SceneConfig(width=32, height=24, duration_s=0.2, color_filter="RGGB",
                               velocity_px_s=(100.0, 20.0)))
    grey_frames = [type(f)(f.image, f.exposure_start_us, f.exposure_end_us) for f in sim.frames]
    bgr_frames = [type(f)(demosaic(f.image, "RGGB"), f.exposure_start_us, f.exposure_end_us) for f in sim.frames]
    assert bgr_frames[0].image.shape == (24, 32, 3)
    finals = {}
    for kind, frames in (("bgr", bgr_frames), ("grey", grey_frames)):
        sim.frames[:] = frames
        source = BurstSource(_packets(sim), width=32, height=24)
        source.info = SourceInfo(32, 24, "dv file", kind="replay")  # no color_filter
        finals[kind] = Node(NodeConfig.from_options({"device": "auto", "no_publish": True, "every": 200}),
                            source).run()
    assert finals["bgr"]["bayer_pattern"] == "RGGB"  # the DAVIS346 colour default the re-mosaic uses
    assert "bayer_pattern" not in finals["grey"]  # a grey run's stats are unchanged
    info = SourceInfo(32, 24, "dv file", kind="replay")
    assert colour_line(info, None, finals["bgr"].get("bayer_pattern")) == (
        "  camera: dv file 32x24, colour (RGGB Bayer mosaic, the source's BGR frames re-mosaiced)")
    assert colour_line(info, None, finals["grey"].get("bayer_pattern")) is None
    named = SourceInfo(32, 24, "cam", color_filter="GBRG")
    assert colour_line(named) == "  camera: cam 32x24, colour (GBRG Bayer mosaic)"
    assert colour_line(info, "BGGR", "BGGR") == (
        "  camera: dv file 32x24, colour (BGGR Bayer mosaic given by --bayer-pattern)")
