"""CPU time of this process's threads, read from Linux /proc: one reading of every thread (thread_cpu_seconds),
and ThreadCpu, which samples each named thread over a run for the benchmarks' CPU-by-thread figures."""

from __future__ import annotations

import os
import threading


def thread_cpu_seconds() -> dict[int, tuple[str, float]]:
    """{thread id: (OS thread name, user + system CPU seconds)} of this process (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[int, tuple[str, float]] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                head, rest = fh.read().rsplit(")", 1)
        except OSError:
            continue  # the thread ended meanwhile
        fields = rest.split()
        out[int(tid)] = (head.split("(", 1)[1], (int(fields[11]) + int(fields[12])) / tick)
    return out


class ThreadCpu:
    """Samples each named thread's CPU time from /proc (Linux), keeping the last value seen per thread."""

    def __init__(self, period_s: float = 0.1) -> None:
        self.cpu_s: dict[str, float] = {}  # by thread name (threads of the same name summed)
        self._per_thread: dict[str, float] = {}
        self._base: dict[str, float] = self._sample()
        self._stop = threading.Event()
        self._period_s = period_s
        self._thread = threading.Thread(target=self._run, name="cpu-sampler", daemon=True)

    def __enter__(self) -> "ThreadCpu":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(2)

    @staticmethod
    def _sample() -> dict[str, float]:
        """CPU s per thread of this process: Python threads by name, libzmq's I/O thread and others by OS name."""
        python_names = {t.native_id: t.name for t in threading.enumerate()}
        return {f"{python_names.get(tid, name)}/{tid}": cpu_s for tid, (name, cpu_s) in thread_cpu_seconds().items()}

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            for key, total_s in self._sample().items():
                self._base.setdefault(key, total_s)  # threads started meanwhile count from their first sample
                self._per_thread[key] = total_s - self._base[key]
            by_name: dict[str, float] = {}
            for key, v in self._per_thread.items():
                name = key.rsplit("/", 1)[0]
                by_name[name] = by_name.get(name, 0.0) + v
            self.cpu_s = by_name

    def split(self) -> str:
        keep = {k: v for k, v in self.cpu_s.items()
                if k in ("pump", "edi-worker", "edi-deblur", "publisher", "MainThread") or k.startswith("ZMQbg/IO")}
        total = sum(keep.values()) or 1.0
        return ", ".join(f"{k} {v:.2f} s ({100 * v / total:.0f}%)" for k, v in sorted(keep.items(),
                                                                                      key=lambda kv: -kv[1]))
