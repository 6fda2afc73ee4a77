"""Event-camera sources for edi-live: the live DAVIS driver over pyusb, its emulator, and AEDAT4 replay.

Drivers know nothing of EDI, the ring buffer or ZeroMQ; they yield `edi_live.datatypes.Packet`s.
Submodules are imported lazily, so `import drivers` does not load pyusb.
"""

from __future__ import annotations

from typing import Any

SOURCE_KINDS = ("replay", "davis240", "davis346", "auto", "dv")


def open_source(kind: str, **options: Any) -> Any:
    """Build (not yet open) the `edi_live.source.Source` for `kind`.

    kind "replay": options `path` (required), `speed` (1.0 = real time, 0 = as fast as possible), `loop`.
    kind "davis240" | "davis346" | "auto": options `serial`, `backend` (a pyusb IBackend, e.g. the emulator's),
    `exposure_us`, `frame_interval_us`, `reconnect`, `policy` (passed to DavisSource).
    kind "dv": options `endpoints` (required; one per DV network output) and `reconnect` (DvNetworkSource).
    """
    if kind == "replay":
        from drivers.replay import ReplaySource

        path = options.pop("path")
        return ReplaySource(path, **options)
    if kind in ("davis240", "davis346", "auto"):
        from drivers.davis.device import DavisSource

        return DavisSource(kind, **options)
    if kind == "dv":
        from drivers.dv_network import DvNetworkSource

        return DvNetworkSource(options.pop("endpoints"), **options)
    raise ValueError(f"unknown source kind {kind!r} (expected one of {', '.join(SOURCE_KINDS)})")


def list_devices(backend: Any = None) -> list:
    """Every attached DAVIS camera (DeviceDescription items) seen through the pyusb `backend` (None = libusb)."""
    from drivers.davis.discovery import list_devices as _list_devices

    return _list_devices(backend)
