"""tools.thread_cpu: the benchmarks' CPU-by-thread line names every thread of the node that does its work."""

from __future__ import annotations

from tools.thread_cpu import ThreadCpu


def test_the_split_counts_the_deblur_helper_which_runs_the_deblurs_and_their_calibration():
    threads = ThreadCpu()  # (not started: the figures are set here)
    threads.cpu_s = {"edi-worker": 3.0, "edi-deblur": 1.0, "cpu-sampler": 9.0}
    line = threads.split()
    assert "edi-deblur 1.00 s (25%)" in line and "edi-worker 3.00 s (75%)" in line
    assert "cpu-sampler" not in line
