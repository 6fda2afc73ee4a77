"""The node's files when the place they are written to goes away mid-run: every lost file is named."""

from __future__ import annotations

import logging
import shutil

import pytest

from edi_live.config import NodeConfig
from edi_live.errors import RecordingError
from edi_live.node import Node
from tests.edi_live.test_node import replay
from tests.edi_live.test_worker import StandIn


class FolderRemovedAfterFirstPacket:
    """A replay during which the output folder is removed (a clean-up job, `rm -rf` by hand)."""

    def __init__(self, source, folder):
        self.source, self.folder = source, folder

    def __getattr__(self, name):
        return getattr(self.source, name)

    def __enter__(self):
        self.source.__enter__()
        return self

    def __exit__(self, *exc):
        return self.source.__exit__(*exc)

    def __iter__(self):
        for k, packet in enumerate(self.source):
            yield packet
            if k == 0:
                shutil.rmtree(self.folder)


def test_out_and_record_both_lost_with_their_folder_are_both_named(real_recordings, tmp_path, caplog):
    path = real_recordings["evlib_sample_davis346.aedat4"]
    folder = tmp_path / "run"
    folder.mkdir()
    out, record = folder / "sharp.aedat4", folder / "raw.aedat4"
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, "out": str(out),
                                   "record": str(record)})
    source = FolderRemovedAfterFirstPacket(replay(path, speed=0), folder)
    node = Node(cfg, source, reconstructor_factory=lambda w, h, e: StandIn())
    with caplog.at_level(logging.WARNING, logger="edi_live"), pytest.raises(RecordingError) as info:
        node.run()
    said = [str(info.value)] + [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    for lost in (out, record):
        assert any(str(lost) in line and "no longer there" in line for line in said), (lost, said)


def test_a_start_up_failure_with_save_calibration_is_one_line_not_also_nothing_to_save(real_recordings, tmp_path,
                                                                                         caplog):
    """--out that cannot be created (a missing folder) ended the start-up, and --save-calibration then also logged
    "nothing to save ...: 0 APS frame(s) deblurred" before the error line: a second, misleading line for a run that
    never started."""
    path = real_recordings["evlib_sample_davis346.aedat4"]
    out, saved = tmp_path / "missing" / "sharp.aedat4", tmp_path / "cal.json"
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, "out": str(out),
                                   "save_calibration": str(saved)})
    node = Node(cfg, replay(path, speed=0), reconstructor_factory=lambda w, h, e: StandIn())
    with caplog.at_level(logging.WARNING, logger="edi_live"), pytest.raises(RecordingError) as info:
        node.run()
    assert str(out) in str(info.value)
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []
    assert not saved.exists()
