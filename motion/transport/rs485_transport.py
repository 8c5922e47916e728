"""The RS485 transport over pyserial (the package's only importer of ``serial``).

RS485 is half duplex: one request, its reply, then the next request. For each request the transport

1. drains the input: frames already received are stale (counted per motor), corrupt bytes count on the bus
   (``BusCounters.bad_frames`` / ``dropped_bytes``), and the parser is emptied (a line that keeps streaming is
   drained until the request's window ends, never longer; the parser drops junk as it comes, so its buffer holds at
   most one frame);
2. writes the request;
3. waits for the reply until the request's window ends, taking in every frame the parser finds (a frame from
   another motor or with another command is stale, never matched to this request); at the end of the window it
   takes in what the port holds once more (a reply that came while a busy host kept this thread from reading is the
   drive's answer in time, not a miss), an incomplete frame is given up on (``next_frame(flush=True)``) and the
   request expires.

Per-request timeout rule: request *i* of *n* gets an equal share of the time left until the deadline,
``window_end = now + (deadline_s - now) / (n - i)``, measured just before it is sent. Time a prompt reply leaves
unused goes to the requests after it, so one silent drive costs at most its share and the call never returns
after the deadline. A request whose turn comes after the deadline is not sent at all (its reply would collide
with the next request on the shared pair): it is reported as no reply and counted in
``BusCounters.skipped_requests``.

Corrupt bytes seen while waiting for motor *m* (bad checksums, bad lengths, truncated frames, line noise) count
as ``bad_frames`` of *m*: on a half-duplex bus only the addressed drive may talk. Each corrupt frame candidate the
parser rejects counts once; noise that never looked like a frame counts once per window.

A port that is gone (the device unplugged, the far end of a pseudo-terminal closed: it hangs up, reads end, writes
fail with EIO) raises :class:`~motion.errors.PortLost`: see :mod:`motion.transport.base`.

Waiting uses ``select`` on the port's file descriptor, so this backend needs a POSIX system.
"""

from __future__ import annotations

import os
import select
import time
from collections.abc import Callable, Sequence
from typing import Final

import serial

from motion.errors import EncodeError, PortUnavailable, TransportError
from motion.protocol import MultiMotorTorque, rs485_frame
from motion.protocol.table import RS485_BAUDRATES, ProtocolFamily
from motion.transport.base import PORT_ERRORS, Request, Transport, port_failure, port_lost, probe_in_turn
from motion.transport.portlock import PortLock, device_key

#: Baud rates RMD RS485 drives of the older generation support (v1.62: 115200 is the factory default).
BAUDRATES: Final = RS485_BAUDRATES[ProtocolFamily.V2]
#: Bytes asked of the port per read; larger than any frame (65 bytes) so one read usually takes a whole reply.
READ_CHUNK_BYTES: Final = 256


class Rs485Transport(Transport):
    """RMD drives on one RS485 line (8N1, half duplex).

    Args:
        port: serial device (``/dev/ttyUSB0``, a pseudo-terminal, ...).
        baudrate: one of the family's baud rates (:data:`~motion.protocol.table.RS485_BAUDRATES`), bit/s.
        clock: time source of the deadlines (see :class:`~motion.transport.base.Transport`).
        exclusive: lock the port against other processes (``flock``), so that two programs cannot share a line.
        write_timeout_s: how long a write may block before the port counts as failed.
        family: the drives' protocol generation (``v3``: ``3E id 08 <8 bytes> CRC16`` frames,
            :mod:`motion.protocol.v3`).

    Raises:
        EncodeError: the baud rate is not one RMD drives support (checked before the port is touched).
        PortHeld: another rmd-motion session holds the port (:mod:`motion.transport.portlock`).
        TransportError: the port could not be opened (missing, busy, locked by another process).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115_200,
        *,
        clock: Callable[[], float] = time.monotonic,
        exclusive: bool = True,
        write_timeout_s: float = 0.1,
        family: ProtocolFamily = ProtocolFamily.V2,
    ) -> None:
        super().__init__(clock=clock, family=family)
        allowed = self.generation.rs485_baudrates
        if baudrate not in allowed:
            raise EncodeError(
                "baudrate",
                ", ".join(map(str, allowed)),
                baudrate,
                f"RMD RS485 {self.generation.rs485_document} baud rates",
            )
        self.port = port
        self.baudrate = baudrate
        # the session's lock first (another rmd-motion session is named), then pyserial's lock on the device itself
        # (against any other program that locks it)
        lock = PortLock(device_key(port), f"RS485 port {port!r}", "rs485")
        try:
            # timeout=0: reads return what is there; waiting is done with select until a window's end instead,
            # because changing pyserial's timeout reconfigures the port on every call.
            self._serial = serial.Serial(
                port=port,
                baudrate=baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=0,
                write_timeout=write_timeout_s,
                exclusive=exclusive,
            )
            self._fds: list[int] = [self._serial.fileno()]
        except (serial.SerialException, OSError, ValueError) as exc:
            lock.release()
            raise PortUnavailable(f"cannot open RS485 port {port!r} at {baudrate} baud: {exc}", "rs485") from exc
        self._port_lock = lock
        self._speak()

    def _speak(self, *, owns_port: bool = True) -> None:
        """The framing of :attr:`family` and empty per-exchange state."""
        self._owns_port = owns_port
        self._parser = self.generation.rs485_parser()
        self._encode = self.generation.encode_rs485_request
        self._frames: list[bytes] = []
        self._motors: list[int] = []
        self._seen_candidates = 0
        self._seen_dropped = 0

    def _sibling(self, family: ProtocolFamily, *, takes_port: bool) -> Rs485Transport:
        """A transport of ``family`` on this one's open port (owning it when ``takes_port``, this one then not)."""
        sibling = Rs485Transport.__new__(Rs485Transport)
        Transport.__init__(sibling, clock=self.clock, family=family)
        sibling.port, sibling.baudrate = self.port, self.baudrate
        sibling._serial, sibling._fds = self._serial, self._fds
        sibling._speak(owns_port=takes_port and self._owns_port)
        sibling.frame_tap = self.frame_tap
        if takes_port:
            if self._owns_port:
                self._hand_over_lock(sibling)
            self._owns_port = False
        return sibling

    def probe_families(self, ids: Sequence[int], window_s: float) -> dict[int, ProtocolFamily] | None:
        """See :meth:`Transport.probe_families`: a status read (0x9A) in this transport's framing, then in the other
        to the ids silent to it (:func:`~motion.transport.base.probe_in_turn`; a frame of the other framing is
        garbage to a drive: its checksums fail and it stays silent)."""
        found = probe_in_turn(self, ids, window_s, lambda family: self._sibling(family, takes_port=False))
        self._read_behind_the_slots()  # the other framing's sibling read the line too
        return found

    def with_family(self, family: ProtocolFamily) -> Rs485Transport:
        """See :meth:`Transport.with_family`."""
        return self._sibling(family, takes_port=True)

    def request_wire_s(self, requests: Sequence[Request]) -> float | None:
        """See :meth:`Transport.request_wire_s`: the frames' bytes at :attr:`baudrate` (8N1)."""
        size = sum(len(self._encode(r.message, r.motor_id)) for r in requests)
        return rs485_frame.rs485_frame_time_s(size, self.baudrate)

    def describe(self) -> str:
        """``"rs485 PORT"``."""
        return f"rs485 {self.port}"

    def _prepare(self, requests: Sequence[Request]) -> None:
        frames, motors = self._frames, self._motors
        frames.clear()
        motors.clear()
        for request in requests:
            if isinstance(request.message, MultiMotorTorque):
                raise EncodeError(
                    "message", "a single-motor request (RS485 has no broadcast)", "MultiMotorTorque (CAN ID 0x280)"
                )
            frames.append(self._encode(request.message, request.motor_id))
            motors.append(request.motor_id)

    def _exchange(self, deadline_s: float) -> None:
        clock, count = self.clock, len(self._frames)
        for index in range(count):
            now = clock()
            if now >= deadline_s:
                break
            window_end_s = now + (deadline_s - now) / (count - index)
            self._drain(window_end_s)
            self._write(self._frames[index])
            self._sent(index)
            self._wait(index, window_end_s)
            self.motor_counters(self._motors[index]).bad_frames += self._corrupt_since_last_check()

    def _drain(self, until_s: float) -> None:
        """Take in everything received before the next request as stale (until ``until_s`` at the latest), then empty
        the parser."""
        while True:
            chunk = self._read()
            self._parser.feed(chunk)
            if len(chunk) < READ_CHUNK_BYTES or self.clock() >= until_s:
                break
            self._take_frames(flush=False)  # the parser drops what cannot start a frame: its buffer stays small
        self._take_frames(flush=True)
        self._parser.discard()
        self.bus_counters.bad_frames += self._corrupt_since_last_check()

    def _wait(self, index: int, window_end_s: float) -> None:
        """Read until request ``index`` is answered or its window ends."""
        clock, parser = self.clock, self._parser
        while not self._answered(index):
            remaining_s = window_end_s - clock()
            if remaining_s <= 0.0:
                # what the port holds now came while this thread was not looking (a host that descheduled it past
                # the window): the drive answered, the host was late; take it before giving up on the request
                parser.feed(self._read())
                self._take_frames(flush=True)
                if not self._answered(index):
                    self._expire(index)
                return
            try:
                ready = select.select(self._fds, (), (), remaining_s)[0]
            except (OSError, ValueError) as exc:
                raise self._failure("waiting on", exc) from exc
            if ready:
                parser.feed(self._read(ready=True))
                self._take_frames(flush=False)

    def _take_frames(self, *, flush: bool) -> None:
        parser = self._parser
        while (reply := parser.next_reply(flush=flush)) is not None:
            motor_id, message = reply
            if message is None:
                (self.bus_counters if motor_id is None else self.motor_counters(motor_id)).bad_frames += 1
            elif motor_id is None:  # (a V3 0x79 reply on 0xCD: not the control loop's)
                self.bus_counters.unknown_id_frames += 1
            else:
                self._offer(motor_id, message)

    def _corrupt_since_last_check(self) -> int:
        """Corrupt frames the parser rejected since the last call; noise without any frame candidate counts one."""
        parser = self._parser
        candidates = parser.bad_header_checksums + parser.bad_data_checksums + parser.bad_lengths + parser.truncated
        bad = candidates - self._seen_candidates
        if bad == 0 and parser.dropped_bytes > self._seen_dropped:
            bad = 1
        self._seen_candidates = candidates
        self._seen_dropped = self.bus_counters.dropped_bytes = parser.dropped_bytes
        return bad

    def _read(self, *, ready: bool = False) -> bytes:
        """Every byte the port holds, b"" when none: one system call on pyserial's non-blocking descriptor (its own
        ``read`` adds a ``select`` per call). ``ready``: ``select`` said the port is readable, so no bytes mean the
        device is gone (pyserial's read says the same)."""
        try:
            chunk = os.read(self._fds[0], READ_CHUNK_BYTES)
        except BlockingIOError:
            chunk = b""
        except OSError as exc:
            raise self._failure("read from", exc) from exc
        if not chunk:
            if ready:  # the end of the port's input: it hung up
                raise port_lost(f"read from {self.describe()} failed: the port reports input but returned none")
            return chunk
        if self.frame_tap is not None:
            self.frame_tap(self.clock(), True, None, chunk)
        return chunk

    def _write(self, frame: bytes) -> None:
        try:
            self._serial.write(frame)
        except (serial.SerialException, *PORT_ERRORS) as exc:
            raise self._failure("write to", exc) from exc
        if self.frame_tap is not None:
            self.frame_tap(self.clock(), False, None, frame)

    def _failure(self, what: str, exc: BaseException) -> TransportError:
        """The error for a failed ``what`` (``read from``, ...): :class:`PortLost` when the port is gone."""
        return port_failure(f"{what} {self.describe()} failed: {exc}", exc, self._fds[0])

    def _close(self) -> None:
        if not self._owns_port:
            return
        try:
            self._serial.close()
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"closing {self.describe()} failed: {exc}") from exc
