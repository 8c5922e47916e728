"""ROS 2's message encoding (``cdr``: OMG CDR, little endian, behind a 4-byte encapsulation header) for the fields the
recording's messages hold (:mod:`motion.telemetry.mcap`).

A shim, measured: ``mcap-ros2-support``'s encoder interprets the message definition field by field, 37 µs for a
six-joint ``JointState`` where this writer takes a few (``bench/recording_cost.py``); a recording writes several
messages per control cycle. Its output is checked byte for byte against that encoder in ``tests/test_recording.py``.
Exit plan: drop it for the library's encoder once that compiles a definition into one ``struct`` format per message
(it decodes that way already); nothing here is used to read.

Alignment follows CDR: each primitive on a multiple of its size, counted from the end of the encapsulation header;
a sequence is its ``uint32`` length, then its elements; a string its length including the terminating NUL, its UTF-8
bytes, the NUL.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from typing import Any, Final

import numpy as np

#: The encapsulation header of little-endian plain CDR (``CDR_LE``).
HEADER: Final = b"\x00\x01\x00\x00"
_INT32: Final = struct.Struct("<i")
_INT64: Final = struct.Struct("<q")
_UINT32: Final = struct.Struct("<I")
_TIME: Final = struct.Struct("<iI")
_FLOAT64: Final = struct.Struct("<d")


class CdrWriter:
    """One message, field by field (in the order of its definition)."""

    __slots__ = ("_parts", "_size")

    def __init__(self) -> None:
        self._parts: list[bytes] = [HEADER]
        self._size = 0  # bytes after the header: what alignment counts from

    def _raw(self, data: bytes) -> None:
        self._parts.append(data)
        self._size += len(data)

    def _align(self, size: int) -> None:
        pad = -self._size % size
        if pad:
            self._raw(b"\x00" * pad)

    def int32(self, value: int) -> CdrWriter:
        self._align(4)
        self._raw(_INT32.pack(value))
        return self

    def uint32(self, value: int) -> CdrWriter:
        self._align(4)
        self._raw(_UINT32.pack(value))
        return self

    def int64(self, value: int) -> CdrWriter:
        self._align(8)
        self._raw(_INT64.pack(value))
        return self

    def octet(self, value: int) -> CdrWriter:
        """A ``byte``, ``uint8`` or ``bool`` (0 or 1)."""
        self._raw(bytes((value,)))
        return self

    def float64(self, value: float) -> CdrWriter:
        self._align(8)
        self._raw(_FLOAT64.pack(value))
        return self

    def time(self, sec: int, nanosec: int) -> CdrWriter:
        """A ``builtin_interfaces/Time``."""
        self._align(4)
        self._raw(_TIME.pack(sec, nanosec))
        return self

    def string(self, text: str) -> CdrWriter:
        data = text.encode() + b"\x00"
        self.uint32(len(data))
        self._raw(data)
        return self

    def strings(self, texts: Iterable[str]) -> CdrWriter:
        items = list(texts)
        self.uint32(len(items))
        for text in items:
            self.string(text)
        return self

    def float64s(self, values: Any) -> CdrWriter:
        """A ``float64[]`` from a sequence or array."""
        array = np.asarray(values, dtype="<f8")
        self.uint32(array.size)
        if array.size:
            self._align(8)
            self._raw(array.tobytes())
        return self

    def bools(self, values: Any) -> CdrWriter:
        """A ``bool[]`` from a sequence or array."""
        array = np.asarray(values, dtype=np.bool_)
        self.uint32(array.size)
        self._raw(array.astype(np.uint8).tobytes())
        return self

    def octets(self, data: bytes) -> CdrWriter:
        """A ``uint8[]``."""
        self.uint32(len(data))
        self._raw(bytes(data))
        return self

    def data(self) -> bytes:
        """The message, header included."""
        return b"".join(self._parts)
