"""A raw CAN frame endpoint over any python-can interface (the package's only importer of ``can``).

Used by :class:`~motion.transport.can_transport.CanTransport` on the host side and by the emulator to attach
emulated drives to an in-process ``virtual`` bus. Frames are :class:`motion.protocol.CanFrame`.
"""

from __future__ import annotations

import functools
import io
import os
import select
import time
from collections.abc import Callable, Sequence
from typing import Any

import can

from motion.closing import Closing
from motion.errors import PortUnavailable, TransportError
from motion.protocol import CanFrame
from motion.protocol.compiled import frozen_builder
from motion.transport.base import port_failure

_new_frame = frozen_builder(CanFrame)


def _open_slcan_shim(channel: str, kwargs: dict[str, Any]) -> can.BusABC | None:
    """python-can's slcan reads one byte per system call (python-can issue 2027): while the installed release lacks
    the fix, open the bus through :mod:`motion.transport.slcan_shim`; None means "use python-can's own"."""
    # Imported here: it imports pyserial, which a CAN bus of another interface never needs.
    from motion.transport import slcan_shim  # noqa: PLC0415

    return slcan_shim.SlcanShimBus(channel, **kwargs) if slcan_shim.needs_shim() else None


#: Reads without a frame that one recv call takes in before it gives up (bounds the call when the descriptor keeps
#: signalling input that never completes a frame).
_MAX_SKIPPED_READS = 256


class CanEndpoint(Closing):
    """Send and receive classic CAN data frames on one python-can bus.

    Args:
        interface: python-can interface name (``virtual``, ``socketcan``, ``slcan``, ``pcan``, ``kvaser``, ...).
        channel: interface channel (``can0``, ``/dev/ttyACM0``, a virtual channel name, ...).
        bitrate: bit rate in bit/s, or None to leave the interface's setting alone.
        **bus_kwargs: passed to :class:`can.Bus` unchanged.

    Raises:
        TransportError: the bus could not be opened (unknown interface, missing device, ...).
    """

    def __init__(self, interface: str, channel: str, bitrate: int | None = None, **bus_kwargs: Any) -> None:
        kwargs = dict(bus_kwargs)
        if bitrate is not None:
            kwargs["bitrate"] = bitrate
        try:
            shim = _open_slcan_shim(channel, kwargs) if interface == "slcan" else None
            self._bus: can.BusABC = (
                shim if shim is not None else can.Bus(interface=interface, channel=channel, **kwargs)
            )
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise PortUnavailable(f"cannot open CAN interface {interface!r} channel {channel!r}: {exc}") from exc
        self.interface = interface
        self.channel = channel
        self._closed = False
        # Where the bus has a descriptor, recv waits on it and then takes the input without blocking: python-can's
        # slcan blocks for its serial read timeout (1 ms) whatever timeout it is given, so a poll cost every control
        # cycle 1 ms and a wait could end up to 1 ms after the cycle's deadline.
        self._fd: int | None = None
        if os.name == "posix":
            try:
                self._fd = self._bus.fileno()
            except (NotImplementedError, io.UnsupportedOperation, OSError, ValueError):
                self._fd = None
        # A bus that buffers input itself (the slcan shim) says so: select must not wait while it holds a frame.
        self._pending_input = getattr(self._bus, "pending_input", None)
        # The slcan shim carries standard data frames without a can.Message (see slcan_shim): the loop's frames.
        self._recv_frame = getattr(self._bus, "recv_frame", None)
        self._send_frame = getattr(self._bus, "send_frame", None)
        send_frames = getattr(self._bus, "send_frames", None)
        #: Send a cycle's batch in one write (the slcan shim), or None where the bus sends frame by frame.
        self.send_batch: Callable[[Sequence[CanFrame], float | None], None] | None = (
            None if send_frames is None else functools.partial(self._send_lines, send_frames)
        )

    def send(self, frame: CanFrame, timeout_s: float | None = None) -> None:
        """Send one frame.

        Raises:
            PortLost: the port is gone (:func:`~motion.transport.base.port_gone`).
            TransportError: the interface refused the frame (bus off, buffer full).
        """
        try:
            if self._send_frame is not None:
                self._send_frame(frame.arbitration_id, frame.data, timeout_s)
                return
            message = can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
            self._bus.send(message, timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as exc:
            raise self._failure("send", exc) from exc

    def _send_lines(
        self,
        send_frames: Callable[[Sequence[tuple[int, bytes]], float | None], None],
        frames: Sequence[CanFrame],
        timeout_s: float | None,
    ) -> None:
        """:attr:`send_batch` (the slcan shim's lines in one write).

        Raises:
            PortLost: the port is gone (:func:`~motion.transport.base.port_gone`).
            TransportError: the interface refused the batch (nothing of it counts as sent).
        """
        try:
            send_frames([(frame.arbitration_id, frame.data) for frame in frames], timeout_s)
        except (can.CanError, OSError, ValueError) as exc:
            raise self._failure("send", exc) from exc

    def recv(self, timeout_s: float | None) -> tuple[CanFrame, float] | None:
        """Receive one data frame, or None when ``timeout_s`` passes first (None: wait for ever).

        Remote, error and extended-id frames are skipped (RMD drives use none of them) without ending the wait; a
        data frame that is not 8 bytes long is returned as it is, so that the caller can count it as a bad frame.

        Returns:
            ``(frame, timestamp_s)`` where the timestamp is the interface's receive time.

        Raises:
            PortLost: the port is gone (:func:`~motion.transport.base.port_gone`).
            TransportError: the interface failed (bus off).
        """
        end = None if timeout_s is None else time.monotonic() + timeout_s
        skipped = 0
        while True:
            remaining = None if end is None else max(0.0, end - time.monotonic())
            try:
                if self._fd is not None:
                    buffered = self._pending_input is not None and self._pending_input()
                    if not buffered and not select.select([self._fd], [], [], remaining)[0]:
                        return None
                    remaining = 0.0
                message = self._bus.recv(timeout=remaining) if self._recv_frame is None else self._recv_frame(remaining)
            except (can.CanError, OSError, ValueError) as exc:
                raise self._failure("receive", exc) from exc
            if message.__class__ is tuple:
                return _new_frame(*message), time.time()  # slcan's time stamp: the host's clock
            if message is None:
                # The input was no frame (an adapter's acknowledgement) or only part of one: wait on, or at the end
                # of the time take in what else is there, so that a poll still drains every frame already received.
                skipped += 1
                if self._fd is not None and skipped < _MAX_SKIPPED_READS:
                    continue
                return None
            if not (message.is_error_frame or message.is_remote_frame or message.is_extended_id):
                return _new_frame(message.arbitration_id, bytes(message.data)), float(message.timestamp)

    def _failure(self, what: str, exc: BaseException) -> TransportError:
        """The error for a failed ``what`` (send, receive): :class:`PortLost` when the port is gone."""
        return port_failure(f"CAN {what} on {self.interface}:{self.channel} failed: {exc}", exc, self._fd)

    @property
    def dropped_bytes(self) -> int:
        """Bytes of junk the interface dropped (the slcan shim: lines longer than any slcan line), 0 where it does
        not count them."""
        return int(getattr(self._bus, "junk_bytes", 0))

    def close(self) -> None:
        """Release the bus; safe to call more than once.

        Raises:
            TransportError: the interface failed while closing (a dead slcan adapter refuses its close command).
        """
        if not self._closed:
            self._closed = True
            try:
                self._bus.shutdown()
            except (can.CanError, OSError, ValueError) as exc:
                raise TransportError(f"closing CAN interface {self.interface}:{self.channel} failed: {exc}") from exc
