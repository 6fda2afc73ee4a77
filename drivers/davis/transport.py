"""The only place the driver touches pyusb: finding DAVIS devices through any pyusb backend, opening and
claiming interface 0, control transfers, bulk reads from endpoint 0x82, and the single translation of pyusb
exceptions into edi-live errors (permission, busy, disconnected, no libusb).
"""

from __future__ import annotations

import errno
from typing import Any

import usb.core
import usb.util

from drivers.davis import models, protocol as P
from drivers.udev import RULE_TEXT, RULES_FILE, install_command
from edi_live.errors import (DeviceBusyError, DeviceDisconnectedError, DevicePermissionError,
                             SourceError)

_DISCONNECT_ERRNOS = {errno.ENODEV, errno.EIO, errno.EPIPE, errno.ESHUTDOWN, errno.ENXIO}
_LIBUSB_NO_DEVICE, _LIBUSB_IO, _LIBUSB_PIPE = -4, -1, -9
NO_LIBUSB_HINT = ("libusb 1.0 was not found: install it (Debian/Ubuntu: sudo apt install libusb-1.0-0, macOS: "
                  "brew install libusb, Windows: see the pyusb docs) or pass --usb-backend MODULE:CALLABLE")


def permission_message(where: str) -> str:
    return (f"permission denied opening {where}: install the udev rule ({install_command()}, or copy "
            f"{RULES_FILE} to /etc/udev/rules.d/), then replug the camera. Rule: {RULE_TEXT}")


def translate(exc: BaseException, where: str) -> SourceError:
    """Turn a pyusb exception into one edi-live error naming the device and what to do."""
    if isinstance(exc, SourceError):
        return exc
    if isinstance(exc, usb.core.NoBackendError):
        return SourceError(NO_LIBUSB_HINT)
    code = getattr(exc, "errno", None)
    backend_code = getattr(exc, "backend_error_code", None)
    if code == errno.EACCES or code == errno.EPERM or backend_code == -3:
        return DevicePermissionError(permission_message(where))
    if code == errno.EBUSY or backend_code == -6:
        return DeviceBusyError(f"{where} is busy: another program (DV, jAER, ROS, another edi-live) has claimed it; "
                               "close that program or unplug and replug the camera")
    if code in _DISCONNECT_ERRNOS or backend_code in (_LIBUSB_NO_DEVICE, _LIBUSB_IO, _LIBUSB_PIPE):
        return DeviceDisconnectedError(f"{where} was disconnected ({exc}); check the cable, or run with --reconnect")
    return SourceError(f"USB error on {where}: {exc}")


def find_davis(backend: Any = None) -> list[Any]:
    """Every attached iniVation DAVIS (FX2 or FX3) visible through `backend` (None = pyusb's default)."""
    try:
        found = usb.core.find(find_all=True, backend=backend, idVendor=models.VENDOR_ID)
        return [d for d in found if d.idProduct in models.MODEL_BY_PID]
    except usb.core.USBError as exc:  # enumeration itself failed
        raise translate(exc, "the USB bus") from exc
    except usb.core.NoBackendError as exc:
        raise translate(exc, "the USB bus") from exc
    except Exception as exc:  # a backend (--usb-backend MODULE:CALLABLE) failing in its own way
        raise SourceError(f"listing the cameras on the USB bus failed in the USB backend "
                          f"({type(exc).__name__}: {exc})") from exc


def describe(dev: Any) -> str:
    return f"DAVIS {models.MODEL_BY_PID[dev.idProduct].name} at USB {dev.bus}:{dev.address}"


def read_serial(dev: Any) -> str:
    """The serial-number string (opens the device, so it can raise a permission error)."""
    try:
        if not dev.iSerialNumber:
            return f"TMP{(dev.bus or 0) * (dev.address or 0):05d}"
        return str(usb.util.get_string(dev, dev.iSerialNumber))[:8]
    except (usb.core.USBError, ValueError, NotImplementedError) as exc:
        raise translate(exc if isinstance(exc, usb.core.USBError) else
                        usb.core.USBError(str(exc), errno=errno.EACCES), describe(dev)) from exc


def read_register(dev: Any, module: int, param: int) -> int:
    """One configuration register of an unclaimed device (a vendor request on endpoint 0, as libcaer's discovery
    reads device facts before opening it for streaming)."""
    try:
        data = bytes(dev.ctrl_transfer(P.REQ_IN, P.VR_CONFIG, module, param, 4, timeout=1000))
        return P.unpack_value(data)
    except (usb.core.USBError, ValueError, NotImplementedError) as exc:
        raise translate(exc if isinstance(exc, usb.core.USBError) else usb.core.USBError(str(exc)),
                        describe(dev)) from exc


class UsbTransport:
    """An opened, claimed DAVIS: vendor requests on endpoint 0 and bulk reads on 0x82."""

    def __init__(self, dev: Any) -> None:
        self.dev = dev
        self.where = describe(dev)
        self._claimed = False
        try:
            try:
                if dev.is_kernel_driver_active(models.INTERFACE):
                    dev.detach_kernel_driver(models.INTERFACE)
            except (NotImplementedError, usb.core.USBError):
                pass  # not supported on this platform/backend, or not needed
            try:
                if dev.get_active_configuration().bConfigurationValue != models.CONFIGURATION:
                    dev.set_configuration(models.CONFIGURATION)
            except usb.core.USBError as exc:
                if getattr(exc, "errno", None) in (errno.EACCES, errno.EBUSY, errno.ENODEV):
                    raise
                dev.set_configuration(models.CONFIGURATION)
            usb.util.claim_interface(dev, models.INTERFACE)
            self._claimed = True
        except usb.core.USBError as exc:
            self.close()
            raise translate(exc, self.where) from exc

    @property
    def firmware_version(self) -> int:
        return int(self.dev.bcdDevice) & 0xFF

    def ctrl_out(self, request: int, value: int, index: int, data: bytes) -> None:
        try:
            n = self.dev.ctrl_transfer(0x40, request, value, index, data, timeout=1000)
        except usb.core.USBError as exc:
            raise translate(exc, self.where) from exc
        if n != len(data):
            raise DeviceDisconnectedError(f"{self.where}: vendor request 0x{request:02X} wrote {n} of {len(data)} "
                                          "bytes; replug the camera")

    def ctrl_in(self, request: int, value: int, index: int, length: int) -> bytes:
        try:
            return bytes(self.dev.ctrl_transfer(0xC0, request, value, index, length, timeout=1000))
        except usb.core.USBError as exc:
            raise translate(exc, self.where) from exc

    def clear_halt(self, endpoint: int = models.DATA_ENDPOINT) -> None:
        try:
            self.dev.clear_halt(endpoint)
        except usb.core.USBError as exc:
            raise translate(exc, self.where) from exc

    def read(self, size: int, timeout_ms: int) -> bytes | None:
        """One bulk read from 0x82; None on a timeout with no data (partial data is returned)."""
        try:
            return bytes(self.dev.read(models.DATA_ENDPOINT, size, timeout=timeout_ms))
        except usb.core.USBTimeoutError:
            return None
        except usb.core.USBError as exc:
            if getattr(exc, "errno", None) == errno.ETIMEDOUT or getattr(exc, "backend_error_code", 0) == -7:
                return None
            raise translate(exc, self.where) from exc

    def close(self) -> None:
        try:
            if self._claimed:
                usb.util.release_interface(self.dev, models.INTERFACE)
        except usb.core.USBError:
            pass  # the device may already be gone
        finally:
            self._claimed = False
            try:
                usb.util.dispose_resources(self.dev)
            except usb.core.USBError:
                pass
