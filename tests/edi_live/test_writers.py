"""--out and --record writers: lossless, time-ordered, finalised after faults; dv-processing is the oracle."""

from __future__ import annotations

import dv_processing as dv  # the oracle from the test extra: a missing oracle fails, it does not skip
import numpy as np

from edi_live.datatypes import Reconstruction
from edi_live.writers import OutWriter, RecordWriter


def recon(t_us: int, value: int, kind: str = "latent", dtype=np.uint8) -> Reconstruction:
    img = np.full((6, 8), value, dtype)
    img[0, 0] = value // 2  # not constant, so a transposed or shifted image would show
    return Reconstruction(img, t_us, kind, t_us, t_us, t_us, 0.2, 0.2, 10)


def read_frames(path):
    rec = dv.io.MonoCameraRecording(str(path))
    frames = []
    while True:
        f = rec.getNextFrame()
        if f is None:
            break
        frames.append(f)
    return rec, frames


def test_out_frames_reopen_in_dv_processing_in_time_order(tmp_path):
    path = tmp_path / "sharp.aedat4"
    w = OutWriter(path, 8, 6, queue_items=2)  # tiny queue: submit must wait, never drop
    w.start()
    times = [1000, 1500, 2000, 1200, 2500, 3000]  # 1200: a deblurred frame after latent ones (causal mode)
    for i, t in enumerate(times):
        w.submit(recon(t, 10 + i, "deblurred" if t == 1200 else "latent"))
    w.close(timeout_s=10)
    rec, frames = read_frames(path)
    assert [f.timestamp for f in frames] == sorted(times)
    by_t = {t: 10 + i for i, t in enumerate(times)}
    for f in frames:
        img = f.image.squeeze()
        assert img.shape == (6, 8) and img.dtype == np.uint8
        assert img[1, 1] == by_t[f.timestamp] and img[0, 0] == by_t[f.timestamp] // 2
        assert f.exposure.total_seconds() == 0  # exposure start = end = t
        assert str(f.source).endswith("RECONSTRUCTION")
    assert w.stats()["out_frames"] == len(times) and w.stats()["out_late"] == 0


def test_out_keeps_a_deblurred_frame_that_comes_long_after_newer_latent_frames(tmp_path):
    # The worker's deblur thread: latent frames keep coming from the previous reference f0 while the next APS
    # frame (f1) is deblurred; in an unpaced run they reach far past f1 (here 250 ms, beyond the default
    # 100 ms reorder window), then the deblurred f1 arrives. It must be written, in time order, not dropped.
    f0, f1 = 0, 50_000
    sent = [Reconstruction(np.full((6, 8), 1, np.uint8), f0, "deblurred", f0, -5000, 5000, 0.2, 0.2, 10)]
    sent += [Reconstruction(np.full((6, 8), 2, np.uint8), t, "latent", f0, -5000, 5000, 0.2, 0.2, 10)
             for t in range(5_000, 300_001, 10_000)]
    sent.append(Reconstruction(np.full((6, 8), 3, np.uint8), f1, "deblurred", f1, 45_000, 55_000, 0.2, 0.2, 10))
    sent += [Reconstruction(np.full((6, 8), 4, np.uint8), t, "latent", f1, 45_000, 55_000, 0.2, 0.2, 10)
             for t in (310_000, 320_000)]
    path = tmp_path / "sharp.aedat4"
    w = OutWriter(path, 8, 6)
    w.start()
    for rec in sent:
        w.submit(rec)
    w.close(timeout_s=10)
    _, frames = read_frames(path)
    assert [f.timestamp for f in frames] == sorted(r.t_us for r in sent)
    assert w.stats()["out_late"] == 0 and w.stats()["out_frames"] == len(sent)
    assert [int(f.image.squeeze()[0, 0]) for f in frames if f.timestamp == f1] == [3]


def test_out_writer_fault_is_reported_and_the_file_still_finalised(tmp_path):
    path = tmp_path / "sharp.aedat4"
    errors = []
    w = OutWriter(path, 8, 6, on_error=errors.append, reorder_us=0)
    w.start()
    w.submit(recon(100, 50))
    w.submit(recon(200, 60))
    w.submit(recon(300, 70, dtype=np.float32))  # the AEDAT4 writer refuses float pixels
    w.submit(recon(400, 80))  # after the fault: must not hang
    w.close(timeout_s=10)
    assert len(errors) == 1
    rec, frames = read_frames(path)
    assert [f.timestamp for f in frames] == [100, 200]  # everything before the fault


def test_record_round_trip_of_a_real_recording(tmp_path, real_recordings):
    from drivers.replay import merged_packets

    src = real_recordings["evlib_sample_davis346.aedat4"]
    path = tmp_path / "raw.aedat4"
    w = RecordWriter(path, 346, 260, queue_items=4)
    w.start()
    n_events = n_frames = 0
    for packet in merged_packets(src):
        w.submit(packet)
        n_events += len(packet.events)
        n_frames += len(packet.frames)
    w.close(timeout_s=30)
    assert w.stats()["record_skipped"] == 0
    original = dv.io.MonoCameraRecording(str(src))
    copy = dv.io.MonoCameraRecording(str(path))

    def all_events(r):
        parts = []
        while (batch := r.getNextEventBatch()) is not None:
            parts.append(batch.numpy())
        return np.concatenate(parts)

    a, b = all_events(original), all_events(copy)
    assert len(b) == n_events
    np.testing.assert_array_equal(a["timestamp"], b["timestamp"])
    np.testing.assert_array_equal(a["x"], b["x"])
    np.testing.assert_array_equal(a["polarity"], b["polarity"])
    _, frames = read_frames(path)
    assert len(frames) == n_frames > 0


def test_out_writes_colour_reconstructions_as_colour_frames(tmp_path):
    import aedat

    path = tmp_path / "colour.aedat4"
    w = OutWriter(path, 8, 6)
    w.start()
    bgr = np.zeros((6, 8, 3), np.uint8)
    bgr[..., 0], bgr[..., 1], bgr[..., 2] = 30, 120, 210  # B, G, R
    bgr[0, 0] = (1, 2, 3)
    w.submit(Reconstruction(bgr, 1000, "latent", 1000, 1000, 1000, 0.2, 0.2, 10))
    w.close(timeout_s=10)
    _, (frame,) = read_frames(path)
    assert frame.image.shape == (6, 8, 3) and np.array_equal(frame.image, bgr)  # dv-processing: BGR
    (packet,) = list(aedat.Decoder(str(path)))
    assert packet["frame"]["format"] == "RGB" and np.array_equal(packet["frame"]["pixels"], bgr[..., ::-1])


def test_a_folder_removed_during_the_run_is_an_error_naming_the_file_not_a_silent_loss(tmp_path):
    import shutil

    from edi_live.errors import RecordingError

    folder = tmp_path / "run"
    folder.mkdir()
    errors = []
    w = OutWriter(folder / "sharp.aedat4", 8, 6, on_error=errors.append)
    w.start()
    w.submit(recon(1000, 10))
    shutil.rmtree(folder)  # as a clean-up job or a user might while the node runs
    w.submit(recon(2000, 20))  # writes into the open (now nameless) file still succeed
    w.close(timeout_s=10)
    assert not (folder / "sharp.aedat4").exists()
    assert len(errors) == 1 and isinstance(errors[0], RecordingError)
    assert str(folder / "sharp.aedat4") in str(errors[0]) and "no longer there" in str(errors[0])


def test_a_file_still_at_its_path_closes_without_an_error(tmp_path):
    errors = []
    w = OutWriter(tmp_path / "sharp.aedat4", 8, 6, on_error=errors.append)
    w.start()
    w.submit(recon(1000, 10))
    w.close(timeout_s=10)
    assert errors == [] and len(read_frames(tmp_path / "sharp.aedat4")[1]) == 1


_FULL_DISK = """
import resource, sys
import numpy as np
from edi_live.datatypes import Reconstruction
from edi_live.writers import OutWriter

resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))  # writes past 400 kB fail (EFBIG), as on a full disk
errors = []
w = OutWriter(sys.argv[1], 256, 192, on_error=errors.append, reorder_us=0)
w.start()
rng = np.random.default_rng(1)
for i in range(40):  # ~49 kB a frame (noise does not compress): the limit comes after 8, and the cut-off
    # frame frees far more room than the table of those 8 needs
    w.submit(Reconstruction(rng.integers(0, 255, (192, 256), dtype=np.uint8), 1000 * (i + 1), "latent",
                            0, 0, 0, 0.2, 0.2, 1))
w.close(timeout_s=30)
print(w.frames, type(errors[0]).__name__ if errors else "no error")
"""


def test_a_full_disk_keeps_every_frame_written_before_it_in_a_finalised_file(tmp_path):
    # the failed packet stayed half-written and the table was never written: DV tools saw an interrupted file
    # ending in a broken packet, and --replay of a --record cut this way ended with a 'truncated' error (exit 1)
    import subprocess
    import sys
    from pathlib import Path

    path = tmp_path / "sharp.aedat4"
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", _FULL_DISK, str(path)], cwd=repo, capture_output=True, text=True,
                          timeout=60, env={"PYTHONPATH": str(repo), "PATH": "/usr/bin:/bin"})
    written, error = proc.stdout.split()
    assert error == "RecordingError", proc.stderr
    assert 0 < int(written) < 40
    rec, frames = read_frames(path)  # dv-processing reads it: a whole file, no broken packet at its end
    assert [f.timestamp for f in frames] == [1000 * (i + 1) for i in range(int(written))]
    from edi_live.aedat4 import Aedat4Reader

    with Aedat4Reader(path) as reader:
        assert reader.data_table() is not None and len(reader.data_table()) == int(written)
        assert sum(1 for _ in reader) == int(written)  # read to its end without a 'truncated' error
