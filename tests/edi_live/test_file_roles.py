"""edi_live.file_roles: keeping the files a run writes apart from those it reads, on paths that cannot be resolved."""

from __future__ import annotations

from pathlib import Path

import pytest

from edi_live.file_roles import check_apart, same_file


@pytest.fixture
def link_loop(tmp_path: Path) -> Path:
    a, b = tmp_path / "a.aedat4", tmp_path / "b.aedat4"
    a.symlink_to(b)
    b.symlink_to(a)
    return a


@pytest.mark.parametrize("flag", ["out", "record", "save-calibration"])
def test_a_symlink_loop_is_no_file_the_run_reads(tmp_path, link_loop, flag):
    """`--out LOOP` (a link that points at itself through another) ended in "internal error: RuntimeError: Symlink
    loop ... report it": resolving the path to compare it raised. A loop names no file, so it is apart from every
    one; opening it then fails with its own one-line error."""
    recording = tmp_path / "rec.aedat4"
    recording.write_bytes(b"x")
    assert not same_file(link_loop, recording) and not same_file(recording, link_loop)
    check_apart({"replay": recording}, {flag: link_loop, "out" if flag != "out" else "record": tmp_path / "o"})
