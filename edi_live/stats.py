"""Counters of a running node: the published stats map, the terminal status line and the final summary.

`collect()` merges the counters every stage exposes (source status, ring, worker, publisher, writers) into one
flat map with unit-suffixed keys. `Rates` turns running totals into per-second rates between two calls (one
instance per reader, so the publisher's once-a-second map and the status line do not disturb each other).
`StatusLine` draws one live line on a TTY (rewritten in place) or plain lines every few seconds otherwise.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, TextIO

import numpy as np

from edi_live import live_line


def collect(source: Any = None, ring: Any = None, worker: Any = None, publisher: Any = None,
            writers: tuple[Any, ...] = ()) -> dict[str, Any]:
    """One flat map of every counter; missing stages are skipped. Safe to call from any thread."""
    out: dict[str, Any] = {}
    src_dropped = 0
    if source is not None:
        try:
            st = source.status()
        except Exception:  # a source that cannot report must not take the stats down
            st = None
        if st is not None:
            out.update({f"source_{k}": v for k, v in dataclasses.asdict(st).items()})
            src_dropped = int(st.dropped_events)
    if ring is not None:
        out.update(ring.stats())
        out["events_in"] = ring.pushed_events
    if worker is not None:
        out.update(worker.stats())
    pub_dropped = 0
    if publisher is not None:
        ps = publisher.stats()
        pub_dropped = int(ps.get("dropped", 0))
        out.update({"frames_sent": ps.get("sent", 0), "publish_dropped": pub_dropped,
                    "frames_unsubscribed": ps.get("unsubscribed", 0),
                    "latency_p50_us": ps.get("latency_p50_us"), "latency_p99_us": ps.get("latency_p99_us")})
    for w in writers:
        if w is not None:
            out.update(w.stats())
    out["frames_out"] = out.get("frames_deblurred", 0) + out.get("frames_latent", 0)
    out["drops"] = src_dropped + out.get("ring_dropped_events", 0) + out.get("ring_dropped_frames", 0) + pub_dropped
    return out


class Rates:
    """Per-second rates of running totals between consecutive calls."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._last_t = clock()
        self._last: dict[str, float] = {}

    def update(self, totals: dict[str, float]) -> dict[str, float]:
        now = self._clock()
        dt = max(now - self._last_t, 1e-9)
        rates = {k: (v - self._last.get(k, 0)) / dt for k, v in totals.items()}
        self._last_t, self._last = now, dict(totals)
        return rates


def with_rates(stats: dict[str, Any], rates: Rates) -> dict[str, Any]:
    """`stats` plus events_per_s and frames_per_s since the previous call on `rates`."""
    r = rates.update({"events": stats.get("events_processed", 0), "frames": stats.get("frames_out", 0)})
    return {**stats, "events_per_s": round(r["events"], 1), "frames_per_s": round(r["frames"], 1)}


def _si(value: float) -> str:
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(value) >= scale:
            return f"{value / scale:.2f}{unit}"
    return f"{value:.0f}"


def _ms(value_us: float | None) -> str:
    return "-" if value_us is None else f"{value_us / 1000:.2f}ms"


def format_status(s: dict[str, Any]) -> str:
    """events/s, frames/s, c, latency p50/p99, drops, ring occupancy, camera values, prediction: one line."""
    c = s.get("c_on"), s.get("c_off")
    c_text = "c=-" if c[0] is None or c[0] != c[0] else (
        f"c={c[0]:.3f}" if abs(c[0] - c[1]) < 1e-9 else f"c_on={c[0]:.3f} c_off={c[1]:.3f}")
    return (f"{_si(s.get('events_per_s', 0))} ev/s  {s.get('frames_per_s', 0):.0f} fps  {c_text}  "
            f"latency p50 {_ms(s.get('latency_p50_us'))} p99 {_ms(s.get('latency_p99_us'))}  "
            f"drops {s.get('drops', 0)}  ring {100 * s.get('ring_occupancy', 0):.0f}%{_camera_short(s)}"
            f"{_prediction_short(s)}")


def _offset_text(s: dict[str, Any]) -> str:
    """How the offset in use came about: estimated, and then the camera's own part beside EDI's step lag."""
    if not s.get("clock_offset_estimated"):
        return ""
    if s.get("clock_offset_from_calibration"):
        return " (the saved calibration's, not yet confirmed)"
    physical = s.get("clock_offset_physical_us")
    if physical is None or physical == s.get("clock_offset_us", 0):
        return " (estimated)"
    return f" (estimated: the camera's {physical} µs + {s.get('clock_offset_us', 0) - physical} µs of step lag)"


def _black_level_text(s: dict[str, Any]) -> str:
    if s.get("black_level_from_calibration"):
        return " (the saved calibration's, not yet confirmed)"
    return " (estimated)" if s.get("black_level_estimated") else ""


def _camera_short(s: dict[str, Any]) -> str:
    """The camera values once they differ from an ideal camera's: black level and event clock offset; the pixels'
    noise rate (median, 99th percentile, noisy pixels) once estimated."""
    parts = []
    if s.get("black_level_dn"):
        parts.append(f"black {s['black_level_dn']:g} DN")
    if s.get("clock_offset_us"):
        parts.append(f"offset {s['clock_offset_us']} µs")
    if s.get("noise_hz_p50") is not None:
        parts.append(f"noise {s['noise_hz_p50']:.2g}/{s.get('noise_hz_p99', 0):.2g} Hz "
                     f"({s.get('noisy_pixels', 0)} noisy)")
    return "  " + "  ".join(parts) if parts else ""  # each its own field: a narrow terminal lays them out apart


def _noise_text(s: dict[str, Any]) -> str:
    """The summary's per-pixel noise figures, when there are any."""
    if s.get("noise_hz_p50") is None:
        return ""
    return (f"; noise per pixel {s['noise_hz_p50']:.3g} Hz median (ON {s.get('noise_on_hz_p50', 0):.3g}, OFF "
            f"{s.get('noise_off_hz_p50', 0):.3g}), {s.get('noise_hz_p99', 0):.3g} Hz p99, "
            f"{s.get('noisy_pixels', 0)} noisy pixels")


def _prediction_short(s: dict[str, Any]) -> str:
    if s.get("pred_psnr_db") is None or s.get("still_psnr_db") is None:
        return ""
    return f"  predicts {s['pred_psnr_db']:.1f} dB (still {s['still_psnr_db']:.1f})"


def _prediction_line(s: dict[str, Any]) -> str | None:
    """The summary's quality line: how well the output predicted the APS frames it had not seen yet."""
    if s.get("pred_psnr_db") is None or s.get("still_psnr_db") is None:
        return None
    active = ""
    if s.get("pred_psnr_active_db") is not None and s.get("still_psnr_active_db") is not None:
        active = f"; at pixels with events {s['pred_psnr_active_db']:.2f} against {s['still_psnr_active_db']:.2f} dB"
    beats = s.get("pred_beats_still_frac")
    beats_text = "" if beats is None else f", better in {100 * beats:.0f} % of them"
    return (f"  prediction of the next APS frame: {s['pred_psnr_db']:.2f} dB PSNR against {s['still_psnr_db']:.2f} dB "
            f"for 'nothing moved' over {s.get('pred_frames_scored', 0)} scored frames{beats_text}{active}")


def format_summary(s: dict[str, Any], elapsed_s: float) -> str:
    """The end-of-run report: totals, rates over the run (`elapsed_s`, without the kernel warm-up: that is the
    stats' warm_up_s, on a line of its own), c and its re-estimations, drops."""
    events = s.get("events_processed", 0)
    frames = s.get("frames_out", 0)
    el = max(elapsed_s, 1e-9)
    lines = [
        f"edi-live: done in {elapsed_s:.2f} s: {events} events ({_si(events / el)} ev/s), "
        f"{s.get('aps_frames_in', 0)} APS frames in, {frames} frames out "
        f"({s.get('frames_deblurred', 0)} deblurred"
        f"{' (' + str(s['deblurs_ahead']) + ' integrated ahead)' if s.get('deblurs_ahead') else ''}, "
        f"{s.get('frames_latent', 0)} latent, "
        f"{s.get('heartbeats', 0)} heartbeats; {frames / el:.0f} fps)",
        f"  c_on={s.get('c_on', float('nan')):.4f} c_off={s.get('c_off', float('nan')):.4f}, "
        f"re-estimated {s.get('reestimations', 0)} times, black level {s.get('black_level_dn', 0):g} DN"
        f"{_black_level_text(s)}, "
        f"clock offset {s.get('clock_offset_us', 0)} µs{_offset_text(s)}; "
        f"ignored pixels: hot {s.get('hot_pixels', 0)}, "
        f"unreliable {s.get('unreliable_pixels', 0)}, flicker {s.get('flicker_pixels', 0)}{_noise_text(s)}; "
        f"drops {s.get('drops', 0)} "
        f"(ring events {s.get('ring_dropped_events', 0)}, ring frames {s.get('ring_dropped_frames', 0)}, "
        f"publish {s.get('publish_dropped', 0)}, source events {s.get('source_dropped_events', 0)}); "
        f"skipped: static {s.get('skipped_static', 0)} (APS frames not deblurred: "
        f"{s.get('skipped_static_deblur', 0)}), max-fps {s.get('skipped_max_fps', 0)}",
    ]
    if s.get("source_dropped_bytes"):
        lines.append(f"  warning: the camera's USB reader dropped {s['source_dropped_bytes']} bytes of raw data that the "
                     f"host did not take in time ({s.get('source_gaps', 0)} gap(s) in the stream): the events and APS "
                     f"frames in them are lost (the reader's thread was starved of CPU: other load on the machine)")
    if events and not s.get("aps_frames_in"):
        lines.append(f"  warning: no APS frame arrived, so none of the {events} events became a frame: EDI needs the "
                     f"camera's APS frames (an events-only recording, or a camera without them, has none)")
    if not events and s.get("aps_frames_in"):
        lines.append(f"  warning: no event arrived, so APS frames went out as they came, not sharpened: "
                     f"{s.get('frames_out', 0)} of {s['aps_frames_in']} (those that changed, and one per heartbeat "
                     f"while none did); EDI needs the camera's events (a frames-only recording, or a camera whose "
                     f"DVS is off, has none)")
    if not events and not s.get("aps_frames_in"):
        lines.append("  warning: nothing arrived from the input (not one event or APS frame): an empty recording, or a "
                     "camera or stream that sent nothing before the stop")
    if s.get("ring_history_truncated"):
        lines.append(f"  warning: {s['ring_history_truncated']} exposure window(s) reached back past the ring's history "
                     f"(half of --ring-events): those APS frames were deblurred from part of their events; raise "
                     f"--ring-events")
    if s.get("warm_up_s"):
        lines.append(f"  start-up: EDI kernels compiled or loaded in {s['warm_up_s']:.2f} s (once per process, "
                     f"before the input opened; not counted in the time and rates above)")
    if "frames_sent" in s:
        latency = ""
        if s.get("latency_p99_us") is not None:
            latency = f"; last-interval latency p50 {_ms(s.get('latency_p50_us'))} p99 {_ms(s['latency_p99_us'])}"
        unsubscribed, unrendered = s.get("frames_unsubscribed", 0), s.get("frames_not_rendered", 0)
        nobody = f", {unsubscribed} not sent" if unsubscribed else ""
        nobody += f", {unrendered} latent frames not rendered" if unrendered else ""
        nobody += " (no subscriber)" if nobody else ""
        lines.append(f"  published {s['frames_sent']} frames{nobody}{latency}")
    if "frames_sent" not in s and s.get("frames_not_rendered"):
        lines.append(f"  {s['frames_not_rendered']} latent frames not rendered: nothing takes them (no publisher, "
                     f"no --out or --dv-output), and so no prediction figure")
    prediction = _prediction_line(s)
    if prediction is not None:
        lines.append(prediction)
    if s.get("nearest_added_latency_ms_p50") is not None:
        lines.append(f"  mode nearest: held-back frames waited {s['nearest_added_latency_ms_p50']:.2f} ms (p50)")
    if s.get("fused_added_latency_ms_p50") is not None:
        lines.append(f"  mode fused: frames waited {s['fused_added_latency_ms_p50']:.2f} ms (p50) for the next APS frame")
    if "out_frames" in s:
        late = f" ({s['out_late']} arrived too late for time order and were skipped)" if s.get("out_late") else ""
        lines.append(f"  --out frames written: {s['out_frames']}{late}")
    if "record_events" in s:
        skipped = f" ({s['record_skipped']} items skipped)" if s.get("record_skipped") else ""
        lines.append(f"  --record events written: {s['record_events']}{skipped}")
    return "\n".join(lines)


class StatusLine:
    """A live status line on a TTY (redrawn in place every `interval_s`, edi_live/live_line.py), plain lines
    otherwise."""

    def __init__(self, stream: TextIO, interval_s: float | None = None, tty: bool | None = None) -> None:
        self.stream: TextIO | None = stream
        self.tty = bool(tty if tty is not None else getattr(stream, "isatty", lambda: False)())
        self.interval_s = interval_s if interval_s is not None else (0.5 if self.tty else 5.0)
        self._next = time.monotonic() + self.interval_s
        self._rates = Rates()
        self._last: str | None = None

    def maybe_draw(self, stats_fn: Callable[[], dict[str, Any]]) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.interval_s
        line = format_status(with_rates(stats_fn(), self._rates))
        if self.tty:
            # laid out in rows of whole fields that fit the terminal (edi_live/live_line.py)
            self._write(live_line.redraw(line, live_line.columns(self.stream)))
            self._last = line
        else:
            self._write("edi-live: " + line + "\n")

    def finish(self) -> None:
        """Leave the last live line on the screen, so the next output starts on a fresh line below it."""
        if self.tty and self._last is not None:
            self._write(live_line.end(self._last, live_line.columns(self.stream)))
            self._last = None

    def _write(self, text: str) -> None:
        """A stream that went away ('2>&1 | head', a closed terminal) ends the status, never the run."""
        if self.stream is None:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # BrokenPipeError, EIO; ValueError: the stream was closed
            self.stream = None


class LatencySamples:
    """Latency samples (µs) of the current stats interval, in a fixed-size buffer."""

    def __init__(self, size: int) -> None:
        self._buf = np.zeros(size, dtype=np.float64)
        self._n = 0

    def add(self, value_us: float) -> None:
        self._buf[self._n % len(self._buf)] = value_us
        self._n += 1

    def take(self) -> tuple[float | None, float | None]:
        """p50 and p99 of the samples since the last take (None when there were none), then reset."""
        n = min(self._n, len(self._buf))
        self._n = 0
        if n == 0:
            return None, None
        p50, p99 = np.percentile(self._buf[:n], [50, 99])
        return float(p50), float(p99)
