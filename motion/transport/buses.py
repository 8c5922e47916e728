"""An arm on several buses as one transport (issue 35).

Control and safety name each drive by its address, ``bus index × ADDRESS_STRIDE + motor id``
(:data:`motion.protocol.table.ADDRESS_STRIDE`; the first bus's addresses are the motor ids themselves), so the
controller, the watchdog and the supervisor stay keyed by one number per drive and never ask which bus a drive is on.
:class:`Buses` splits a cycle's batch by bus, runs the buses' exchanges at the same time (the first in the calling
thread, each other in a worker thread of its own: a backend waits on its port with the GIL released, so the buses'
waits overlap) and merges the replies back into the request order, each named by its address. A 0x280 multi-motor
frame goes to the bus of its request's address (motors 1..4 of that bus).

A fault on one bus is every bus's: a port lost on one raises :class:`~motion.errors.PortLost` from :meth:`transact`
after the other buses' batches went out (the halt that follows reaches their drives in the same cycle), and the
transport counts as closed from then on.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping, Sequence
from typing import Final

from motion.errors import PortLost, TransportError
from motion.protocol import MultiMotorTorque
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily, split_address
from motion.transport.base import BusCounters, FrameTap, MotorCounters, Reply, Request, Transport

#: How long :meth:`Buses.transact` waits for a worker beyond the deadline before it counts the bus as failed, s.
_WORKER_GRACE_S: Final = 1.0


class _Worker:
    """A thread that runs one bus's exchanges when handed them (one at a time)."""

    def __init__(self, bus: Transport, name: str) -> None:
        self.bus = bus
        self._requests: Sequence[Request] = ()
        self._deadline_s = 0.0
        self.replies: list[Reply] = []
        self.error: BaseException | None = None
        self.took_s = 0.0  # how long the last exchange took, s
        self.stuck = False  # an exchange did not end in time: the bus is taken for gone
        self._start = threading.Event()
        self._done = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=f"rmd-bus-{name}", daemon=True)
        self._thread.start()

    def submit(self, requests: Sequence[Request], deadline_s: float) -> None:
        """Start an exchange of ``requests`` (collect it with :meth:`result`)."""
        self._requests, self._deadline_s, self.error = requests, deadline_s, None
        self._done.clear()
        self._start.set()

    def result(self, timeout_s: float) -> list[Reply]:
        """The replies of the exchange submitted last.

        Raises:
            TransportError: the bus failed (the backend's own error).
            PortLost: the port is gone, or the exchange did not end in time (then :attr:`stuck` is set).
        """
        if not self._done.wait(timeout_s):
            # its thread is stuck in the backend: the bus is taken for gone (never handed a batch again)
            self.stuck = True
            raise PortLost(
                f"{self.bus.describe()}: its exchange did not end within {_WORKER_GRACE_S:g} s of its deadline"
            )
        if self.error is not None:
            raise self.error
        return self.replies

    def stop(self) -> None:
        self._stopping = True
        self._start.set()
        self._thread.join(_WORKER_GRACE_S)

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
        buses: the transports, in the order of the configuration's ``buses:`` (index = the address's bus index); all
            of one protocol generation and one clock.
        names: the buses' names, for messages.
        parallel: the buses' exchanges at the same time (a worker thread per bus beyond the first); False: one after
            the other in the calling thread (``bench/buses_bench.py`` measures the difference).

    Raises:
        TransportError: fewer than two buses, or buses of different generations.
    """

    def __init__(self, buses: Sequence[Transport], names: Sequence[str], *, parallel: bool = True) -> None:
        if len(buses) < 2 or len(names) != len(buses):
            raise TransportError(f"several buses take two or more transports, each named; got {len(buses)}")
        families = {bus.family for bus in buses}
        if len(families) > 1:
            told = ", ".join(f"{n}: {b.family.value}" for n, b in zip(names, buses, strict=True))
            raise TransportError(f"the buses of one arm speak one protocol generation; found {told}")
        self.buses = tuple(buses)
        self.names = tuple(names)
        super().__init__(clock=buses[0].clock, family=buses[0].family)
        self.parallel = parallel
        self._workers = (
            [_Worker(bus, name) for bus, name in zip(self.buses[1:], self.names[1:], strict=True)] if parallel else []
        )
        self._split: list[list[Request]] = [[] for _ in self.buses]
        self._where: list[int] = []  # per request of the cycle, its bus
        self._took_s = [0.0] * len(self.buses)  # how long each bus's share of the last exchange took, s

    # --- the cycle -----------------------------------------------------------------------------------------

    def transact(self, requests: Sequence[Request], deadline_s: float) -> list[Reply]:
        """See :meth:`Transport.transact`: each bus's share at the same time, the replies in request order with the
        drives' addresses.

        Raises:
            PortLost: a bus's port is gone (the other buses' batches went out first).
            TransportError: a bus failed, or the transport is closed.
        """
        if self._closed:
            raise TransportError(f"{self.describe()} is closed")
        split, where = self._split, self._where
        for share in split:
            share.clear()
        where.clear()
        for request in requests:
            bus, motor_id = split_address(request.motor_id)
            if not 0 <= bus < len(split):
                raise TransportError(f"request to address {request.motor_id}: no bus {bus} in {self.describe()}")
            split[bus].append(Request(motor_id, request.message) if bus else request)
            where.append(bus)
        self.bus_counters.cycles += 1
        # a bus whose port is gone is skipped: the others' batches (the halt that follows a fault) still go out
        stuck = [False, *(w.stuck for w in self._workers)]
        live = [bus.lost is None and not bus.closed and not s for bus, s in zip(self.buses, stuck, strict=False)]
        for worker, share, alive in zip(self._workers, split[1:], live[1:], strict=False):  # (none: sequential)
            if alive:
                worker.submit(share, deadline_s)
        errors: list[BaseException] = []
        answers: list[list[Reply]] = []
        inline = range(len(self.buses)) if not self.parallel else range(1)  # (the buses this thread exchanges on)
        took = self._took_s
        for k in inline:
            began = self.clock()
            try:
                answers.append(self.buses[k].transact(split[k], deadline_s) if live[k] else [])
            except BaseException as exc:  # the other buses still end their exchange first
                errors.append(exc)
                answers.append([])
            took[k] = self.clock() - began
        grace = max(0.0, deadline_s - self.clock()) + _WORKER_GRACE_S
        for k, (worker, alive) in enumerate(zip(self._workers, live[1:], strict=False), start=1):
            try:
                answers.append(worker.result(grace) if alive else [])
            except BaseException as exc:
                errors.append(exc)
                answers.append([])
            took[k] = worker.took_s
        gone = [bus.lost for bus in self.buses if bus.lost is not None]
        gone += [e for e in errors if isinstance(e, PortLost)]
        if gone and self._lost is None:
            self._lost = gone[0]
        if errors:
            raise next((e for e in errors if isinstance(e, PortLost)), errors[0])  # (each names its port)
        if not all(live):
            closed = ", ".join(name for name, alive in zip(self.names, live, strict=True) if not alive)
            raise self._lost or PortLost(f"bus(es) {closed} of {self.describe()} closed")
        return self._merge(requests, answers)

    def _merge(self, requests: Sequence[Request], answers: list[list[Reply]]) -> list[Reply]:
        """The buses' replies in request order (a 0x280 request's four in its place), named by address."""
        streams: list[Iterator[Reply]] = [iter(a) for a in answers]
        merged: list[Reply] = []
        for request, bus in zip(requests, self._where, strict=True):
            stream, base = streams[bus], bus * ADDRESS_STRIDE
            for _ in range(4 if isinstance(request.message, MultiMotorTorque) else 1):
                reply = next(stream)
                merged.append(reply._replace(motor_id=base + reply.motor_id) if base else reply)
        return merged

    # --- what the buses tell -------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """True once closed, or once any bus is closed or lost: the arm's drives are not all reachable any more
        (:meth:`transact` still carries the other buses' batches, then raises)."""
        return (
            self._closed
            or self._lost is not None
            or any(bus.closed for bus in self.buses)
            or any(w.stuck for w in self._workers)
        )

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
        shares: list[list[Request]] = [[] for _ in self.buses]
        for request in requests:
            bus, motor_id = split_address(request.motor_id)
            shares[bus].append(Request(motor_id, request.message))
        times = [bus.request_wire_s(share) for bus, share in zip(self.buses, shares, strict=True)]
        return None if any(t is None for t in times) else max(t for t in times if t is not None)

    def with_family(self, family: ProtocolFamily) -> Buses:
        """See :meth:`Transport.with_family`: every bus switches (each takes its link over)."""
        self._stop_workers()
        buses = Buses([bus.with_family(family) for bus in self.buses], self.names)
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
        for bus in getattr(self, "buses", ()):
            bus.frame_tap = tap

    @property
    def bus_counters_by_bus(self) -> dict[str, BusCounters]:
        """Each bus's own counters, by name."""
        return {name: bus.bus_counters for name, bus in zip(self.names, self.buses, strict=True)}

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


def several(buses: Sequence[Transport], names: Sequence[str]) -> Transport:
    """The transport of an arm on ``buses``: the one bus itself, else :class:`Buses` of them."""
    return buses[0] if len(buses) == 1 else Buses(buses, names)


__all__ = ["Buses", "several"]
