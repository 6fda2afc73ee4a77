"""The realistic-camera benchmark (tools/bench_realistic.py): its oracle undoes the true camera, and its scores
are taken in the camera's tone."""

from __future__ import annotations

import numpy as np

from edi_live.simulation import simulate
from tools import accuracy_harness as harness
from tools import accuracy_methods as methods
from tools import bench_accuracy as ba
from tools import bench_realistic as br


def _tiny(**kw):
    from edi_live.simulation import preset
    return preset("translate", width=64, height=48, duration_s=0.2, frame_interval_us=40_000, exposure_us=20_000,
                  velocity_px_s=(150.0, 30.0), latent_per_interval=2, seed=3, **kw)


def test_oracle_inputs_undo_the_true_camera():
    from edi_live.simulation import with_effects
    ideal = simulate(_tiny())
    real = simulate(with_effects(_tiny(), "clock_offset", "black_level", "response", "hot_pixels"))
    ev, frames = br.oracle_inputs(real)
    hot = {tuple(xy) for xy in real.hot_pixel_xy}
    assert hot and not any((int(e["x"]), int(e["y"])) in hot for e in ev)
    keep = np.array([(int(x), int(y)) not in hot for x, y in zip(ideal.events["x"], ideal.events["y"])])
    signal = ideal.events[keep]
    np.testing.assert_array_equal(ev["t"][: signal.size], signal["t"])  # back on the APS clock
    for (b, informative), lin in zip(frames, real.aps_linear):
        assert np.abs(b - lin)[informative].max() < 0.6  # linear again, up to 8-bit rounding


def test_oracle_camera_is_plain_edi_on_an_ideal_camera_and_wins_on_a_real_one():
    ideal = simulate(_tiny())
    a, b = br.run_oracle_camera(ideal), methods.run_edi_functions(ideal)
    for g in a.deblurred:
        np.testing.assert_allclose(a.deblurred[g][0], b.deblurred[g][0], rtol=1e-6)
    from edi_live.simulation import with_effects
    real = simulate(with_effects(_tiny(), "black_level", "response", "clock_offset"))
    oracle = harness.score(real, br.run_oracle_camera(real))
    default = harness.score(real, harness.run_reconstructor(real))
    assert oracle.psnr_deblur > default.psnr_deblur + 3.0 and oracle.psnr_latent > default.psnr_latent


def test_realistic_section_runs_quick(capsys):
    assert ba.main(["--realistic", "--quick"]) == 0  # bench_accuracy hands over to bench_realistic
    out = capsys.readouterr().out
    assert "default - oracle f / lat (dB)" in out and "given - oracle f / lat (dB)" in out
    assert "mean of the 2 mixed scenes" in out and "all effects" in out
    assert len([ln for ln in out.splitlines() if ln.startswith("| ") and "PSNR" not in ln]) == 4
    full = br.realistic_suite()
    from edi_live.simulation import EFFECTS
    assert sum(g == "mix" for g, _, _ in full) >= 5
    assert {lab.split(": ")[1] for g, lab, _ in full if g == "alone"} >= {f"{n} alone" for n in EFFECTS}


def test_tone_is_the_response_and_leaves_linear_methods_comparable():
    x = np.array([0.0, 10.0, 100.0, 255.0])
    np.testing.assert_allclose(br.tone(x, 1.15), 255.0 * (x / 255.0) ** (1 / 1.15))
    np.testing.assert_array_equal(br.tone(x, 1.0), x)
    from edi_live.simulation import linearise_aps, with_effects
    sim = simulate(with_effects(_tiny(), "response"))
    toned = br.in_camera_tone(sim)
    # the truth in the camera's tone is what the camera's APS reads for the sharp scene, before 8-bit rounding
    for g in range(len(sim.gt_images)):
        np.testing.assert_allclose(linearise_aps(sim.config, toned.gt_images[g]), sim.gt_images[g], rtol=1e-4,
                                   atol=1e-3)


def test_a_node_that_does_not_know_the_response_loses_only_in_linear_light():
    """The node's c absorbs the APS response, so its frames keep the camera's tone: scored there it is close to
    the oracle that knows gamma; in linear light it loses the tone curve. Per-pixel EDI on both sides (the node's
    smoothed divisor would beat the oracle by ~3 dB here, whatever the response)."""
    from edi_live.simulation import with_effects
    sim = simulate(with_effects(_tiny(), "response"))
    gamma = float(sim.camera()["aps_gamma"])
    node, oracle = harness.run_reconstructor(sim, divisor_median=False), br.run_oracle_camera(sim)
    toned = br.in_camera_tone(sim)
    tone_gap = harness.score(toned, node).psnr_deblur - harness.score(toned, br.toned(oracle, gamma)).psnr_deblur
    linear_gap = harness.score(sim, node).psnr_deblur - harness.score(sim, oracle).psnr_deblur
    assert abs(tone_gap) < 1.0
    assert linear_gap < -3.0


def test_calibrated_run_starts_from_what_a_first_run_of_the_same_camera_saved():
    """The 'calibrated' column: a first run of the same camera on another scene is saved and loaded as the node
    does it (--save-calibration, --calibration), so a black level that the scored scene cannot show (flat blocks,
    no dark pixel) comes from the calibration scene, which has dark pixels."""
    from edi_live.reconstructor import EdiReconstructor
    from edi_live.simulation import preset, with_effects
    cfg = with_effects(preset("translate", texture="blocks", duration_s=0.3, velocity_px_s=(200.0, 50.0), seed=5,
                              latent_per_interval=1), "black_level")
    real = simulate(cfg)
    first = EdiReconstructor(cfg.width, cfg.height)
    harness.run_reconstructor(simulate(br.calibration_scene(cfg)), reconstructor=first)
    assert first.black_level > 0  # the calibration scene shows the black level
    out = br.run_calibrated(real)
    assert f"black {first.black_level:g} DN, offset {first.clock_offset_us} µs" in out.note
    assert harness.score(real, out).psnr_deblur > harness.score(real, harness.run_reconstructor(real)).psnr_deblur + 1.0
