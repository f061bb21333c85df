"""
Images kept serialized until the front end needs their pixels.

At 15 Hz per camera most images arrive while the arm moves and are thrown away on their stamp
alone: only frames taken while the marker is still are decoded.  Deserializing every VGA frame
into a Python message in the executor thread costs CPU for nothing, so the node subscribes to
images with ``raw=True`` (the serialized CDR bytes, one memcpy), reads the header stamp straight
from the bytes, and hands the front end a :class:`LazyMessage` that deserializes on first use.

CDR layout of a message that starts with a ``std_msgs/Header`` (sensor_msgs/Image and
CompressedImage both do): a 4-byte encapsulation header (``00 01`` little endian, ``00 00``
big endian, then two option bytes), then ``int32 sec`` and ``uint32 nanosec`` (4-aligned from
the start of the payload, so at byte 4 and 8), then the frame id string: ``uint32`` length
(the terminating NUL included) at byte 12, then its bytes from byte 16.
"""

import struct

from rclpy.serialization import deserialize_message

_ENDIAN = {b'\x00\x01': '<', b'\x00\x03': '<', b'\x00\x00': '>', b'\x00\x02': '>'}


def header_stamp_ns(raw) -> int:
    """
    Return the header stamp (integer nanoseconds) of a serialized message that starts with one.

    Raises ValueError for bytes too short to hold a header or an unknown encapsulation, and for
    a negative stamp or nanoseconds outside [0, 1e9), as a corrupt message would have.
    """
    if len(raw) < 12:
        raise ValueError(f'serialized message of {len(raw)} bytes is too short for a header')
    endian = _ENDIAN.get(bytes(raw[:2]))
    if endian is None:
        raise ValueError(f'unknown CDR encapsulation {bytes(raw[:2]).hex()}')
    sec, nanosec = struct.unpack_from(endian + 'iI', raw, 4)
    if sec < 0 or nanosec >= 1_000_000_000:
        raise ValueError(f'header stamp {sec} s {nanosec} ns is not a valid time')
    return sec * 1_000_000_000 + nanosec


def header_fields(raw):
    """
    Return ``(sec, nanosec, frame_id)`` of the header of a serialized message that starts with one.

    A few microseconds against the milliseconds of deserializing a VGA image: the node reads
    every image's header this way to stamp the CameraInfo it publishes beside it.  Raises
    ValueError as :func:`header_stamp_ns` does, and for a frame id that overruns the bytes or
    is not UTF-8.
    """
    stamp = header_stamp_ns(raw)
    endian = _ENDIAN[bytes(raw[:2])]
    if len(raw) < 16:
        raise ValueError(f'serialized message of {len(raw)} bytes is too short for a header')
    (n,) = struct.unpack_from(endian + 'I', raw, 12)
    if n < 1 or 16 + n > len(raw):
        raise ValueError(f'header frame_id of {n} bytes overruns a message of {len(raw)} bytes')
    try:
        frame_id = bytes(raw[16:16 + n - 1]).decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ValueError(f'header frame_id is not UTF-8: {exc}') from exc
    return stamp // 1_000_000_000, stamp % 1_000_000_000, frame_id


class LazyMessage:
    """
    A serialized message that becomes the message on first attribute access.

    ``msg_type`` is the rclpy message class.  A malformed payload raises on that first access
    (in the front-end worker, which counts and skips it), never in the executor.
    """

    __slots__ = ('_raw', '_type', '_msg')

    def __init__(self, raw, msg_type):
        self._raw = raw
        self._type = msg_type
        self._msg = None

    @property
    def message(self):
        """Deserialize on first use, then keep the result."""
        if self._msg is None:
            self._msg = deserialize_message(self._raw, self._type)
            self._raw = None
        return self._msg

    def stamp_ns(self) -> int:
        """Return the header stamp in nanoseconds, without deserializing if not done yet."""
        if self._raw is not None:
            return header_stamp_ns(self._raw)
        stamp = self._msg.header.stamp
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def __getattr__(self, name):
        return getattr(self.message, name)
