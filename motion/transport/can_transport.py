"""The CAN transport over any python-can interface, built on :class:`~motion.transport.can_endpoint.CanEndpoint`.

A cycle drains the receive queue (whatever is there is a previous cycle's and counts as stale), sends every
request back to back (the bus arbitrates, drives answer in parallel), then receives until every expected reply
is matched or the deadline passes, and takes in what the receive queue holds then (a reply that came while a busy
host kept the thread from reading is an answer in time, not a miss). Replies are matched by arbitration id
(``0x140 + motor id``) and DATA[0] (the command byte the drive echoes); see :mod:`motion.transport.base` for the
matching and stale rule.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, Final, Protocol

from motion.errors import DecodeError
from motion.protocol import CanFrame
from motion.protocol.generation import Generation
from motion.protocol.table import MOTOR_ID_MAX, MOTOR_ID_MIN, ProtocolFamily
from motion.transport.base import Request, Transport
from motion.transport.can_endpoint import CanEndpoint
from motion.transport.portlock import PortLock, can_key


def take_in_can_frame(
    transport: Transport,
    frame: CanFrame,
    address_base: int = 0,
    *,
    tapped: bool = False,
    generation: Generation | None = None,
) -> None:
    """Take one received CAN frame into ``transport``: tap it (unless ``tapped``: the caller did), decode it (with
    ``generation``, default the transport's), offer it (or count why not); the drive's address is ``address_base`` +
    its motor id (an arm on several buses: ``bus index × ADDRESS_STRIDE``).

    Shared by every transport that carries RMD CAN frames (this one and the simulated bus).
    """
    arbitration_id = frame.arbitration_id
    if transport.frame_tap is not None and not tapped:
        transport.frame_tap(transport.clock(), True, arbitration_id, frame.data)
    # (a V3 drive's 0x300 id-setting and 0x500 motion replies are not the control loop's: counted as frames of other
    # devices, as 0x280 frames are)
    if generation is None:
        generation = transport.generation
    motor_id = arbitration_id - generation.can_reply_base
    if not _FIRST_MOTOR_ID <= motor_id <= _LAST_MOTOR_ID:
        # Other devices may share the bus; their frames are not drive replies.
        transport.bus_counters.unknown_id_frames += 1
        return
    try:
        message = generation.decode_can_reply(arbitration_id, frame.data)[1]
    except DecodeError:
        transport.motor_counters(address_base + motor_id).bad_frames += 1
        return
    transport._offer(address_base + motor_id, message)


# Looked up once, not for every frame.
_FIRST_MOTOR_ID: Final = MOTOR_ID_MIN
_LAST_MOTOR_ID: Final = MOTOR_ID_MAX


class CanPort(Protocol):
    """What :class:`CanTransport` needs of the bus: the seam where it meets python-can (:class:`CanEndpoint`), and
    where another link (a loopback for a benchmark, a test double of an adapter) can be given instead."""

    interface: str
    channel: str

    def send(self, frame: CanFrame, timeout_s: float | None = None) -> None:
        """Queue one frame for transmission (raise TransportError when it cannot be)."""

    def recv(self, timeout_s: float | None) -> tuple[CanFrame, float] | None:
        """The next received frame and its time, or None after ``timeout_s``."""

    def close(self) -> None:
        """Release the port."""


#: Shortest time a frame may take to enter the interface's transmit queue before the bus counts as failed, s.
SEND_TIMEOUT_MIN_S = 0.1


class CanTransport(Transport):
    """RMD drives on one CAN bus.

    Args:
        interface: python-can interface name (``socketcan``, ``slcan``, ``pcan``, ``virtual``, ...).
        channel: interface channel (``can0``, ``/dev/ttyACM0``, a virtual channel name, ...).
        bitrate: bit rate in bit/s (RMD drives use 1 Mbit/s), or None to leave the interface's setting alone.
        clock: time source of the deadlines (see :class:`~motion.transport.base.Transport`).
        family: the drives' protocol generation (``v3``: replies on 0x240 + id, :mod:`motion.protocol.v3`).
        **bus_kwargs: passed to :class:`can.Bus` unchanged.

    Use :meth:`over` for a port that is already open (injected instead of opened here; the session lock of
    :mod:`motion.transport.portlock` is then its opener's).

    Raises:
        PortHeld: another rmd-motion session holds the channel (:mod:`motion.transport.portlock`).
        TransportError: the bus could not be opened.
    """

    def __init__(
        self,
        interface: str,
        channel: str,
        bitrate: int | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        family: ProtocolFamily = ProtocolFamily.V2,
        **bus_kwargs: Any,
    ) -> None:
        lock = PortLock(can_key(interface, channel), f"CAN interface {interface!r} channel {channel!r}", "can")
        try:
            endpoint = CanEndpoint(interface, channel, bitrate, **bus_kwargs)
        except BaseException:
            lock.release()
            raise
        self._adopt(endpoint, clock, family)
        self._port_lock = lock

    @classmethod
    def over(
        cls,
        port: CanPort,
        *,
        clock: Callable[[], float] = time.monotonic,
        family: ProtocolFamily = ProtocolFamily.V2,
        owns_port: bool = True,
    ) -> CanTransport:
        """The transport over ``port``, already open: closing the transport closes it, unless ``owns_port`` is False
        (a second transport on the same bus, e.g. speaking the other generation to some of its drives)."""
        transport = cls.__new__(cls)
        transport._adopt(port, clock, family, owns_port=owns_port)
        return transport

    def _adopt(
        self, port: CanPort, clock: Callable[[], float], family: ProtocolFamily, *, owns_port: bool = True
    ) -> None:
        super().__init__(clock=clock, family=family)
        self._endpoint: CanPort = port
        # a port that writes a cycle's batch at once (CanEndpoint over the slcan shim): its send_batch
        self._send_batch: Callable[[Sequence[CanFrame], float | None], None] | None = getattr(port, "send_batch", None)
        self._owns_port = owns_port
        self._frames: list[CanFrame] = []

    @property
    def port(self) -> CanPort:
        """The port the frames go through (a :class:`CanEndpoint` unless one was given to :meth:`over`)."""
        return self._endpoint

    def probe_families(self, ids: Sequence[int], window_s: float) -> dict[int, ProtocolFamily] | None:
        """See :meth:`Transport.probe_families` (frame level, on :attr:`port`)."""
        from motion.transport.detect import detect_can  # noqa: PLC0415 - detect builds on this module

        found = detect_can(self._endpoint, ids, window_s)
        self._read_behind_the_slots()
        return found

    def with_family(self, family: ProtocolFamily) -> CanTransport:
        """See :meth:`Transport.with_family`."""
        transport = CanTransport.over(self._endpoint, clock=self.clock, family=family, owns_port=self._owns_port)
        transport.frame_tap = self.frame_tap
        if self._owns_port:
            self._hand_over_lock(transport)
        self._owns_port = False
        return transport

    def describe(self) -> str:
        """``"can INTERFACE:CHANNEL"``."""
        return f"can {self._endpoint.interface}:{self._endpoint.channel}"

    def _prepare(self, requests: Sequence[Request]) -> None:
        frames = self._frames
        encode = self.generation.encode_can_request
        frames.clear()
        for request in requests:
            frames.append(encode(request.message, request.motor_id))

    def _exchange(self, deadline_s: float) -> None:
        endpoint, clock, take_in = self._endpoint, self.clock, take_in_can_frame
        recv = endpoint.recv
        # Anything already queued was sent before this cycle's requests: take it in as stale now, so that it
        # cannot be matched to them (until the deadline: a bus that babbles frames faster than they are taken in
        # must not hold the cycle for ever).
        while (received := recv(0.0)) is not None:
            take_in(self, received[0])
            if clock() >= deadline_s:
                break
        # A send that cannot complete means a full transmit queue (bus off, no ACK): an error. It gets at least
        # SEND_TIMEOUT_MIN_S, not just what is left of the cycle: pyserial (slcan) raises a write timeout once the
        # timeout has passed even when every byte was written, which a descheduled thread hits on a loaded machine.
        send_timeout_s = max(deadline_s - clock(), SEND_TIMEOUT_MIN_S)
        send, tap, sent = endpoint.send, self.frame_tap, 0
        try:
            if self._send_batch is not None:  # (the batch in one write: if it fails, none counts as sent)
                self._send_batch(self._frames, send_timeout_s)
                sent = len(self._frames)
                if tap is not None:
                    now = clock()
                    for frame in self._frames:
                        tap(now, False, frame.arbitration_id, frame.data)
            else:
                for frame in self._frames:
                    send(frame, send_timeout_s)
                    sent += 1
                    if tap is not None:
                        tap(clock(), False, frame.arbitration_id, frame.data)
        finally:
            self._sent_first(sent)  # the requests that went out, also when a send failed
        while self._open_slots:
            remaining_s = deadline_s - clock()
            if remaining_s <= 0.0:
                break
            received = recv(remaining_s)
            if received is not None:
                take_in(self, received[0])
        # What the endpoint holds at the deadline came while this thread was not looking (a host that descheduled
        # it past the deadline): those drives answered, the host was late. Take it in (as many frames as there were
        # requests, at most: a babbling bus does not hold the cycle).
        left = len(self._frames)
        while self._open_slots and left and (received := recv(0.0)) is not None:
            take_in(self, received[0])
            left -= 1
        if self._open_slots:  # a reply is missing: junk on the line may be why (the slcan shim counts what it drops)
            self.bus_counters.dropped_bytes = getattr(endpoint, "dropped_bytes", 0)

    def _close(self) -> None:
        if self._owns_port:
            self._endpoint.close()
