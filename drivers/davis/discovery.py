"""Listing attached DAVIS cameras (`edi-live --list-devices`) and picking one by model and serial."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from drivers import udev
from drivers.davis import models, protocol as P, transport
from edi_live.datatypes import ColorFilter
from edi_live.errors import DeviceNotFoundError, DevicePermissionError, SourceError


@dataclass(frozen=True)
class DeviceDescription:
    """One attached camera as seen on the bus (before opening it for streaming)."""

    model: str            # "davis240" or "davis346" (from the USB product ID)
    product_id: int
    serial: str | None    # None when it could not be read (see `error`)
    bus: int | None
    address: int | None
    firmware_version: int
    error: str | None = None
    sensor: str | None = None  # "mono", "colour" or None when the colour-filter register could not be read
    color_filter: ColorFilter | None = None  # a colour sensor's Bayer pattern

    def __str__(self) -> str:
        s = f"{self.model} serial={self.serial or '?'} usb={self.bus}:{self.address} firmware={self.firmware_version}"
        if self.sensor == "colour":
            s += f" colour ({self.color_filter} Bayer)"
        elif self.sensor:
            s += f" {self.sensor}"
        return s + (f" ({self.error})" if self.error else "")


def _read_sensor(dev: Any) -> tuple[str | None, ColorFilter | None]:
    """("colour", pattern) or ("mono", None) from the APS colour-filter register, as libcaer's discovery reads it
    (a control transfer on endpoint 0, no interface claimed); (None, None) when the camera does not answer."""
    try:
        pattern = models.color_filter_of_code(transport.read_register(dev, P.APS, P.APS_COLOR_FILTER))
    except (SourceError, ValueError):
        return None, None
    return ("colour" if pattern else "mono"), pattern


def _describe(dev: Any) -> DeviceDescription:
    model = models.MODEL_BY_PID[dev.idProduct]
    serial, error = None, None
    try:
        serial = transport.read_serial(dev)
    except DevicePermissionError:
        error = f"permission denied: install the udev rule with {udev.install_command()}"
    except SourceError as exc:
        error = str(exc)
    sensor, pattern = _read_sensor(dev) if error is None else (None, None)
    return DeviceDescription(model.name, int(dev.idProduct), serial, dev.bus, dev.address,
                             int(dev.bcdDevice) & 0xFF, error, sensor, pattern)


def list_devices(backend: Any = None) -> list[DeviceDescription]:
    """Every attached DAVIS240/DAVIS346 visible through the pyusb `backend` (None = libusb)."""
    return [_describe(d) for d in transport.find_davis(backend)]


def select_device(model: str = "auto", serial: str | None = None, backend: Any = None) -> Any:
    """The pyusb device matching model ("auto", "davis240", "davis346") and serial; raises DeviceNotFoundError."""
    if model != "auto":
        models.get_model(model)
    devices = transport.find_davis(backend)
    candidates = [d for d in devices if model == "auto" or models.MODEL_BY_PID[d.idProduct].name == model]
    if serial is not None:
        matching = []
        for d in candidates:
            if transport.read_serial(d) == serial:
                matching.append(d)
        if not matching:
            seen = ", ".join(str(_describe(d)) for d in devices) or "none"
            raise DeviceNotFoundError(f"no {model if model != 'auto' else 'DAVIS'} camera with serial {serial} "
                                      f"(attached: {seen}); check --serial or run edi-live --list-devices")
        candidates = matching
    if not candidates:
        what = "DAVIS camera" if model == "auto" else f"{model} camera"
        other = f" (found only: {', '.join(str(_describe(d)) for d in devices)})" if devices else ""
        raise DeviceNotFoundError(f"no {what} found on USB{other}: check the cable and power, run "
                                  "edi-live --list-devices, or use --usb-backend drivers.emulator:backend to "
                                  "emulate one")
    return candidates[0]
