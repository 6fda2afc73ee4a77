"""tools.measure_prediction on recordings that give it nothing to score: the user is told why, per file."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.aedat4 import Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, Frame
from tools import measure_prediction


def _recording(path, n_frames: int) -> None:
    """346x260: 2000 events over 0.2 s at one pixel, and `n_frames` APS frames 50 ms apart before them."""
    t0 = 1_000_000
    with Aedat4Writer(path, 346, 260) as w:
        for i in range(n_frames):
            start = t0 + 50_000 * i
            w.write_frame(Frame(np.full((260, 346), 100, np.uint8), start, start + 10_000, start, start + 10_000, i))
        ev = np.zeros(2000, EVENT_DTYPE)
        ev["t"] = t0 + 50_000 * n_frames + np.arange(2000) * 100
        ev["x"], ev["y"], ev["p"] = 7, 5, 1
        w.write_events(ev)


# A recording without APS frames printed a row of dashes ("0/0  -  -  -") and exit 0, nothing else: it looked
# like a broken tool, not like a recording the figure cannot be computed on.
@pytest.mark.parametrize("n_frames, why", [(0, "holds no APS frames"), (1, "none of its 1 APS frame(s)")])
def test_a_recording_with_nothing_to_score_is_said_by_name(tmp_path, capsys, n_frames, why):
    path = tmp_path / f"frames{n_frames}.aedat4"
    _recording(path, n_frames)
    assert measure_prediction.main([str(path)]) == 0
    out, err = capsys.readouterr()
    assert f"frames{n_frames}.aedat4" in out  # its row is still printed
    notes = [line for line in err.splitlines() if str(path) in line]
    assert len(notes) == 1 and "nothing scored" in notes[0] and why in notes[0], err


# A node option before the files took its value for a file name: '--c 0.3 FILE' replayed '0.3' with a bare '--c'
# and ended in "argument --c: expected one argument", while 'FILE --c 0.3' worked.
@pytest.mark.parametrize("order", ["options first", "files first"])
def test_node_options_keep_their_values_before_or_after_the_files(real_recordings, capsys, order):
    path = str(real_recordings["evlib_sample_davis346.aedat4"])
    options = ["--c", "0.3", "--every=500"]
    argv = options + [path] if order == "options first" else [path] + options
    assert measure_prediction.main(argv) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "node options: --c 0.3 --every=500" in out
    row = next(line for line in out.splitlines() if line.startswith("evlib_sample_davis346.aedat4"))
    assert row.split()[1:3] == ["0.300", "0.300"]  # the thresholds given, not the estimate
