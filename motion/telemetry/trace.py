"""The bus trace of a run: every frame a transport sends and takes in, kept in memory and written as a candump log
(CAN) or a hex log (RS485) at the end (see :mod:`motion.telemetry`). On an arm of several buses each frame keeps the
index of its bus (in the configuration's order): a transport of several buses asks the tap for one per bus
(:meth:`BusTrace.on_bus`)."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from typing import Final, NamedTuple, TextIO

import numpy as np

from motion.transport.base import FrameTap, Transport

#: Frames per chunk of the bus trace.
CHUNK_FRAMES: Final = 16384


class TracedFrame(NamedTuple):
    """One frame of a :class:`BusTrace`."""

    time_s: float  #: transport clock, s
    received: bool  #: True for a frame the host took in, False for one it sent
    arbitration_id: int | None  #: CAN identifier, None on RS485
    data: bytes  #: payload (CAN) or port bytes (RS485)
    bus: int = 0  #: index of its bus among the arm's (0 on an arm of one)


class _FrameChunk:
    __slots__ = ("bus", "data", "end", "ident", "received", "time_s")

    def __init__(self, frames: int) -> None:
        self.time_s = np.zeros(frames)
        self.ident = np.zeros(frames, dtype=np.int32)
        self.received = np.zeros(frames, dtype=np.bool_)
        self.end = np.zeros(frames, dtype=np.int64)
        self.bus = np.zeros(frames, dtype=np.int16)
        self.data = bytearray()


class BusTrace:
    """Every frame of a transport, kept in memory (install with :meth:`install`; it is the bus's frame tap).

    Args:
        chunk_frames: frames per preallocated chunk.
    """

    def __init__(self, *, chunk_frames: int = CHUNK_FRAMES) -> None:
        self._chunk_frames = chunk_frames
        self._chunks = [_FrameChunk(chunk_frames)]
        self._chunk = self._chunks[0]
        self._n = 0
        #: Unix time minus transport clock, s (set by :meth:`install`).
        self.unix_offset_s = 0.0
        self._bus: Transport | None = None

    def install(self, bus: Transport) -> BusTrace:
        """Observe every frame ``bus`` sends and takes in from now on."""
        self.unix_offset_s = time.time() - bus.clock()
        bus.frame_tap = self
        self._bus = bus
        return self

    def uninstall(self) -> None:
        """Stop observing (the recorded frames stay)."""
        if self._bus is not None and self._bus.frame_tap is self:
            self._bus.frame_tap = None
        self._bus = None

    def __call__(self, time_s: float, received: bool, arbitration_id: int | None, data: bytes) -> None:
        """Record one frame (a :data:`~motion.transport.base.FrameTap`) of the first bus (an arm's only one)."""
        self.record(0, time_s, received, arbitration_id, data)

    def on_bus(self, index: int) -> FrameTap:
        """The tap of the arm's bus ``index`` (configuration order): its frames are recorded as that bus's."""

        def tap(time_s: float, received: bool, arbitration_id: int | None, data: bytes) -> None:
            self.record(index, time_s, received, arbitration_id, data)

        return tap

    def record(self, bus: int, time_s: float, received: bool, arbitration_id: int | None, data: bytes) -> None:
        """Record one frame of the arm's bus ``bus`` (index, configuration order)."""
        chunk, n = self._chunk, self._n
        if n == self._chunk_frames:
            chunk, n = _FrameChunk(self._chunk_frames), 0
            self._chunks.append(chunk)
            self._chunk = chunk
        chunk.time_s[n] = time_s
        chunk.ident[n] = -1 if arbitration_id is None else arbitration_id
        chunk.received[n] = received
        chunk.bus[n] = bus
        chunk.data += data
        chunk.end[n] = len(chunk.data)
        self._n = n + 1

    def __len__(self) -> int:
        return (len(self._chunks) - 1) * self._chunk_frames + self._n

    def __iter__(self) -> Iterator[TracedFrame]:
        for chunk in self._chunks:
            count = self._n if chunk is self._chunk else self._chunk_frames
            start = 0
            for k in range(count):
                end = int(chunk.end[k])
                ident = int(chunk.ident[k])
                yield TracedFrame(
                    float(chunk.time_s[k]),
                    bool(chunk.received[k]),
                    None if ident < 0 else ident,
                    bytes(chunk.data[start:end]),
                    int(chunk.bus[k]),
                )
                start = end

    def write_candump(self, file: TextIO, channels: str | Sequence[str] = "can0") -> None:
        """Write the CAN frames as a candump log (see :mod:`motion.telemetry`), each on its bus's interface name
        (``channels``: one name, or one per bus by index; blanks become ``_``)."""
        offset = self.unix_offset_s
        names = [_word(channel) or "can0" for channel in ((channels,) if isinstance(channels, str) else channels)]
        for frame in self:
            if frame.arbitration_id is not None:
                file.write(
                    f"({frame.time_s + offset:.6f}) {names[frame.bus]} {frame.arbitration_id:03X}#"
                    f"{frame.data.hex().upper()} {'R' if frame.received else 'T'}\n"
                )

    def write_hex(self, file: TextIO, buses: Sequence[str] = ()) -> None:
        """Write every frame as ``(UNIX_TIME) T|R HEX BYTES`` (the RS485 trace); with ``buses`` (names by index: an
        arm of several), ``(UNIX_TIME) BUS T|R HEX BYTES``. A CAN bus's frame among them (an arm on buses of both
        transports) is a candump line, ``(UNIX_TIME) BUS ID#DATA T|R``, as :meth:`write_candump` writes it."""
        offset = self.unix_offset_s
        names = [_word(name) + " " for name in buses]
        for frame in self:
            direction = "R" if frame.received else "T"
            bus = names[frame.bus] if names else ""
            if frame.arbitration_id is not None:
                line = f"{frame.arbitration_id:03X}#{frame.data.hex().upper()} {direction}"
            else:
                line = f"{direction} {frame.data.hex(' ').upper()}"
            file.write(f"({frame.time_s + offset:.6f}) {bus}{line}\n")


def _word(name: str) -> str:
    """``name`` as one word of a trace line (blanks become ``_``)."""
    return "_".join(name.split())
