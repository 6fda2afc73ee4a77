"""tools/bench_option.py: its KEY=VALUE parsing, and that the option reaches the reconstructor it compares."""

from __future__ import annotations

import pytest

from tools import bench_option as bo


def test_settings_parse_as_literals_with_toml_booleans():
    assert bo.parse_setting("latent_denoise=true") == ("latent_denoise", True)
    assert bo.parse_setting("divisor_median = False") == ("divisor_median", False)
    assert bo.parse_setting("denoise_us=5000") == ("denoise_us", 5000)
    assert bo.parse_setting("estimator=consistency") == ("estimator", "consistency")
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        bo.parse_setting("latent_denoise")


def test_the_option_reaches_the_runs_it_compares(monkeypatch):
    from edi_live.simulation import preset

    tiny = preset("translate", width=64, height=48, duration_s=0.2, frame_interval_us=40_000, exposure_us=20_000,
                  velocity_px_s=(150.0, 30.0), latent_per_interval=2, seed=3, c_sigma=0.03)
    monkeypatch.setattr(bo, "scene_suite", lambda quick: [("tiny", tiny), ("static tiny", tiny)])
    monkeypatch.setattr(bo, "realistic_suite", lambda quick: [("mix", "tiny real", tiny), ("alone", "x", tiny)])
    same = bo.compare({"latent_denoise": False}, log=lambda *_: None)
    assert same["ideal"][0] == same["ideal"][1] and same["ideal"][2] == same["ideal"][3]
    plain = bo.compare({"divisor_median": False}, log=lambda *_: None)  # per-pixel EDI at f: a different frame
    assert plain["ideal"][0] != plain["ideal"][1] and plain["realistic"][0] != plain["realistic"][1]
