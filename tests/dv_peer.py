"""dv-processing as the reference peer of edi-live's DV network code, run as a separate process.

It must be a process of its own: dv-processing's blocking calls (NetworkReader's constructor waits for the
IOHeader) hold the GIL, so in the test's process they would starve the Python server they wait for.

    python tests/dv_peer.py read HOST PORT N            NetworkReader: print the stream info, then N frames or
                                                        event batches as JSON lines, then exit (= disconnect)
    python tests/dv_peer.py serve KIND FILE [--port P] [--wait-clients K] [--hold-s S] [--size WxH]
                                                        [--pace-s S] [--go-file F] [--exit-file F]
                                                        NetworkWriter serving one stream KIND (events | frames |
                                                        imu | triggers) of a real recording, read with
                                                        dv-processing's own MonoCameraRecording; prints
                                                        {"port": P} once bound, {"done": n} when all is written
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time

import dv_processing as dv


def _print(obj: dict) -> None:
    print(json.dumps(obj), flush=True)


def read(host: str, port: int, n: int, timeout_s: float = 20.0) -> None:
    reader = dv.io.NetworkReader(host, port)
    frames = reader.isFrameStreamAvailable()
    res = reader.getFrameResolution() if frames else reader.getEventResolution()
    _print({"camera": reader.getCameraName(), "frames": frames, "events": reader.isEventStreamAvailable(),
            "resolution": list(res) if res is not None else None})
    got, deadline = 0, time.monotonic() + timeout_s
    while got < n and time.monotonic() < deadline and reader.isRunning():
        if frames:
            f = reader.getNextFrame()
            if f is None:
                time.sleep(0.002)
                continue
            _print({"t": f.timestamp, "shape": list(f.image.shape), "source": f.source.name,
                    "exposure_us": round(f.exposure.total_seconds() * 1e6), "pixel_sum": int(f.image.sum())})
        else:
            batch = reader.getNextEventBatch()
            if batch is None:
                time.sleep(0.002)
                continue
            ev = batch.numpy()
            _print({"n": len(ev), "t0": int(ev["timestamp"][0]), "t1": int(ev["timestamp"][-1]),
                    "xsum": int(ev["x"].astype("i8").sum())})
        got += 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve(kind: str, path: str, port: int, wait_clients: int, hold_s: float, size: str | None,
          pace_s: float, go_file: str | None = None, exit_file: str | None = None) -> None:
    rec = dv.io.MonoCameraRecording(path)
    camera = rec.getCameraName()
    res = tuple(int(v) for v in size.split("x")) if size else rec.getEventResolution()
    stream = {"events": lambda: dv.io.Stream.EventStream(0, "events", camera, res),
              "frames": lambda: dv.io.Stream.FrameStream(0, "frames", camera, res),
              "imu": lambda: dv.io.Stream.IMUStream(0, "imu", camera),
              "triggers": lambda: dv.io.Stream.TriggerStream(0, "triggers", camera)}[kind]()
    port = port or _free_port()
    writer = dv.io.NetworkWriter("127.0.0.1", port, stream)
    _print({"port": port})
    deadline = time.monotonic() + 30
    while writer.getClientCount() < wait_clients and time.monotonic() < deadline:
        time.sleep(0.005)
    while go_file and not os.path.exists(go_file) and time.monotonic() < deadline + 30:
        time.sleep(0.01)
    n = 0
    get, put = {"events": (rec.getNextEventBatch, writer.writeEvents),
                "frames": (rec.getNextFrame, writer.writeFrame),
                "imu": (rec.getNextImuBatch, writer.writeImu),
                "triggers": (rec.getNextTriggerBatch, writer.writeTriggers)}[kind]
    while True:
        item = get()
        if item is None:
            break
        put(item)
        n += 1
        if pace_s:
            time.sleep(pace_s)
    deadline = time.monotonic() + 10  # let the IO thread send everything before reporting
    while writer.getQueuedPacketCount() and time.monotonic() < deadline:
        time.sleep(0.005)
    _print({"done": n})
    if exit_file:  # the client says when it has everything: what the writer still buffers would die with us
        deadline = time.monotonic() + 60
        while not os.path.exists(exit_file) and time.monotonic() < deadline:
            time.sleep(0.01)
    else:
        time.sleep(hold_s)
    # the end of a DV instance: the OS closes every connection. (Destroying a NetworkWriter right as a client
    # leaves can hang in dv-processing 2.0.4, so the destructor is not used.)
    os._exit(0)


def main() -> None:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("read")
    r.add_argument("host")
    r.add_argument("port", type=int)
    r.add_argument("n", type=int)
    s = sub.add_parser("serve")
    s.add_argument("kind", choices=("events", "frames", "imu", "triggers"))
    s.add_argument("file")
    s.add_argument("--port", type=int, default=0)
    s.add_argument("--wait-clients", type=int, default=1)
    s.add_argument("--hold-s", type=float, default=0.5)
    s.add_argument("--size")
    s.add_argument("--pace-s", type=float, default=0.0)
    s.add_argument("--go-file", help="start writing once this file exists")
    s.add_argument("--exit-file", help="after writing, end once this file exists (not after --hold-s)")
    a = p.parse_args()
    if a.cmd == "read":
        read(a.host, a.port, a.n)
    else:
        serve(a.kind, a.file, a.port, a.wait_clients, a.hold_s, a.size, a.pace_s, a.go_file, a.exit_file)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
