"""tools/viewer_output.py: the viewer's MP4 and PNG files, on a temporary folder: frames of another size are left out
of the MP4 with one warning, a saved PNG is never overwritten, and a PNG cut short by a write error is removed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.tools.test_viewer import H, W, pattern
from tools import viewer_output as viewer


def test_frames_left_out_of_the_mp4_for_their_size_are_reported(tmp_path, caplog):
    """The MP4 keeps its first frame's size and skips others: it did so silently, the summary saying only
    'N saved' for fewer frames than received."""
    recorder = viewer.Recorder(tmp_path / "mixed.mp4", None, 30.0)
    small = np.zeros((24, 32), np.uint8)
    with caplog.at_level("INFO", logger="edi-live-viewer"):
        for seq, image in enumerate([pattern(0), small, pattern(2), small]):
            recorder.write({"seq": seq}, image)
        recorder.close()
    assert recorder.written == 2 and recorder.skipped_size == 2
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "32x24" in warnings[0] and f"{W}x{H}" in warnings[0], warnings
    cap = cv2.VideoCapture(str(tmp_path / "mixed.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2
    cap.release()


@pytest.mark.parametrize("shape", [(1, 100), (2, 1, 3)])
def test_a_first_frame_the_encoder_refuses_is_named_with_its_size(tmp_path, shape):
    # 'cannot open x.mp4 for MP4 (mp4v) writing' sent the user to look at a file and folder that were fine
    recorder = viewer.Recorder(tmp_path / "x.mp4", None, 30.0)
    size = f"{shape[1]}x{shape[0]}"
    with pytest.raises(viewer.EdiLiveError, match=f"writing of {size} frames \\(the size of frame 7, the first"):
        recorder.write({"seq": 7}, np.zeros(shape, np.uint8))
    recorder.close()


def test_png_never_overwrites_a_frame_already_saved(tmp_path, caplog):
    """A second recording into the same --png folder (or a node restarted mid-recording: its seq starts at 0
    again) overwrote the frames saved under the same numbers, without a word."""
    png_dir = tmp_path / "png"
    png_dir.mkdir()
    earlier = png_dir / "frame_000000001.png"
    cv2.imwrite(str(earlier), pattern(77))
    recorder = viewer.Recorder(None, png_dir, 30.0)
    with caplog.at_level("INFO", logger="edi-live-viewer"):
        recorder.write({"seq": 1}, pattern(1))
        recorder.write({"seq": 1}, pattern(2))  # the publisher restarted
    np.testing.assert_array_equal(cv2.imread(str(earlier), cv2.IMREAD_UNCHANGED), pattern(77))
    saved = {p.name: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in png_dir.glob("frame_*.png")}
    assert len(saved) == 3 and recorder.written == 2
    assert sorted(int(image[0, 0]) for image in saved.values()) == [1, 2, 77]
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "frame_000000001.png" in warnings[0], warnings


def test_a_png_cut_short_by_a_full_disk_is_removed(tmp_path, monkeypatch):
    # a disk that filled up mid-write left a truncated frame_SEQ.png, unreadable, among the good ones
    import builtins
    import errno

    class FullDisk:
        def __init__(self, path, mode):
            self._fh = builtins.open(path, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._fh.close()

        def write(self, data):
            self._fh.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")

    png_dir = tmp_path / "png"
    recorder = viewer.Recorder(None, png_dir, 30.0)
    recorder.write({"seq": 1}, pattern(1))
    monkeypatch.setattr(viewer, "open", FullDisk, raising=False)
    with pytest.raises(viewer.EdiLiveError, match="No space left"):
        recorder.write({"seq": 2}, pattern(2))
    assert [p.name for p in png_dir.iterdir()] == ["frame_000000001.png"]
