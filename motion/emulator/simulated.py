"""Simulated time: the controller and the emulated drives on one clock, with the wire modelled frame by frame.

No threads and no sleeping: a :class:`Simulation` holds the emulated drives, the frames on the bus and the one
clock both sides read. :class:`SimulatedBus` is a :class:`~motion.transport.base.Transport` whose ``transact``
puts the cycle's requests on the modelled wire, advances the drives to the instant each request has fully arrived
(CAN bits at the bit rate, stuff bits included; RS485 bytes at the baud rate), lets them answer after their latency
(and any ``delay`` fault), and hands each reply to the host at the instant its last bit arrives, or not at all if
that is after the deadline (then it is still on its way, and a later cycle takes it in as stale, as on a real bus).
:class:`SimulatedClock` is the controller's clock: ``sleep_until`` advances the simulation to the deadline.

The host's own computation takes no simulated time: results depend on the drives, the plant and the wire, never on
how fast or busy the host is, so a run gives the same logs on every host and every run. What the host itself can
hold in real time is measured separately (:mod:`motion.control.ratecheck`).

Frame timing follows :mod:`motion.emulator.timing`: one medium, a frame starts when it is ready and the bus is free,
first ready first sent (CAN arbitration by identifier is not modelled). RS485 follows the half-duplex rule of
:class:`~motion.transport.rs485_transport.Rs485Transport` (one request, its reply or the end of its window, then the
next request) with the same per-request windows.
"""

from __future__ import annotations

import heapq
import math
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Final

from motion.emulator.core import Emulator, Exchange, Outgoing
from motion.emulator.framelog import FrameLog
from motion.emulator.timing import TimingModel, can_frame_bits
from motion.errors import DecodeError
from motion.protocol import CanFrame, WireProtocol
from motion.protocol.generation import GENERATIONS
from motion.protocol.rs485_frame import rs485_frame_time_s
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily, split_address
from motion.transport.base import FrameTap, Request, Transport, probe_in_turn
from motion.transport.can_transport import take_in_can_frame
from motion.transport.detect import expected_answers, generations, probe_frames
from motion.transport.plan import FILLED

#: Default CAN bit rate, bit/s (RMD drives run at 1 Mbit/s).
DEFAULT_BITRATE: Final = 1_000_000
#: Default RS485 baud rate, bit/s (the RS485 document's default).
DEFAULT_BAUD: Final = 115_200


_Outgoing = Outgoing[CanFrame] | Outgoing[bytes]


@dataclass(order=True, slots=True)
class _Frame:
    """A frame waiting for its wire."""

    ready_s: float
    seq: int
    request: bool = field(compare=False)
    wire: CanFrame | bytes = field(compare=False)
    outgoing: _Outgoing | None = field(compare=False, default=None)


@dataclass(frozen=True, slots=True)
class Arrival:
    """A reply whose last bit reached the host at ``time_s``, on line ``line``."""

    time_s: float
    motor_id: int
    wire: CanFrame | bytes
    line: int = 0


#: The most CAN frames whose bit counts a simulation remembers (then it starts again).
_FRAME_BITS_KEPT = 4096


@dataclass(slots=True)
class _Line:
    """One wire of a simulation (a bus): its frames wait in ``queue`` and go out one at a time."""

    index: int
    protocol: WireProtocol
    rate: int  # bit/s: the CAN bit rate or the RS485 baud rate
    channel: str
    queue: list[_Frame] = field(default_factory=list)
    busy_until_s: float = 0.0
    current: _Frame | None = None  # the frame on the wire now, until busy_until_s


class Simulation:
    """Emulated drives on modelled wires, and the one clock of the run.

    One wire (a bus) by default; ``lines`` gives several, each a medium of its own whose frames go out at the same
    time as the others' (an arm on several buses): line ``k`` carries the drives whose addresses are
    ``k × ADDRESS_STRIDE + motor id`` (:mod:`motion.protocol.table`).

    Args:
        emulator: the drives (their simulation time is the run's start).
        protocol: CAN or RS485 (of the one line).
        bitrate: CAN bit rate, bit/s (of the one line).
        baud: RS485 baud rate, bit/s (of the one line).
        timing: the drives' reply latency (the bus-time model is always on here).
        frame_log: where to log every frame (at its simulated time), or None.
        lines: several lines instead, each ``(protocol, bit rate or baud rate)``.

    Raises:
        ValueError: a bit rate or baud rate that is not positive, or no line.
    """

    def __init__(
        self,
        emulator: Emulator,
        protocol: WireProtocol = WireProtocol.CAN,
        *,
        bitrate: int = DEFAULT_BITRATE,
        baud: int = DEFAULT_BAUD,
        timing: TimingModel | None = None,
        frame_log: FrameLog | None = None,
        lines: Sequence[tuple[WireProtocol, int]] | None = None,
    ) -> None:
        if lines is None:
            lines = [(protocol, bitrate if protocol is WireProtocol.CAN else baud)]
        if not lines or any(rate <= 0 for _, rate in lines) or bitrate <= 0 or baud <= 0:
            raise ValueError(f"bit rates and baud rates must be > 0 bit/s and a line given, got {lines}")
        self.emulator = emulator
        self.now_s = emulator.time_s
        self.lines = [
            _Line(k, p, rate, f"sim-{p.value.lower()}" + (f"-{k}" if k else ""), busy_until_s=self.now_s)
            for k, (p, rate) in enumerate(lines)
        ]
        self.protocol = self.lines[0].protocol
        self.bitrate = self.lines[0].rate if self.protocol is WireProtocol.CAN else bitrate
        self.baud = self.lines[0].rate if self.protocol is WireProtocol.RS485 else baud
        self._frame_bits: dict[tuple[int, bytes], int] = {}  # (the frames of a run repeat: their bits, remembered)
        self.timing = timing or TimingModel()
        self.frame_log = frame_log
        self.channel = self.lines[0].channel
        self._arrived: deque[Arrival] = deque()
        self._seq = 0
        #: Requests that broke the protocol (never answered), and requests no drive answered.
        self.decode_errors = 0
        self.unanswered = 0

    # --- the clock ------------------------------------------------------------------------------------------

    def now(self) -> float:
        """Simulated time, s."""
        return self.now_s

    def sleep_until(self, deadline_s: float) -> None:
        """Let the wires and the drives run until ``deadline_s`` (never backwards)."""
        if deadline_s > self.now_s:
            self._run_bus(deadline_s)
            self.now_s = deadline_s
            self.emulator.advance_to(deadline_s)

    # --- the wire -------------------------------------------------------------------------------------------

    def wire_time_s(self, wire: CanFrame | bytes, line: int = 0) -> float:
        """Time a frame occupies line ``line``, s."""
        rate = self.lines[line].rate
        if isinstance(wire, CanFrame):
            key = (wire.arbitration_id, wire.data)
            bits = self._frame_bits.get(key)
            if bits is None:
                if len(self._frame_bits) >= _FRAME_BITS_KEPT:
                    self._frame_bits.clear()
                bits = self._frame_bits[key] = can_frame_bits(*key)
            return bits / rate
        return rs485_frame_time_s(len(wire), rate)

    def submit(self, wire: CanFrame | bytes, line: int = 0) -> None:
        """The host hands a request to line ``line`` now."""
        self._push(self.lines[line], self.now_s, True, wire, None)

    def _push(self, line: _Line, ready_s: float, request: bool, wire: CanFrame | bytes, out: _Outgoing | None) -> None:
        self._seq += 1
        heapq.heappush(line.queue, _Frame(ready_s, self._seq, request, wire, out))

    def next_arrival(self, limit_s: float) -> Arrival | None:
        """Run the wires until a reply reaches the host by ``limit_s``; the first such reply, or None.

        A reply that arrives after ``limit_s`` stays on its way (a later call or cycle takes it in).
        """
        if not self._arrived:
            self._run_bus(limit_s, stop_at_arrival=True)
        if self._arrived and self._arrived[0].time_s <= limit_s:
            return self._arrived.popleft()
        return None

    def arrived_by(self, t_s: float) -> list[Arrival]:
        """Every reply that reached the host by ``t_s`` and was not taken yet (in arrival order)."""
        self._run_bus(t_s)
        out = []
        while self._arrived and self._arrived[0].time_s <= t_s:
            out.append(self._arrived.popleft())
        return out

    def _run_bus(self, limit_s: float, *, stop_at_arrival: bool = False) -> None:
        """Run the wires' events in time order while the next one is by ``limit_s``: a frame's last bit (a request
        reaches the drives, a reply the host), a waiting frame's first (its wire free, first ready first sent), a V3
        drive's own reply falling due."""
        lines, emulator = self.lines, self.emulator
        while True:
            when, line, ends = math.inf, lines[0], False
            for candidate in lines:
                if candidate.current is not None:
                    if candidate.busy_until_s < when or (candidate.busy_until_s == when and not ends):
                        when, line, ends = candidate.busy_until_s, candidate, True
                elif candidate.queue:
                    start = max(candidate.queue[0].ready_s, candidate.busy_until_s)
                    if start < when:
                        when, line, ends = start, candidate, False
            due = emulator.next_active_reply_s()  # (V3 drives' replies without requests, 0xB6; CAN only)
            if due is not None and due <= limit_s and due <= when:
                emulator.advance_to(due)
                for outgoing in emulator.active_replies(due):
                    target = lines[split_address(outgoing.motor_id)[0]]
                    self._push(target, due + self.timing.reply_delay_s(), False, outgoing.wire, outgoing)
                continue
            if when > limit_s:
                return
            if not ends:
                started = line.current = heapq.heappop(line.queue)
                line.busy_until_s = when + self.wire_time_s(started.wire, line.index)
                continue
            frame = line.current
            assert frame is not None
            line.current = None
            if frame.request:
                self._execute(frame.wire, when, line)
                continue
            assert frame.outgoing is not None  # every reply frame carries its outgoing record
            self._arrived.append(Arrival(when, frame.outgoing.motor_id, frame.wire, line.index))
            if self.frame_log is not None:  # (the text only where it is written: a message's repr is not free)
                self._log(line, "OUT", frame.wire, f"motor {frame.outgoing.motor_id}: {frame.outgoing.message}", when)
            if stop_at_arrival:
                return

    def _execute(self, wire: CanFrame | bytes, arrival_s: float, line: _Line) -> None:
        """A request reached the drives of ``line`` at ``arrival_s``: advance them there, execute it, queue the
        replies."""
        self.emulator.advance_to(arrival_s)
        exchange: Exchange[CanFrame] | Exchange[bytes]
        try:
            if isinstance(wire, CanFrame):
                exchange = self.emulator.handle_can(wire, line.index)
            else:
                exchange = self.emulator.handle_rs485(wire, line.index)
        except DecodeError as exc:
            self.decode_errors += 1
            self._log(line, "BAD", wire, f"{type(exc).__name__}: {exc}", arrival_s)
            return
        if self.frame_log is not None:
            target = f"motor {exchange.motor_id}" if exchange.motor_id is not None else "motors 1-4"
            self._log(line, "IN", wire, f"{target}: {exchange.request}", arrival_s)
            for note in exchange.notes:
                self._log(line, "NOTE", wire, note, arrival_s)
        if not exchange.replies:
            self.unanswered += 1
        for outgoing in exchange.replies:
            ready = arrival_s + self.timing.reply_delay_s() + outgoing.delay_s
            self._push(line, ready, False, outgoing.wire, outgoing)

    def _log(self, line: _Line, direction: str, wire: CanFrame | bytes, decoded: str, time_s: float) -> None:
        if self.frame_log is not None:
            text = f"{wire.arbitration_id:03X}: {wire.data.hex(' ')}" if isinstance(wire, CanFrame) else wire.hex(" ")
            self.frame_log.write(direction, line.channel, text, decoded, time_s=time_s)


class SimulatedBus(Transport):
    """The transport of a :class:`Simulation`: the same slots, matching and counters as the real backends.

    Its clock is the simulation's (pass ``simulation`` as the controller's clock too).

    Args:
        simulation: the simulated lines and drives.
        family: the protocol generation it speaks on every line; a sequence: each line's; None: each line's drives'.
        names: the lines' names (an arm's buses).
    """

    def __init__(
        self,
        simulation: Simulation,
        family: ProtocolFamily | Sequence[ProtocolFamily] | None = None,
        *,
        names: Sequence[str] = (),
    ) -> None:
        count, emulated = len(simulation.lines), simulation.emulator.families
        if family is None:
            per_line = [emulated[k] if k < len(emulated) else emulated[0] for k in range(count)]
        else:
            per_line = [family] * count if isinstance(family, str) else list(family)
            if len(per_line) != count:
                raise ValueError(f"protocol generations {per_line}: one for each of the {count} lines expected")
        super().__init__(clock=simulation.now, family=per_line[0])
        self.families = tuple(ProtocolFamily(f) for f in per_line)
        self.simulation = simulation
        #: The lines' names (an arm's buses), for the rate check's figures per bus; empty: not told.
        self.names = tuple(names)
        self._line_took_s = [0.0] * len(simulation.lines)  # each line's share of the last exchange, s
        self._started_s = simulation.now_s
        #: Per line, whether it is a CAN bus (else an RS485 line).
        self._line_can = [line.protocol is WireProtocol.CAN for line in simulation.lines]
        self._can = all(self._line_can)
        self._one_line = len(simulation.lines) == 1
        #: Each line's codec (its generation's).
        self._generations = [GENERATIONS[f] for f in self.families]
        self._encoders = [
            g.encode_can_request if can else g.encode_rs485_request
            for g, can in zip(self._generations, self._line_can, strict=True)
        ]
        self._wires: list[CanFrame | bytes] = []
        self._lines: list[int] = []
        self._motors: list[int] = []

    def probe_families(self, ids: Sequence[int], window_s: float) -> dict[int, ProtocolFamily] | None:
        """See :meth:`Transport.probe_families`: on CAN at the frame level over the simulated wire; on RS485 a status
        read in each generation's framing in turn (as :class:`~motion.transport.rs485_transport.Rs485Transport`)."""
        if not self._can:  # (an RS485 line among the lines: each drive asked in turn)
            return probe_in_turn(self, ids, window_s, lambda family: SimulatedBus(self.simulation, family))
        sim = self.simulation
        sim.arrived_by(sim.now_s)  # what was sent before is nobody's answer
        on_line: dict[int, list[int]] = {}
        for address in sorted(set(ids)):
            line, motor_id = split_address(address)
            on_line.setdefault(line, []).append(motor_id)
        wanted = {line: expected_answers(motor_ids) for line, motor_ids in on_line.items()}
        for line, motor_ids in on_line.items():
            for frame in probe_frames(motor_ids):
                sim.submit(frame, line)
        end = sim.now_s + window_s
        answered: dict[int, set[int]] = {line: set() for line in on_line}
        while sum(map(len, answered.values())) < len(set(ids)):
            arrival = sim.next_arrival(end)
            if arrival is None:
                sim.sleep_until(end)
                break
            sim.now_s = arrival.time_s
            wire, line = arrival.wire, arrival.line
            if isinstance(wire, CanFrame) and wanted.get(line, {}).get(wire.arbitration_id) == wire.data[0]:
                answered[line].add(wire.arbitration_id)
        self._read_behind_the_slots()  # (the late replies it drained are no outstanding answer any more)
        return {
            line * ADDRESS_STRIDE + motor_id: family
            for line, found in answered.items()
            for motor_id, family in generations(found).items()
        }

    def with_family(self, family: ProtocolFamily) -> SimulatedBus:
        """See :meth:`Transport.with_family`."""
        return self.with_families([family] * len(self.families))

    def with_families(self, families: Sequence[ProtocolFamily]) -> SimulatedBus:
        """See :meth:`Transport.with_families`: each line's generation (itself where they are its own)."""
        if tuple(families) == self.families:
            return self
        bus = SimulatedBus(self.simulation, families, names=self.names)
        bus.frame_tap = self.frame_tap
        return bus

    def request_wire_s(self, requests: Sequence[Request]) -> float | None:
        """See :meth:`Transport.request_wire_s`: the simulated wire's own timing."""
        sim, busy = self.simulation, [0.0] * len(self.simulation.lines)
        for request in requests:
            line, motor_id = split_address(request.motor_id)
            busy[line] += sim.wire_time_s(self._encoders[line](request.message, motor_id), line)
        return max(busy)  # (the lines carry their frames at the same time)

    def describe(self) -> str:
        """``"simulated can"``, ``"simulated rs485"`` (``"simulated can + rs485"``: lines of both)."""
        return "simulated " + " + ".join(dict.fromkeys(line.protocol.value.lower() for line in self.simulation.lines))

    def _prepare(self, requests: Sequence[Request]) -> None:
        wires, lines, motors = self._wires, self._lines, self._motors
        wires.clear()
        lines.clear()
        motors.clear()
        encoders = self._encoders
        for request in requests:
            line, motor_id = split_address(request.motor_id)  # (one line: the motor id itself)
            wires.append(encoders[line](request.message, motor_id))
            lines.append(line)
            motors.append(request.motor_id)

    def _exchange(self, deadline_s: float) -> None:
        self._started_s = self.simulation.now_s
        timed = len(self.names) > 1  # (each line's time, for the rate check's figure per bus)
        if timed:
            self._line_took_s[:] = [0.0] * len(self._line_took_s)
        if self._can:
            self._exchange_can(deadline_s)
        elif self._one_line:
            self._exchange_rs485(deadline_s)
        else:
            self._exchange_lines(deadline_s)
        if timed:  # a line whose replies did not all come took the whole exchange (as a bus's worker in real time)
            plan, state, took = self._slots, self._slot_state, self._line_took_s
            first, whole = plan.first_slot, self.simulation.now_s - self._started_s
            for index, line in enumerate(self._lines):
                if any(state[slot] != FILLED for slot in range(first[index], first[index + 1])):
                    took[line] = whole

    def bus_times_s(self) -> Mapping[str, float] | None:
        """See :meth:`Transport.bus_times_s`: each line's time from the exchange's start to its last reply, or to the
        exchange's end where one of its replies did not come."""
        if len(self.names) < 2:
            return None
        return dict(zip(self.names, self._line_took_s, strict=False))

    def _exchange_can(self, deadline_s: float) -> None:
        sim = self.simulation
        for stale in sim.arrived_by(sim.now_s):  # a previous cycle's replies
            self._take_in(stale)
        for index, (wire, line) in enumerate(zip(self._wires, self._lines, strict=True)):
            sim.submit(wire, line)
            self._sent(index)
            self._tap(False, wire, line)
        while self._open_slots:
            arrival = sim.next_arrival(deadline_s)
            if arrival is None:
                sim.sleep_until(deadline_s)
                return
            sim.now_s = arrival.time_s
            self._take_in(arrival)

    def _exchange_rs485(self, deadline_s: float) -> None:
        sim, count = self.simulation, len(self._wires)
        for index, wire in enumerate(self._wires):
            now = sim.now_s
            if now >= deadline_s:
                return
            window_end_s = now + (deadline_s - now) / (count - index)
            for stale in sim.arrived_by(now):  # a line is half duplex: what came before the request is stale
                self._take_in(stale)
            sim.submit(wire)
            self._sent(index)
            self._tap(False, wire)
            while not self._answered(index):
                arrival = sim.next_arrival(window_end_s)
                if arrival is None:
                    sim.sleep_until(window_end_s)
                    self._expire(index)
                    break
                sim.now_s = arrival.time_s
                self._take_in(arrival, waiting_for=self._motors[index])

    def _exchange_lines(self, deadline_s: float) -> None:
        """Lines of both transports, or several RS485 lines, at the same time: a CAN bus's frames go out at once, an
        RS485 line's requests one after the other (the next when the one before is answered or its share of what
        is left of the cycle has passed, as :meth:`_exchange_rs485` on one line)."""
        sim = self.simulation
        for stale in sim.arrived_by(sim.now_s):  # a previous cycle's replies
            self._take_in(stale)
        waiting: dict[int, deque[int]] = {}  # per RS485 line, its requests not sent yet
        for index, (wire, line) in enumerate(zip(self._wires, self._lines, strict=True)):
            if self._line_can[line]:
                sim.submit(wire, line)
                self._sent(index)
                self._tap(False, wire, line)
            else:
                waiting.setdefault(line, deque()).append(index)
        current: dict[int, tuple[int, float]] = {}  # per RS485 line, its request on the wire and that one's end
        for line, queue in waiting.items():
            self._send_next(line, queue, current, deadline_s)
        while self._open_slots or current:
            limit = min([deadline_s, *(end for _, end in current.values())])
            arrival = sim.next_arrival(limit)
            if arrival is None:
                sim.sleep_until(limit)
                if limit >= deadline_s:
                    return
                for line, (index, end) in list(current.items()):
                    if end <= sim.now_s:
                        self._expire(index)
                        self._send_next(line, waiting[line], current, deadline_s)
                continue
            sim.now_s = arrival.time_s
            on_wire = current.get(arrival.line)
            self._take_in(arrival, waiting_for=None if on_wire is None else self._motors[on_wire[0]])
            if on_wire is not None and self._answered(on_wire[0]):
                self._send_next(arrival.line, waiting[arrival.line], current, deadline_s)

    def _send_next(
        self, line: int, waiting: deque[int], current: dict[int, tuple[int, float]], deadline_s: float
    ) -> None:
        """Send RS485 line ``line``'s next request, with its share of the time left (none left: the line is done)."""
        current.pop(line, None)
        now = self.simulation.now_s
        if not waiting or now >= deadline_s:
            return
        index = waiting.popleft()
        wire = self._wires[index]
        self.simulation.submit(wire, line)
        self._sent(index)
        self._tap(False, wire, line)
        current[line] = (index, now + (deadline_s - now) / (len(waiting) + 1))

    @property
    def frame_tap(self) -> FrameTap | None:
        """Every line's frames (see :data:`FrameTap`); a tap that tells an arm's buses apart (a bus trace) records
        each line's as its bus's (its ``on_bus(index)``)."""
        return self._frame_tap

    @frame_tap.setter
    def frame_tap(self, tap: FrameTap | None) -> None:
        self._frame_tap = tap
        per_bus = getattr(tap, "on_bus", None)
        lines = len(self.simulation.lines) if hasattr(self, "simulation") else 1
        self._line_taps = [] if tap is None else [per_bus(k) if per_bus else tap for k in range(lines)]

    def _tap(self, received: bool, wire: CanFrame | bytes, line: int = 0) -> None:
        if self._frame_tap is not None:
            tap = self._line_taps[line]
            if isinstance(wire, CanFrame):
                tap(self.simulation.now_s, received, wire.arbitration_id, wire.data)
            else:
                tap(self.simulation.now_s, received, None, wire)

    def _take_in(self, arrival: Arrival, waiting_for: int | None = None) -> None:
        wire = arrival.wire
        if isinstance(wire, CanFrame):
            self._tap(True, wire, arrival.line)
            take_in_can_frame(
                self, wire, arrival.line * ADDRESS_STRIDE, tapped=True, generation=self._generations[arrival.line]
            )
            took = self._line_took_s
            took[arrival.line] = max(took[arrival.line], arrival.time_s - self._started_s)
            return
        line = arrival.line
        self._tap(True, wire, line)
        try:
            motor_id, message = self._generations[line].decode_rs485_reply(wire)
            if motor_id is None:  # a V3 id-setting reply on 0xCD: not the control loop's
                self.bus_counters.unknown_id_frames += 1
                return
        except DecodeError:
            # On a half-duplex line only the addressed drive talks: corrupt bytes count against it.
            self.motor_counters(arrival.motor_id if waiting_for is None else waiting_for).bad_frames += 1
            return
        took = self._line_took_s
        took[line] = max(took[line], arrival.time_s - self._started_s)
        self._offer(line * ADDRESS_STRIDE + motor_id, message)

    def _close(self) -> None:
        """Nothing to release."""


#: A paced simulation this far behind the wall clock (it waited for the program) starts pacing again from there, s.
PACE_SLACK_S: Final = 0.1


class SimulatedClock:
    """The controller's clock in a :class:`Simulation` (see :class:`~motion.control.clock.Clock`).

    ``simulated`` tells the control loop to run its cycles in the thread that waits for them, not in a thread of
    its own: simulated time passes only while the program waits (for a motion, or :meth:`motion.api.Arm.sleep`).
    """

    simulated: Final = True

    def __init__(self, simulation: Simulation) -> None:
        self.simulation = simulation
        self._pace: tuple[float, float, float] | None = None  # (wall clock, simulated time, factor) at pace()

    def now(self) -> float:
        """Simulated time, s."""
        return self.simulation.now_s

    def pace(self, factor: float = 1.0) -> None:
        """From now on, keep simulated time from running ahead of the wall clock times ``factor`` (a live view then
        shows the motion at its own speed). Only the waiting changes: every result stays the same.

        Raises:
            ValueError: ``factor`` is not positive and finite.
        """
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"pace factor {factor!r} must be > 0")
        self._pace = (time.monotonic(), self.simulation.now_s, factor)

    def sleep_until(self, deadline_s: float) -> None:
        """Advance the simulation to ``deadline_s`` (with :meth:`pace`, not before the wall clock is there)."""
        if self._pace is not None:
            wall0, sim0, factor = self._pace
            now = time.monotonic()
            wait = wall0 + (deadline_s - sim0) / factor - now
            if wait > 0:
                time.sleep(wait)
            elif wait < -PACE_SLACK_S:  # it waited for the program (nothing ran): go on from here, no catching up
                self._pace = (now, deadline_s, factor)
        self.simulation.sleep_until(deadline_s)


__all__ = ["DEFAULT_BAUD", "DEFAULT_BITRATE", "Arrival", "SimulatedBus", "SimulatedClock", "Simulation"]
