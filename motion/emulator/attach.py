"""Bus attachments: each connects an :class:`~motion.emulator.core.Emulator` to a bus in its own thread.

- :class:`VirtualCanAttachment`: python-can's in-process ``virtual`` bus (through :class:`CanEndpoint`).
- :class:`SlcanAttachment`: a pseudo-terminal speaking slcan, i.e. a virtual USB-CAN adapter that python-can's
  ``slcan`` interface (or any LAWICEL tool) opens by path, from any process.
- :class:`Rs485Attachment`: a pseudo-terminal carrying RS485 frames, opened by path with pyserial.

The thread waits for input (at most :data:`TICK_S`, so simulation time keeps up with the monotonic clock even when
the bus is idle), advances the emulator to now, executes the requests and sends each reply when it is due: after the
drive's latency and any ``delay`` fault, and - with the bus-time model - after the request and the reply occupied the
bus (see :mod:`motion.emulator.timing`). Input that breaks the protocol is counted in ``stats.decode_errors``,
logged (``logging`` warning and the frame log) and never answered.

Attachments start when constructed; close them (or use them as context managers). ``close()`` re-raises, as a
RuntimeError, an exception that stopped the thread, so that an emulator bug cannot pass silently.
"""

from __future__ import annotations

import heapq
import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Final, Generic, TypeVar

from motion.closing import Closing
from motion.emulator.core import Emulator, Exchange, Outgoing
from motion.emulator.framelog import FrameLog
from motion.emulator.pty import PseudoTerminal
from motion.emulator.slcan import SlcanDevice
from motion.emulator.timing import BusClock, TimingModel, can_frame_time_s
from motion.errors import DecodeError
from motion.protocol import CanFrame
from motion.protocol.rs485_frame import rs485_frame_time_s
from motion.transport.can_endpoint import CanEndpoint

logger = logging.getLogger("motion.emulator")

#: Longest wait for input before the thread advances simulation time anyway, s.
TICK_S: Final = 0.002
#: Default CAN bit rate for the bus-time model of the virtual bus, bit/s.
DEFAULT_CAN_BITRATE: Final = 1_000_000
#: Default RS485 baud rate, bit/s (the RS485 document's default).
DEFAULT_RS485_BAUD: Final = 115_200
#: An incomplete RS485 frame is given up after this silence on the line, in byte times (and at least 2 ms, because
#: a pseudo-terminal delivers a client's write in pieces at its own pace).
_RS485_GAP_BYTES: Final = 4
_RS485_MIN_GAP_S: Final = 0.002
#: How long close() waits for the thread, s.
_JOIN_TIMEOUT_S: Final = 5.0

W = TypeVar("W")  # reply wire type
R = TypeVar("R")  # received item type


@dataclass(slots=True)
class AttachmentStats:
    """Counters of one attachment.

    Attributes:
        requests: frames received from the host (valid or not).
        replies: frames sent to the host.
        decode_errors: received input that breaks the protocol (counted, logged, not answered).
        unanswered: valid requests no drive answered (drive absent, silent or a dropped request).
        corrupted: replies damaged by a ``corrupt`` fault.
        ignored: frames RMD drives never look at (CAN extended or remote frames).
        undelivered: replies lost because the client could not take them (slcan channel closed, pty full).
        adapter_errors: slcan commands answered with BELL.
    """

    requests: int = 0
    replies: int = 0
    decode_errors: int = 0
    unanswered: int = 0
    corrupted: int = 0
    ignored: int = 0
    undelivered: int = 0
    adapter_errors: int = 0


@dataclass(order=True, slots=True)
class _Pending(Generic[W]):
    due_s: float
    seq: int
    needs_bus: bool
    outgoing: Outgoing[W] = field(compare=False)


def _can_text(frame: CanFrame) -> str:
    return f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}"


class Attachment(ABC, Closing, Generic[W, R]):
    """Base of the attachments: the thread, reply scheduling, counters and logging.

    Args:
        emulator: the drives to attach.
        channel: short name used in logs.
        timing: latency and bus-time model.
        frame_log: where to log every frame, or None.
    """

    def __init__(
        self, emulator: Emulator, channel: str, timing: TimingModel, frame_log: FrameLog | None, line: int = 0
    ) -> None:
        self.emulator = emulator
        self.channel = channel
        #: The bus this attachment is (an emulator of an arm on several buses has one attachment per bus).
        self.line = line
        self.timing = timing
        self.stats = AttachmentStats()
        #: The exception that stopped the thread, if any.
        self.failure: BaseException | None = None
        self._frame_log = frame_log
        self._bus = BusClock()
        self._pending: list[_Pending[W]] = []
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"rmd-emulator-{channel}", daemon=True)
        self._closed = False

    @property
    @abstractmethod
    def path(self) -> str:
        """What a client opens (a pty path or a virtual channel)."""

    @abstractmethod
    def _receive(self, timeout_s: float) -> list[R]:
        """Wait at most ``timeout_s`` for input; return the received frames (answering adapter commands itself)."""

    @abstractmethod
    def _on_input(self, item: R, now_s: float) -> None:
        """Execute one received frame (with :meth:`_accept` or :meth:`_bad`)."""

    @abstractmethod
    def _wire_time(self, wire: W) -> float:
        """Time a reply occupies the bus, s."""

    @abstractmethod
    def _wire_text(self, wire: W) -> str:
        """A reply in hex for the frame log."""

    @abstractmethod
    def _transmit_all(self, wires: list[W]) -> list[bool]:
        """Send the replies due now to the host, in order; whether each was delivered."""

    @abstractmethod
    def _close_io(self) -> None:
        """Release the bus or pty."""

    def _start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                timeout = TICK_S
                if self._pending:
                    timeout = min(timeout, max(0.0, self._pending[0].due_s - time.monotonic()))
                received = self._receive(timeout)
                now = time.monotonic()
                self.emulator.sync(now)
                for item in received:
                    self._on_input(item, now)
                self._unsolicited(now)
                self._flush()
        except Exception as exc:
            logger.exception("%s: emulator attachment stopped", self.channel)
            self.failure = exc

    def _unsolicited(self, now_s: float) -> None:
        """Schedule the frames the drives send without a request (none on this link)."""

    def _schedule(self, outgoing: Outgoing[W], ready_s: float) -> None:
        self._seq += 1
        heapq.heappush(self._pending, _Pending(ready_s, self._seq, self.timing.bus_time, outgoing))

    def _log(self, direction: str, wire: str, decoded: str) -> None:
        if self._frame_log is not None:
            self._frame_log.write(direction, self.channel, wire, decoded)

    def _bad(self, wire: str, error: DecodeError | str) -> None:
        """Count and log input that breaks the protocol; it gets no answer."""
        self.stats.decode_errors += 1
        logger.warning(
            "%s: protocol-breaking input not answered (%d so far): %s", self.channel, self.stats.decode_errors, error
        )
        self._log("BAD", wire, f"{type(error).__name__}: {error}" if isinstance(error, DecodeError) else error)

    def _accept(self, exchange: Exchange[W], request: W, arrival_s: float) -> None:
        """Log a decoded request (the text only where a frame log is written) and schedule its replies."""
        if self._frame_log is not None:
            wire = self._wire_text(request)
            target = f"motor {exchange.motor_id}" if exchange.motor_id is not None else "motors 1-4"
            self._log("IN", wire, f"{target}: {exchange.request}")
            for note in exchange.notes:
                self._log("NOTE", wire, note)
        if not exchange.replies:
            self.stats.unanswered += 1
        request_end = self._bus.occupy(arrival_s, self._wire_time(request)) if self.timing.bus_time else arrival_s
        for outgoing in exchange.replies:
            self._schedule(outgoing, request_end + self.timing.reply_delay_s() + outgoing.delay_s)

    def _flush(self) -> None:
        now = time.monotonic()
        due: list[Outgoing[W]] = []
        while self._pending and self._pending[0].due_s <= now:
            pending = heapq.heappop(self._pending)
            outgoing = pending.outgoing
            if pending.needs_bus:
                # The reply is ready: it takes the bus when free and reaches the host when its last bit has.
                end = self._bus.occupy(pending.due_s, self._wire_time(outgoing.wire))
                heapq.heappush(self._pending, _Pending(end, pending.seq, False, outgoing))
                continue
            due.append(outgoing)
        if not due:
            return
        for outgoing, delivered in zip(due, self._transmit_all([o.wire for o in due]), strict=True):
            if not delivered:
                self.stats.undelivered += 1
                if self._frame_log is not None:
                    note = f"motor {outgoing.motor_id}: reply not delivered (client not listening)"
                    self._log("NOTE", self._wire_text(outgoing.wire), note)
                continue
            self.stats.replies += 1
            self.stats.corrupted += outgoing.corruption is not None
            if self._frame_log is not None:  # (the text only where it is written: a message's repr is not free)
                damage = f" [corrupted: {outgoing.corruption.value}]" if outgoing.corruption is not None else ""
                self._log(
                    "OUT", self._wire_text(outgoing.wire), f"motor {outgoing.motor_id}: {outgoing.message}{damage}"
                )

    def close(self) -> None:
        """Stop the thread and release the bus; safe to call twice.

        Raises:
            RuntimeError: the thread had stopped on an exception (chained).
        """
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(_JOIN_TIMEOUT_S)
        self._close_io()
        if self.failure is not None:
            raise RuntimeError(f"{self.channel}: emulator attachment failed: {self.failure}") from self.failure


class _CanAttachment(Attachment[CanFrame, CanFrame]):
    """Shared CAN handling: decode, execute, time frames at the bit rate."""

    @property
    @abstractmethod
    def bitrate(self) -> int:
        """Bit rate of the bus-time model, bit/s."""

    def _on_input(self, item: CanFrame, now_s: float) -> None:
        self.stats.requests += 1
        try:
            exchange = self.emulator.handle_can(item, self.line)
        except DecodeError as exc:
            self._bad(_can_text(item), exc)
            return
        self._accept(exchange, item, now_s)

    def _unsolicited(self, now_s: float) -> None:
        """V3 drives' replies without requests (0xB6), due by now (the loop wakes every tick)."""
        for outgoing in self.emulator.active_replies(line=self.line):
            self._schedule(outgoing, now_s)

    def _wire_time(self, wire: CanFrame) -> float:
        return can_frame_time_s(wire.arbitration_id, wire.data, self.bitrate)

    def _wire_text(self, wire: CanFrame) -> str:
        return _can_text(wire)


class VirtualCanAttachment(_CanAttachment):
    """The drives on python-can's in-process ``virtual`` bus: open ``CanEndpoint('virtual', channel)`` to talk.

    Args:
        emulator: the drives.
        channel: virtual bus channel name.
        bitrate: bit rate of the bus-time model, bit/s (the virtual bus itself has none).
        timing: latency and bus-time model.
        frame_log: where to log every frame, or None.

    Raises:
        TransportError: the virtual bus could not be opened.
    """

    def __init__(
        self,
        emulator: Emulator,
        channel: str,
        *,
        bitrate: int = DEFAULT_CAN_BITRATE,
        timing: TimingModel | None = None,
        frame_log: FrameLog | None = None,
        line: int = 0,
    ) -> None:
        if bitrate <= 0:
            raise ValueError(f"bit rate must be > 0 bit/s, got {bitrate}")
        super().__init__(emulator, f"can:{channel}", timing or TimingModel(), frame_log, line)
        self._bitrate = bitrate
        self._virtual_channel = channel
        self._endpoint = CanEndpoint("virtual", channel)
        self._start()

    @property
    def path(self) -> str:
        """The virtual channel name."""
        return self._virtual_channel

    @property
    def bitrate(self) -> int:
        """Bit rate of the bus-time model, bit/s."""
        return self._bitrate

    def _receive(self, timeout_s: float) -> list[CanFrame]:
        frames: list[CanFrame] = []
        received = self._endpoint.recv(timeout_s)
        while received is not None:
            frames.append(received[0])
            received = self._endpoint.recv(0.0)  # drain what else is queued without waiting
        return frames

    def _transmit_all(self, wires: list[CanFrame]) -> list[bool]:
        for wire in wires:
            self._endpoint.send(wire)
        return [True] * len(wires)

    def _close_io(self) -> None:
        self._endpoint.close()


class _OnPty:
    """What the pty attachments share: the pty, its path, non-blocking writes."""

    _pty: PseudoTerminal

    @property
    def path(self) -> str:
        """What a client opens: the link, or the pty slave device."""
        return self._pty.path

    @property
    def device_path(self) -> str:
        """The pty slave device (``/dev/pts/N``)."""
        return self._pty.slave_path

    def _write(self, data: bytes) -> bool:
        """Write to the client; False if it did not fit (nobody reads)."""
        return self._pty.write(data) == 0

    def _write_all(self, chunks: list[bytes | None]) -> list[bool]:
        """Write the chunks to the client in one write (one system call for the replies due at once; None: a chunk
        that cannot be delivered); whether each was delivered (a write is delivered or dropped whole)."""
        data = b"".join(chunk for chunk in chunks if chunk)
        written = self._write(data) if data else True
        return [written and chunk is not None for chunk in chunks]

    def _close_io(self) -> None:
        self._pty.close()


class SlcanAttachment(_OnPty, _CanAttachment):
    """The drives behind a virtual slcan USB-CAN adapter on a pseudo-terminal.

    ``can.Bus(interface='slcan', channel=attachment.path, bitrate=1000000)`` opens it from any process (pass
    ``sleep_after_open=0`` to skip python-can's wait for a real adapter to boot).

    Args:
        emulator: the drives.
        link: path of a symlink to create to the pty (stable across runs), or None.
        timing: latency and bus-time model (the bit rate is the one the host sets with ``Sn``).
        frame_log: where to log every frame, or None.

    Raises:
        TransportError: the pty or the link could not be created.
    """

    def __init__(
        self,
        emulator: Emulator,
        link: str | os.PathLike[str] | None = None,
        *,
        timing: TimingModel | None = None,
        frame_log: FrameLog | None = None,
        line: int = 0,
    ) -> None:
        self._pty = PseudoTerminal(link)
        super().__init__(emulator, "slcan" + (f"-{line}" if line else ""), timing or TimingModel(), frame_log, line)
        self.device = SlcanDevice()
        self._start()

    @property
    def bitrate(self) -> int:
        """The bit rate the host set, bit/s."""
        return self.device.bitrate

    def _receive(self, timeout_s: float) -> list[CanFrame]:
        data = self._pty.read(timeout_s)
        if not data:
            return []
        errors = self.device.errors
        answer, frames = self.device.feed(data)
        self.stats.adapter_errors += self.device.errors - errors
        if answer:
            self._write(answer)
        out: list[CanFrame] = []
        for frame in frames:
            if frame.extended or frame.remote:
                self.stats.ignored += 1
                self._log("NOTE", f"{frame.arbitration_id:X}", "extended or remote frame: no RMD drive listens")
            else:
                out.append(CanFrame(frame.arbitration_id, frame.data))
        return out

    def _transmit_all(self, wires: list[CanFrame]) -> list[bool]:
        # (a closed channel delivers nothing; with auto-poll off the adapter queues the line: delivered, no bytes)
        device, now = self.device, time.monotonic()
        return self._write_all([device.to_host(wire, now) if device.is_open else None for wire in wires])


class Rs485Attachment(_OnPty, Attachment[bytes, bytes]):
    """The drives on an RS485 line emulated by a pseudo-terminal (open :attr:`path` with pyserial, any baud).

    Args:
        emulator: the drives.
        link: path of a symlink to create to the pty (stable across runs), or None.
        baud: baud rate of the bus-time model, bit/s.
        timing: latency and bus-time model.
        frame_log: where to log every frame, or None.

    Raises:
        TransportError: the pty or the link could not be created.
    """

    def __init__(
        self,
        emulator: Emulator,
        link: str | os.PathLike[str] | None = None,
        *,
        baud: int = DEFAULT_RS485_BAUD,
        timing: TimingModel | None = None,
        frame_log: FrameLog | None = None,
        line: int = 0,
    ) -> None:
        if baud <= 0:
            raise ValueError(f"baud rate must be > 0 bit/s, got {baud}")
        self._pty = PseudoTerminal(link)
        super().__init__(emulator, "rs485" + (f"-{line}" if line else ""), timing or TimingModel(), frame_log, line)
        self.baud = baud
        self.parser = emulator.generations[line].rs485_parser()
        self._gap_s = max(_RS485_MIN_GAP_S, rs485_frame_time_s(_RS485_GAP_BYTES, baud))
        self._last_rx_s = 0.0
        self._start()

    def _rejected(self) -> int:
        p = self.parser
        return p.bad_header_checksums + p.bad_data_checksums + p.bad_lengths + p.truncated

    def _receive(self, timeout_s: float) -> list[bytes]:
        if self.parser.pending:
            timeout_s = min(timeout_s, self._gap_s)
        data = self._pty.read(timeout_s)
        now = time.monotonic()
        if data:
            self.parser.feed(data)
            self._last_rx_s = now
        rejected, dropped = self._rejected(), self.parser.dropped_bytes
        flush = now - self._last_rx_s >= self._gap_s
        frames: list[bytes] = []
        while (frame := self.parser.next_bytes(flush=flush)) is not None:
            frames.append(frame)
        # Each rejected candidate (bad checksum, length or id, truncated) is one protocol-breaking frame; bytes
        # dropped without any candidate are line noise, also worth one count.
        bad = self._rejected() - rejected or int(self.parser.dropped_bytes > dropped)
        self.stats.requests += bad
        for _ in range(bad):
            self._bad(
                data.hex(" ") or "(line silent)",
                "RS485 input dropped by the parser (checksum, length, "
                f"id or truncated frame); parser: {self.parser.dropped_bytes} bytes dropped so far",
            )
        return frames

    def _on_input(self, raw: bytes, now_s: float) -> None:
        self.stats.requests += 1
        try:
            exchange = self.emulator.handle_rs485(raw, self.line)
        except DecodeError as exc:
            self._bad(raw.hex(" "), exc)
            return
        self._accept(exchange, raw, now_s)

    def _wire_time(self, wire: bytes) -> float:
        return rs485_frame_time_s(len(wire), self.baud)

    def _wire_text(self, wire: bytes) -> str:
        return wire.hex(" ")

    def _transmit_all(self, wires: list[bytes]) -> list[bool]:
        return self._write_all(list(wires))
