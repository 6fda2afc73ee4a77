"""tools.bench_modes: the frame a latent frame derives from, found from its ref_t_us, also once the node has
moved its references into the event clock by an estimated clock offset."""

import numpy as np

from edi_live.simulation import preset, simulate
from tools.bench_modes import reference_index, score_scene


def test_reference_index_finds_the_frame_across_a_clock_offset():
    mids = np.arange(10, dtype=np.int64) * 50_000 + 1_700_000_000_025_000
    truth = np.array([0, 0, 3, 4, 7, 9, 9])
    offsets = np.array([0, 3_541, -2_000, 9_999, -9_999, 0, 4_000])
    np.testing.assert_array_equal(reference_index(mids, mids[truth] + offsets), truth)


def test_score_scene_scores_runs_with_c_estimated():
    # events 2 ms late: with c estimated the node also estimates the clock offset, and its latent frames' ref_t_us
    # then sit 2 ms off the simulator's mid-exposures (the lookup by equality raised IndexError here)
    sim = simulate(preset("translate", duration_s=0.5, event_offset_us=2000))
    res = score_scene("translate", sim, every=2000, modes=("causal",), estimate_c=(0,), log=lambda _: None)
    row = res["causal, c est. K=0"]
    assert row["frames"] > 0
    assert row["wait_max_ms"] == 0.0  # a causal frame never waits for a later APS frame
    assert np.isfinite(row["psnr_own_oracle_truth"])
