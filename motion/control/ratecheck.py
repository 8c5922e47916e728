"""The rate check at connect: measure what this host and this bus can hold before the loop starts, never assume it.

Two figures are measured, with requests that move nothing:

- **the bus round trip**: ``transact`` of a batch shaped like the cycle's (one read per joint, answered like a
  set-point, the family's fine-angle reads (V3), plus the cycle's 0x9A status read), repeated; from the first frame
  out to the last reply in, on the transport's clock (real time on hardware and real-time emulation, simulated time
  in a simulation); where the set-points take longer on the wire than the reads standing in for them (RS485: an 0xA4
  frame is 18 bytes, a read 5), the difference is added at the wire's speed (``Transport.request_wire_s``);
- **the host's own work per cycle** beyond the exchange (whose encoding and decoding the round trip already holds):
  a guarded cycle at rest rehearsed on each measuring exchange's replies, with nothing sent - the set-points (in
  torque mode with the feed-forward, i.e. Pinocchio), the replies absorbed, the tracking model, the watchdog with the
  collision observer (Pinocchio again) - timed with the process's performance counter. In a simulation the host's
  computation takes no simulated time, so it does not count there.

A rate holds when, with the margin, the round trip fits the share of the period given to ``transact``
(``reply_budget``) and round trip plus host work fit the period:

    round_trip × margin ≤ reply_budget / rate        (round_trip + host) × margin ≤ 1 / rate

The highest rate that holds is the smaller of the two bounds, rounded down to a whole 5 Hz (a whole 1 Hz below
:data:`FINE_BELOW_HZ`: a long RS485 line holds a few tens of Hz). The p99 of each figure is used, so a host that is
slow one cycle in a hundred is judged by that cycle.

A p99 of a few dozen exchanges on a shared host moves from one measurement to the next (two checks a minute apart on
one machine: 125 Hz, then 120 Hz; six in a row on a busy one: 120 to 480 Hz). So the check measures for at least
:data:`MEASURE_S` (and at least :data:`MIN_SAMPLES` exchanges), evaluates each quarter of the exchanges on its own as
well, and reports the spread of the highest rate between the quarters. The *recommended* rate, what the messages
tell a user to set, is :data:`RECOMMENDED_SHARE` of the lower end of that spread: a rate the next connect, measuring
anew, very likely accepts too.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from motion.control.clock import is_simulated
from motion.control.controller import Controller
from motion.errors import ConfigError, DrivesSilent
from motion.protocol import Command, WireProtocol
from motion.protocol.table import split_address
from motion.transport.base import Reply, Request

#: The fewest exchanges measured in real time (a few dozen: about 0.1 s of bus time for six joints at 1 Mbit/s) ...
MIN_SAMPLES: Final = 40
#: ... and the least time they take, s: more exchanges on a fast bus, for a p99 that is not one preemption's ...
MEASURE_S: Final = 0.25
#: ... and the most exchanges.
MAX_SAMPLES: Final = 400
#: The measurement's parts evaluated on their own for the spread (consecutive runs of exchanges).
SPREAD_PARTS: Final = 4
#: Exchanges measured in a simulation (each is the same).
SIMULATED_SAMPLES: Final = 3
#: The margin a rate must hold with unless the configuration accepts a smaller one (``control.rate_margin``).
DEFAULT_MARGIN: Final = 1.5
#: Rates are proposed in steps of this many Hz ...
RATE_STEP_HZ: Final = 5.0
#: ... and of 1 Hz below this rate.
FINE_BELOW_HZ: Final = 20.0
#: Share of the highest rate that holds which is recommended (room for the spread between measurements).
RECOMMENDED_SHARE: Final = 0.8
#: Rehearsals of the host's work per measuring exchange (real time): the p99 of a few dozen samples is nearly their
#: maximum, which one preemption of the process decides; five per exchange make it the p99 of a couple of hundred.
REHEARSALS_PER_EXCHANGE: Final = 5
#: The least time between two rehearsals, s (a clock may read the same twice).
_REHEARSAL_STEP_S: Final = 1e-6
#: Time each measuring exchange may take before its reads count as unanswered, s.
_EXCHANGE_TIMEOUT_S: Final = 0.1
#: The oldest a drive's flags (0x9A) and restart read (0x92, V3: 0xB1) may be where the bus has room for them, s.
FLAG_AGE_S: Final = 0.05


def status_reads_per_cycle(drives: int, period_s: float, protocol: WireProtocol) -> int:
    """How many of a bus's round-robin status reads (two per drive: 0x9A and the restart read) each cycle carries: on
    CAN, enough that every drive's are at most :data:`FLAG_AGE_S` old (each read is one more frame, and a slow loop's
    bus has room for them; at 250 Hz with six drives, one); on RS485 one (each read is an exchange of its own on the
    half-duplex line: the flags are ``2 × drives`` cycles old there)."""
    reads = 2 * drives
    if protocol is not WireProtocol.CAN:
        return 1
    cycles = max(1, math.floor(FLAG_AGE_S / period_s + 1e-9))  # the most cycles between two reads of one drive's
    return min(reads, math.ceil(reads / cycles))


class StatusRounds:
    """The round-robin status reads of an arm, each bus's in turn on its own: every cycle carries the next
    :func:`status_reads_per_cycle` of each bus's (each bus's by its own wire: an RS485 line one, a CAN bus enough
    for :data:`FLAG_AGE_S`), so that a cycle's reads spread over the buses by what each can carry.

    Args:
        reads: per drive (by address), its status reads in the order they go out.
        period_s: the control period, s.
        wires: each bus's wire protocol, by the bus index of the addresses.
    """

    def __init__(
        self, reads: Sequence[tuple[int, Sequence[Request]]], period_s: float, wires: Sequence[WireProtocol]
    ) -> None:
        per_bus: dict[int, list[Request]] = {}
        drives: dict[int, int] = {}
        for address, requests in reads:
            bus = split_address(address)[0]
            per_bus.setdefault(bus, []).extend(requests)
            drives[bus] = drives.get(bus, 0) + 1
        #: Per bus: its reads in turn, and how many of them each cycle carries.
        self.rounds = [
            (per_bus[bus], status_reads_per_cycle(drives[bus], period_s, wires[bus])) for bus in sorted(per_bus)
        ]
        self._last = [-1] * len(self.rounds)  # the index of each bus's read that went out last
        #: How many reads each cycle carries, over every bus.
        self.per_cycle = sum(count for _, count in self.rounds)

    @classmethod
    def of(cls, controller: Controller) -> StatusRounds:
        """The status reads of ``controller``'s drives: 0x9A (flags, voltage, temperature) and the family's restart
        read (0x92, whose multi-turn angle jumps when a drive restarted; V3: 0xB1, its runtime, which starts again)."""
        ask = controller.bare_request
        reads = [
            (i, [ask(i, Command.READ_STATUS_1), ask(i, family.restart_read)])
            for i, family in zip(controller.ids, controller.families, strict=True)
        ]
        return cls(reads, controller.period_s, controller.options.wires)

    def next(self) -> tuple[Request, ...]:
        """The next cycle's reads (each bus's next ones in turn)."""
        out: list[Request] = []
        last = self._last
        for k, (reads, count) in enumerate(self.rounds):
            size = len(reads)
            first = last[k] + 1
            out.extend(reads[(first + j) % size] for j in range(count))
            last[k] = (last[k] + count) % size
        return tuple(out)

    def cycles_until(self, request: Request) -> int:
        """In how many cycles ``request`` goes out (1: the next cycle's reads carry it).

        Raises:
            ValueError: not one of the reads.
        """
        for k, (reads, count) in enumerate(self.rounds):
            if request in reads:
                distance = (reads.index(request) - self._last[k] - 1) % len(reads) + 1
                return -(-distance // count)
        raise ValueError(f"{request} is not one of the status reads")


#: A drive that answers none of this many exchanges in a row does not answer (the check fails); fewer misses count as
#: round trips of :data:`_EXCHANGE_TIMEOUT_S`.
_SILENT_EXCHANGES: Final = 3


@dataclass(frozen=True, slots=True)
class RateCheck:
    """What was measured and what it allows.

    Attributes:
        rate_hz: the configured rate.
        reply_budget: share of the period given to ``transact``.
        margin: the margin the rate must hold with.
        round_trip_p99_s: p99 of the cycle-shaped exchange, s (transport clock).
        host_p99_s: p99 of the host's own work per cycle, s (0 in a simulation).
        samples: exchanges measured.
        simulated: measured in simulated time (the bus model only; the host's speed does not matter).
        spread_hz: the lowest and highest of the rates that hold by each of :data:`SPREAD_PARTS` runs of the
            exchanges on its own (not rounded); None where too few were measured (a simulation).
        stable_from_hz: a mode where the host closes the loop: the lowest rate at which every joint's PD keeps its
            stability margin (:mod:`motion.control.stability`); 0 where no such floor applies; ``inf`` where no
            rate up to 1 kHz holds the gains. No rate below it holds or is recommended.
    """

    rate_hz: float
    reply_budget: float
    margin: float
    round_trip_p99_s: float
    host_p99_s: float
    samples: int
    simulated: bool
    spread_hz: tuple[float, float] | None = None
    by_bus_p99_s: tuple[tuple[str, float], ...] = ()
    stable_from_hz: float = 0.0

    def bus_text(self) -> str:
        """An arm on several buses: each bus's own exchange (p99) and the one that limits ("" on one bus)."""
        if not self.by_bus_p99_s:
            return ""
        slowest = max(self.by_bus_p99_s, key=lambda item: item[1])[0]
        each = ", ".join(f"{name} {t * 1e3:.2f} ms" for name, t in self.by_bus_p99_s)
        return f"; by bus (p99, at the same time): {each}: bus {slowest} limits"

    @property
    def highest_rate_hz(self) -> float:
        """The highest rate that holds with the margin, rounded down to a step (:func:`rate_step`; 0 if none does)."""
        return round_rate(self._bound_hz(self.round_trip_p99_s, self.host_p99_s))

    def _bound_hz(self, round_trip_s: float, host_s: float) -> float:
        bounds = []
        if round_trip_s > 0:
            bounds.append(self.reply_budget / (round_trip_s * self.margin))
        if round_trip_s + host_s > 0:
            bounds.append(1.0 / ((round_trip_s + host_s) * self.margin))
        return min(bounds, default=math.inf)

    @property
    def recommended_rate_hz(self) -> float:
        """:data:`RECOMMENDED_SHARE` of the lower end of the spread (of :attr:`highest_rate_hz` where no spread was
        measured), rounded down to a step: a rate the next measurement will very likely accept too; never below
        :attr:`stable_from_hz` (0 where the host's highest rate is below it: no rate holds both)."""
        highest = self.highest_rate_hz
        if highest < self.stable_from_hz:
            return 0.0
        if not math.isfinite(highest):
            return highest
        low = highest if self.spread_hz is None else min(highest, self.spread_hz[0])
        # never 0 where a rate holds: at the lowest step, the highest itself
        recommended = max(min(highest, rate_step(highest)), round_rate(low * RECOMMENDED_SHARE))
        if recommended < self.stable_from_hz:  # (the floor's next step: at most the highest, a step at or above it)
            return min(highest, stable_floor_hz(self.stable_from_hz))
        return recommended

    def spread_text(self) -> str:
        """The spread for people ("" where none was measured)."""
        if self.spread_hz is None:
            return ""
        low, high = self.spread_hz
        return f"; {low:.0f} to {high:.0f} Hz by each quarter of the {self.samples} exchanges on its own"

    @property
    def holds(self) -> bool:
        """True when the configured rate holds with the margin."""
        period = 1.0 / self.rate_hz
        return (
            self.rate_hz >= self.stable_from_hz
            and self.round_trip_p99_s * self.margin <= self.reply_budget * period
            and (self.round_trip_p99_s + self.host_p99_s) * self.margin <= period
        )

    def summary(self) -> str:
        """One line for people."""
        clock = "simulated bus" if self.simulated else "this host and bus"
        return (
            f"{clock}: round trip p99 {self.round_trip_p99_s * 1e3:.2f} ms, host work p99 "
            f"{self.host_p99_s * 1e3:.2f} ms per cycle ({self.samples} exchanges); highest rate with margin "
            f"{self.margin:g}: {self.highest_rate_hz:g} Hz{self.spread_text()}{self.bus_text()} (recommended "
            f"{self.recommended_rate_hz:g} Hz){self.stability_text()}; configured "
            f"{self.rate_hz:g} Hz " + ("holds" if self.holds else "does NOT hold")
        )

    def stability_text(self) -> str:
        """The stability floor for people ("" where there is none)."""
        if self.stable_from_hz <= 0.0:
            return ""
        if math.isinf(self.stable_from_hz):
            return "; the torque loop's gains hold at no rate up to 1000 Hz"
        return f"; the torque loop's gains need at least {self.stable_from_hz:.1f} Hz"


    def floor_text(self) -> str:
        """", but not below N Hz ..." where a stability floor applies ("" where none does)."""
        if self.stable_from_hz <= 0.0 or math.isinf(self.stable_from_hz):
            return ""
        return f", but not below {self.stable_from_hz:.1f} Hz, where torque mode's PD loop loses its margin"


def stable_floor_hz(lowest_hz: float) -> float:
    """The lowest stable rate (:func:`motion.control.stability.lowest_rate_hz`, ``nan``: none) rounded up to a step
    (the rate to propose), ``inf`` for none."""
    if math.isnan(lowest_hz):
        return math.inf
    step = rate_step(lowest_hz)
    return math.ceil(lowest_hz / step - 1e-9) * step


def rate_step(rate_hz: float) -> float:
    """The step rates are proposed in around ``rate_hz``: :data:`RATE_STEP_HZ`, 1 Hz below :data:`FINE_BELOW_HZ`."""
    return RATE_STEP_HZ if rate_hz >= FINE_BELOW_HZ else 1.0


def round_rate(rate_hz: float) -> float:
    """``rate_hz`` rounded down to its step (:func:`rate_step`); infinity stays."""
    if not math.isfinite(rate_hz):
        return rate_hz
    step = rate_step(rate_hz)
    return math.floor(rate_hz / step) * step


class RateError(ConfigError):
    """The configured rate cannot be held on this host and bus (a configuration error: nothing moved)."""

    def __init__(self, source: str, check: RateCheck) -> None:
        self.check = check
        if check.highest_rate_hz < check.stable_from_hz:
            super().__init__(
                source,
                "control.rate_hz",
                f"{check.rate_hz:g} Hz cannot be held, and no rate this host and bus hold keeps torque mode's PD "
                f"loop stable: the round trip "
                f"({check.round_trip_p99_s * 1e3:.2f} ms p99) and this host's work ({check.host_p99_s * 1e3:.2f} ms) "
                f"hold up to {check.highest_rate_hz:g} Hz with a margin of {check.margin:g}"
                f"{check.stability_text()} (lower the joints' kp_nm_per_deg and kd_nm_per_dps or their bandwidth_hz "
                "until `rmd-motion check --offline` shows a lower rate, use position mode, or a faster bus or host)",
            )
            return
        if check.rate_hz < check.stable_from_hz:
            super().__init__(
                source,
                "control.rate_hz",
                f"{check.rate_hz:g} Hz is below the rate torque mode's PD loop needs{check.stability_text()} (the "
                f"bus and host hold up to {check.highest_rate_hz:g} Hz; set control.rate_hz between "
                f"{stable_floor_hz(check.stable_from_hz):g} and {check.recommended_rate_hz:g} Hz)",
            )
            return
        super().__init__(
            source,
            "control.rate_hz",
            f"{check.rate_hz:g} Hz cannot be held: the cycle's bus round trip takes {check.round_trip_p99_s * 1e3:.2f}"
            f" ms (p99) and this host's work {check.host_p99_s * 1e3:.2f} ms, against a period of "
            f"{1e3 / check.rate_hz:.2f} ms ({check.reply_budget:.0%} of it for the replies) with a margin of "
            f"{check.margin:g}; the highest rate that holds is {check.highest_rate_hz:g} Hz{check.spread_text()}"
            f"{check.bus_text()} (set control.rate_hz to {check.recommended_rate_hz:g} Hz or lower"
            f"{check.floor_text()}, which leaves room for the spread between measurements, or accept a smaller "
            "margin with control.rate_margin)",
        )


#: The host's work of one cycle at rest on a measuring exchange's replies at a time, s (nothing may be sent).
Rehearsal = Callable[[list[Reply], float], None]


def measure_rate(
    controller: Controller,
    *,
    margin: float = DEFAULT_MARGIN,
    samples: int | None = None,
    rehearse: Rehearsal | None = None,
    stable_from_hz: float = 0.0,
) -> RateCheck:
    """Measure the cycle's round trip and the host's work per cycle (after ``read_positions``, before the loop
    starts).

    Only reads are sent: nothing moves. In real time: at least :data:`MIN_SAMPLES` exchanges and :data:`MEASURE_S`,
    at most :data:`MAX_SAMPLES` exchanges. In a simulation the exchange is the same every time, so a few samples do
    (:data:`SIMULATED_SAMPLES`), which keeps the emulated arm's unattended time before the loop short.

    Args:
        controller: the controller (its bus, options and request builders).
        margin: the margin the rate must hold with.
        samples: exchanges to measure (default: as above).
        rehearse: the host's work of a cycle at rest (default the controller's alone,
            :meth:`~motion.control.controller.Controller.rehearse`; the safety layer adds its watchdog's).
        stable_from_hz: the lowest rate the control loop is stable at (:attr:`RateCheck.stable_from_hz`).

    Raises:
        TransportError: a drive did not answer the measuring reads.
        ValueError: fewer than 2 samples, or a margin below 1.
        MotionError: ``read_positions`` has not run.
    """
    simulated = is_simulated(controller.clock)
    if samples is not None and samples < 2:
        raise ValueError(f"samples: {samples} must be >= 2")
    fewest = samples or (SIMULATED_SAMPLES if simulated else MIN_SAMPLES)
    most = samples or (SIMULATED_SAMPLES if simulated else MAX_SAMPLES)
    if not (math.isfinite(margin) and margin >= 1.0):
        raise ValueError(f"margin: {margin!r} must be >= 1")
    ids = controller.ids
    # A cycle's frames: one motion read per joint as the set-points, the family's angle reads, its status reads.
    batch = [controller.bare_request(i, Command.READ_STATUS_2) for i in ids] + controller.angle_reads
    batch += StatusRounds.of(controller).next()
    clock, bus = controller.clock, controller.bus
    # What a cycle's set-points take on the wire beyond the reads that stand in for them (measured: the reads; the
    # difference: the wire's speed), for transports that know it.
    setpoints = controller.build_requests(controller.reference)
    stand_ins = batch[: len(ids)]
    longer, shorter = bus.request_wire_s(setpoints), bus.request_wire_s(stand_ins)
    extra_s = max(0.0, longer - shorter) if longer is not None and shorter is not None else 0.0
    round_trips = np.empty(most)
    rehearsals = 1 if simulated else REHEARSALS_PER_EXCHANGE
    host = np.zeros(most * rehearsals)
    if rehearse is None:
        rehearse = controller.rehearse
    at = -math.inf
    began, n = time.monotonic(), 0
    misses = dict.fromkeys(ids, 0)
    by_bus: dict[str, list[float]] = {}
    while n < fewest or (n < most and time.monotonic() - began < MEASURE_S):
        start = clock.now()
        replies = bus.transact(batch, start + _EXCHANGE_TIMEOUT_S)
        for name, took_s in (bus.bus_times_s() or {}).items():
            by_bus.setdefault(name, []).append(took_s)
        missing = {r.motor_id for r in replies if r.message is None}
        # a reply missing once is a round trip of at least the timeout (a stalled host, a lost frame: the p99 says
        # so); a drive that answers none of several exchanges in a row does not answer
        round_trips[n] = max(clock.now() - start, _EXCHANGE_TIMEOUT_S if missing else 0.0) + extra_s
        for motor_id in ids:
            misses[motor_id] = misses[motor_id] + 1 if motor_id in missing else 0
        silent = sorted(i for i, count in misses.items() if count >= _SILENT_EXCHANGES)
        if silent:
            labels = {spec.motor_id: spec.drive_label for spec in controller.specs}
            named = tuple(labels.get(i, f"motor {i}") for i in silent)
            raise DrivesSilent(f"no reply to the rate check's reads from {', '.join(named)}", tuple(silent), named)
        for m in range(rehearsals):
            # strictly later than the last (the models step by the time between two cycles and divide by it)
            at = max(clock.now(), at + _REHEARSAL_STEP_S)
            t0 = time.perf_counter()
            rehearse(replies, at)
            if not simulated:
                host[n * rehearsals + m] = time.perf_counter() - t0
        n += 1
    round_trips, host = round_trips[:n], host[: n * rehearsals]
    check = RateCheck(
        rate_hz=controller.options.rate_hz,
        reply_budget=controller.options.reply_budget,
        margin=margin,
        round_trip_p99_s=float(np.percentile(round_trips, 99)),
        host_p99_s=float(np.percentile(host, 99)),
        samples=n,
        simulated=simulated,
        by_bus_p99_s=tuple((name, float(np.percentile(times, 99))) for name, times in by_bus.items()),
        stable_from_hz=stable_from_hz,
    )
    if simulated or n < 2 * SPREAD_PARTS:
        return check
    parts = [
        check._bound_hz(float(np.percentile(trips, 99)), float(np.percentile(work, 99)))
        for trips, work in zip(
            np.array_split(round_trips, SPREAD_PARTS), np.array_split(host, SPREAD_PARTS), strict=True
        )
    ]
    return dataclasses.replace(check, spread_hz=(min(parts), max(parts)))
