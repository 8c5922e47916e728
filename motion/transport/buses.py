"""An arm on several buses as one transport (issue 35).

Control and safety name each drive by its address, ``bus index × ADDRESS_STRIDE + motor id``
(:data:`motion.protocol.table.ADDRESS_STRIDE`; the first bus's addresses are the motor ids themselves), so the
controller, the watchdog and the supervisor stay keyed by one number per drive and never ask which bus a drive is on.
:class:`Buses` splits a cycle's batch by bus, runs the buses' exchanges at the same time (the first in the calling
thread, each other in a worker thread of its own: a backend waits on its port with the GIL released, so the buses'
waits overlap) and merges the replies back into the request order, each named by its address. A 0x280 multi-motor
frame goes to the bus of its request's address (motors 1..4 of that bus).

A fault on one bus is every bus's, and the other buses stay reachable:

- a bus whose port is gone raises :class:`~motion.errors.PortLost` from :meth:`transact` once, in the cycle that
  found it (after the other buses' batches went out): the arm halts in that cycle. From then on the bus is skipped and
  its drives' replies are missing, as silent drives' are: their halts are owed for ever, the other buses' drives are
  halted, acknowledged, braked and closed as usual. The transport counts as closed once every bus is gone;
- a bus whose exchange has not ended :data:`WORKER_GRACE_S` after the deadline (a wedged driver, a thread kept off
  the CPU) has its replies missing in that cycle, and is skipped while its worker is still in it: the arm sees silent
  drives (its missed-reply rule halts it), never a loop held up by one bus.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping, Sequence
from typing import Final

from motion.errors import PortLost, TransportError
from motion.protocol import MultiMotorTorque
from motion.protocol.table import ADDRESS_STRIDE, MULTI_TORQUE_MOTOR_IDS, ProtocolFamily, split_address
from motion.transport.base import FrameTap, MotorCounters, Reply, Request, Transport

#: How long :meth:`Buses.transact` waits for a worker beyond the deadline, s (a backend returns by its deadline).
WORKER_GRACE_S: Final = 0.005
#: How long closing waits for a worker's thread to end, s.
_JOIN_S: Final = 1.0


class _Worker:
    """A thread that runs one bus's exchanges when handed them (one at a time)."""

    def __init__(self, bus: Transport, name: str) -> None:
        self.bus = bus
        self._requests: Sequence[Request] = ()
        self._deadline_s = 0.0
        self.replies: list[Reply] = []
        self.error: BaseException | None = None
        self.took_s = 0.0  # how long the last exchange took, s
        self._start = threading.Event()
        self._done = threading.Event()
        self._done.set()  # (nothing handed yet)
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"rmd-bus-{name}", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        """Whether the exchange handed last has not ended (its bus must not be touched from another thread)."""
        return not self._done.is_set()

    def submit(self, requests: Sequence[Request], deadline_s: float) -> None:
        """Start an exchange of ``requests`` (collect it with :meth:`result`); not while :attr:`busy`."""
        self._requests, self._deadline_s, self.error = requests, deadline_s, None
        self._done.clear()
        self._start.set()

    def result(self, timeout_s: float) -> list[Reply] | None:
        """The replies of the exchange submitted last, or None when it has not ended within ``timeout_s``.

        Raises:
            TransportError: the bus failed (the backend's own error; PortLost: the port is gone).
        """
        if not self._done.wait(timeout_s):
            return None
        if self.error is not None:
            raise self.error
        return self.replies

    def stop(self) -> None:
        self._stopping = True
        self._start.set()
        self._thread.join(_JOIN_S)

    def _run(self) -> None:
        while True:
            self._start.wait()
            self._start.clear()
            if self._stopping:
                return
            began = self.bus.clock()
            try:
                self.replies = self.bus.transact(self._requests, self._deadline_s)
            except BaseException as exc:  # handed to the control loop's thread, which decides
                self.error = exc
            self.took_s = self.bus.clock() - began
            self._done.set()


class Buses(Transport):
    """Several buses of one arm as one transport (see the module docstring).

    Args:
        buses: the transports, in the order of the configuration's ``buses:`` (index = the address's bus index), of
            one clock; each speaks its own drives' protocol generation (:attr:`families`).
        names: the buses' names, for messages.
        parallel: the buses' exchanges at the same time (a worker thread per bus beyond the first); False: one after
            the other in the calling thread (``bench/buses_bench.py`` measures the difference).

    Raises:
        TransportError: fewer than two buses.
    """

    def __init__(self, buses: Sequence[Transport], names: Sequence[str], *, parallel: bool = True) -> None:
        if len(buses) < 2 or len(names) != len(buses):
            raise TransportError(f"several buses take two or more transports, each named; got {len(buses)}")
        self.buses = tuple(buses)
        self.names = tuple(names)
        super().__init__(clock=buses[0].clock, family=buses[0].family)
        self.families = tuple(bus.family for bus in buses)
        self.parallel = parallel
        self._workers = (
            [_Worker(bus, name) for bus, name in zip(self.buses[1:], self.names[1:], strict=True)] if parallel else []
        )
        self._split: list[list[Request]] = [[] for _ in self.buses]
        self._where: list[int] = []  # per request of the cycle, its bus
        self._took_s = [0.0] * len(self.buses)  # how long each bus's share of the last exchange took, s
        self._gone: set[int] = set()  # the buses found gone (skipped from then on)
        self._tap_lock = threading.Lock()

    # --- the cycle -----------------------------------------------------------------------------------------

    def transact(self, requests: Sequence[Request], deadline_s: float) -> list[Reply]:
        """See :meth:`Transport.transact`: each bus's share at the same time, the replies in request order with the
        drives' addresses (those of a bus gone or late: missing).

        Raises:
            PortLost: a bus's port was found gone in this exchange (the other buses' batches went out first).
            TransportError: a bus failed, or the transport is closed.
        """
        if self._closed:
            raise TransportError(f"{self.describe()} is closed")
        split, buses, gone = self._split_batch(requests), self.buses, self._gone
        self.bus_counters.cycles += 1
        answers: list[list[Reply] | None] = [None] * len(buses)
        handed = [False] * len(buses)
        for k, worker in enumerate(self._workers, start=1):  # (none: sequential)
            if k not in gone and not worker.busy:
                worker.submit(split[k], deadline_s)
                handed[k] = True
        errors: dict[int, BaseException] = {}
        took = self._took_s
        for k in range(len(buses)) if not self.parallel else range(1):  # (the buses this thread exchanges on)
            if k in gone:
                continue
            began = self.clock()
            try:
                answers[k] = buses[k].transact(split[k], deadline_s)
            except BaseException as exc:  # the other buses still end their exchange first
                errors[k] = exc
            took[k] = self.clock() - began
        for k, worker in enumerate(self._workers, start=1):
            if handed[k]:
                try:
                    answers[k] = worker.result(max(0.0, deadline_s - self.clock()) + WORKER_GRACE_S)
                except BaseException as exc:
                    errors[k] = exc
                took[k] = worker.took_s
        self._found_gone(errors)
        if errors:
            raise errors[min(errors)]  # (each names its port)
        return self._merge(requests, answers)

    def _split_batch(self, requests: Sequence[Request]) -> list[list[Request]]:
        """``requests`` by bus, each with its motor id on its bus (kept in :attr:`_split`, the bus of each request in
        :attr:`_where`: the lists are reused from cycle to cycle).

        Raises:
            TransportError: an address names no bus of this arm.
        """
        split, where = self._split, self._where
        for share in split:
            share.clear()
        where.clear()
        for request in requests:
            bus, motor_id = divmod(request.motor_id, ADDRESS_STRIDE)
            if not 0 <= bus < len(split):
                raise TransportError(f"request to address {request.motor_id}: no bus {bus} in {self.describe()}")
            split[bus].append(Request(motor_id, request.message) if bus else request)
            where.append(bus)
        return split

    def _found_gone(self, errors: dict[int, BaseException]) -> None:
        """Take the buses found gone in this exchange out of every later one.

        Raises:
            PortLost: one was (the first of them).
        """
        newly = [
            k
            for k, bus in enumerate(self.buses)
            if k not in self._gone and (bus.lost is not None or bus.closed or isinstance(errors.get(k), PortLost))
        ]
        if not newly:
            return
        self._gone.update(newly)
        for k in newly:
            errors.pop(k, None)
        first = self.buses[newly[0]]
        lost = first.lost or PortLost(f"{first.describe()} closed")
        if self._lost is None:
            self._lost = lost
        names = ", ".join(self.names[k] for k in newly)
        raise PortLost(f"bus {names}: {lost} (the other buses go on; its drives cannot be reached)")

    def _merge(self, requests: Sequence[Request], answers: list[list[Reply] | None]) -> list[Reply]:
        """The buses' replies in request order (a 0x280 request's four in its place), named by address; a bus gone or
        late answers none."""
        streams: list[Iterator[Reply] | None] = [None if a is None else iter(a) for a in answers]
        merged: list[Reply] = []
        for request, bus in zip(requests, self._where, strict=True):
            stream, base = streams[bus], bus * ADDRESS_STRIDE
            multi = isinstance(request.message, MultiMotorTorque)
            if stream is None:
                motors = [base + m for m in MULTI_TORQUE_MOTOR_IDS] if multi else [request.motor_id]
                merged.extend(Reply(motor_id, request.message, None, None) for motor_id in motors)
                continue
            for _ in range(4 if multi else 1):
                reply = next(stream)
                merged.append(reply._replace(motor_id=base + reply.motor_id) if base else reply)
        return merged

    # --- what the buses tell -------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """True once closed, or once every bus is gone (a bus gone among others: its drives read as silent)."""
        return self._closed or len(self._gone) == len(self.buses)

    @property
    def counters(self) -> Mapping[int, MotorCounters]:
        """Per-drive counters by address (a snapshot of every bus's)."""
        return {
            k * ADDRESS_STRIDE + motor_id: counters
            for k, bus in enumerate(self.buses)
            for motor_id, counters in bus.counters.items()
        }

    def motor_counters(self, motor_id: int) -> MotorCounters:
        """The counters of the drive at address ``motor_id`` (its bus's own object)."""
        bus, wire_id = split_address(motor_id)
        return self.buses[bus].motor_counters(wire_id)

    def bus_times_s(self) -> Mapping[str, float] | None:
        """See :meth:`Transport.bus_times_s`."""
        return dict(zip(self.names, self._took_s, strict=True))

    def junk_note(self) -> str:
        """See :meth:`Transport.junk_note`: each bus's."""
        return "".join(bus.junk_note() for bus in self.buses)

    def describe(self) -> str:
        """``"left: can slcan:/dev/ttyACM0, right: can slcan:/dev/ttyACM1"``."""
        return ", ".join(f"{name}: {bus.describe()}" for name, bus in zip(self.names, self.buses, strict=True))

    def probe_families(self, ids: Sequence[int], window_s: float) -> dict[int, ProtocolFamily] | None:
        """See :meth:`Transport.probe_families`: each bus's drives on their bus, by address."""
        found: dict[int, ProtocolFamily] = {}
        for k, bus in enumerate(self.buses):
            mine = [split_address(a)[1] for a in ids if split_address(a)[0] == k]
            if not mine:
                continue
            told = bus.probe_families(mine, window_s)
            if told is None:
                return None
            found.update({k * ADDRESS_STRIDE + i: family for i, family in told.items()})
        return found

    def request_wire_s(self, requests: Sequence[Request]) -> float | None:
        """See :meth:`Transport.request_wire_s`: the busiest bus's share (the buses carry theirs at the same time)."""
        shares = self._split_batch(requests)
        times = [bus.request_wire_s(share) for bus, share in zip(self.buses, shares, strict=True)]
        return None if any(t is None for t in times) else max(t for t in times if t is not None)

    def with_family(self, family: ProtocolFamily) -> Buses:
        """See :meth:`Transport.with_family`: every bus switches (each takes its link over)."""
        return self.with_families([family] * len(self.buses))

    def with_families(self, families: Sequence[ProtocolFamily]) -> Buses:
        """See :meth:`Transport.with_families`: each bus that speaks another generation switches (taking its link
        over); the others carry on."""
        if len(families) != len(self.buses):
            raise TransportError(f"{len(families)} protocol generations for {len(self.buses)} buses")
        if tuple(families) == self.families:
            return self
        self._stop_workers()
        switched = [bus if bus.family is f else bus.with_family(f) for bus, f in zip(self.buses, families, strict=True)]
        buses = Buses(switched, self.names, parallel=self.parallel)
        buses.frame_tap = self.frame_tap
        buses.identities.update(self.identities)
        self._closed = True  # (its buses are the new transport's now)
        return buses

    # --- the tap and the end -------------------------------------------------------------------------------

    @property
    def frame_tap(self) -> FrameTap | None:
        """Every bus's frames (see :data:`FrameTap`)."""
        return self._tap

    @frame_tap.setter
    def frame_tap(self, tap: FrameTap | None) -> None:
        self._tap = tap
        # (the buses' exchanges run in several threads: their frames reach the tap one at a time)
        # (a tap that tells the buses apart, a bus trace, gives one per bus: `on_bus(index)`)
        lock = getattr(self, "_tap_lock", None)
        per_bus = getattr(tap, "on_bus", None)
        for index, bus in enumerate(getattr(self, "buses", ())):
            bus.frame_tap = None if tap is None or lock is None else _locked(per_bus(index) if per_bus else tap, lock)

    def _prepare(self, requests: Sequence[Request]) -> None:
        raise NotImplementedError  # (transact is the buses')

    def _exchange(self, deadline_s: float) -> None:
        raise NotImplementedError  # (transact is the buses')

    def _stop_workers(self) -> None:
        for worker in self._workers:
            worker.stop()
        self._workers = []

    def _close(self) -> None:
        """Stop the workers, close every bus (each logs what it could not release)."""
        self._stop_workers()
        for bus in self.buses:
            bus.close()


def _locked(tap: FrameTap, lock: threading.Lock) -> FrameTap:
    """``tap`` taking one frame at a time (the buses' exchanges run in several threads)."""

    def locked(time_s: float, received: bool, arbitration_id: int | None, data: bytes) -> None:
        with lock:
            tap(time_s, received, arbitration_id, data)

    return locked


def several(buses: Sequence[Transport], names: Sequence[str]) -> Transport:
    """The transport of an arm on ``buses``: the one bus itself, else :class:`Buses` of them."""
    return buses[0] if len(buses) == 1 else Buses(buses, names)


__all__ = ["Buses", "several"]
