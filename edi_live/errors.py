"""The edi-live error hierarchy.

Every failure a user can cause or meet (bad flags, a corrupt file, an unplugged camera, a busy port) is one
of these, with a message written for the person at the terminal: what went wrong, where, and what to do.
The CLI prints `edi-live: error: <message>` and exits 2 for ConfigError, 1 for everything else.
Foreign exceptions (pyusb, zmq, lz4, ...) are translated at one boundary each and chained with `from`.
"""

from __future__ import annotations


class EdiLiveError(Exception):
    """Base class of every error edi-live raises on purpose."""

    exit_code = 1


class ConfigError(EdiLiveError):
    """Invalid options or configuration file: a usage error (exit code 2)."""

    exit_code = 2


class SourceError(EdiLiveError):
    """The input (camera or recording) failed."""


class DeviceNotFoundError(SourceError):
    pass


class DevicePermissionError(SourceError):
    pass


class DeviceBusyError(SourceError):
    pass


class UnsupportedFirmwareError(SourceError):
    pass


class DeviceDisconnectedError(SourceError):
    pass


class ProtocolError(SourceError):
    """The device answered something other than the protocol allows (expected vs read)."""


class RecordingError(SourceError):
    """An AEDAT4 file is unreadable, corrupt or truncated. The message names the file and byte offset."""

    def __init__(self, message: str, path: str | None = None, offset: int | None = None) -> None:
        where = ""
        if path is not None:
            where = f"{path}"
            if offset is not None:
                where += f" at byte {offset}"
            where += ": "
        super().__init__(where + message)
        self.path = path
        self.offset = offset


class PublishError(EdiLiveError):
    pass


class BindError(PublishError):
    pass


class ClientError(EdiLiveError):
    """A subscriber received a malformed or oversized message."""


class NodeError(EdiLiveError):
    """A node thread failed; the message names the thread."""


class OutputError(EdiLiveError):
    """A file edi-live writes at the end (a calibration) could not be written: a full disk, an I/O error."""


class ResourceError(EdiLiveError):
    """The process ran out of something the machine or its limits give it (memory, address space)."""
