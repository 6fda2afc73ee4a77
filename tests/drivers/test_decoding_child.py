"""drivers.decoding_child: the decoding forkserver and its children under the node's stop signals."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# a fresh interpreter, so that the forkserver is started here (the test process may have one running already)
_STOP_THE_STARTING_SERVER = """
import os, signal, sys
from multiprocessing import forkserver
from drivers import decoding_child

decoding_child.start_early()
server = forkserver._forkserver._forkserver_pid  # (CPython's) the server just spawned, still importing
for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # Ctrl-C, kill or hang-up of the whole group
    os.kill(server, sig)
child = decoding_child.DecodeProcess(sys.argv[1], 1_000, False)
try:
    print(sum(len(packet.events) for packet in child))
finally:
    child.close()
"""


def test_a_stop_signal_to_the_group_while_the_forkserver_starts_neither_kills_it_nor_prints_a_traceback(
        real_recordings):
    """Ctrl-C right after `edi-live --replay` started reached the decoding forkserver while it was still importing
    the decoder (it ignores SIGINT only after its preload): it died with a KeyboardInterrupt traceback on the
    node's stderr, and the replay warned "cannot start the decoding process (unexpected EOF)"."""
    from edi_live.aedat4 import Aedat4Reader

    path = real_recordings["evlib_sample_davis346.aedat4"]
    with Aedat4Reader(path) as reader:
        total = sum(len(events) for events in reader.events())
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-c", _STOP_THE_STARTING_SERVER, str(path)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout.split() == [str(total)]
