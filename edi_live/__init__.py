"""edi-live: real-time Event-based Double Integral (EDI) deblurring for DAVIS event cameras.

Data flows one way: driver (drivers/) -> ring buffer -> EDI worker -> ZeroMQ publisher.
Importing this package loads only numpy: no zmq, usb or cv2 at import time.
"""

# first: where numba may keep compiled kernels must be settled before any kernel module is imported
from edi_live import kernel_cache as _kernel_cache  # noqa: F401
from edi_live.datatypes import (
    EVENT_DTYPE,
    IMU_DTYPE,
    TRIGGER_DTYPE,
    Frame,
    Packet,
    Reconstruction,
    SourceInfo,
    SourceStatus,
)
from edi_live.errors import (
    ClientError,
    ConfigError,
    EdiLiveError,
    NodeError,
    RecordingError,
    SourceError,
)

__version__ = "0.1.0"

__all__ = [
    "EVENT_DTYPE",
    "IMU_DTYPE",
    "TRIGGER_DTYPE",
    "Frame",
    "Packet",
    "Reconstruction",
    "SourceInfo",
    "SourceStatus",
    "ClientError",
    "ConfigError",
    "EdiLiveError",
    "NodeError",
    "RecordingError",
    "SourceError",
    "__version__",
]
