"""The fault-schedule explorer (issue 29): random fault schedules and user actions on the example arms, in simulated
time, with the safety invariants checked in every control cycle.

A :class:`Schedule` is a configuration, a halt policy and control mode, the emulator's faults (any kind, at any
instant: during connect, a move, a hold, a halt, a clear) and user actions (move, stop, hold, clear) at given times,
and optionally a joint homed at connect. :func:`run` plays it and returns the violations of:

- **still**: once the arm has been faulted (halting, halted or holding) for :data:`SETTLE_S`, no joint moves more
  than :data:`BAND_DEG` from where it stood then, and no joint that was inside its limits when the fault came leaves
  them by more than :data:`BAND_DEG` (not counted: a joint whose drive could not be reached or may have switched itself
  off — silent, dropped, power-cycled, over-temperature, under-voltage — nor one pushed by an injected collision, nor
  an unbraked joint under ``halt_policy: off``, which falls: all documented);
- **halted**: while the arm is halting or halted, every drive that answered in two cycles in a row is halted (0x81 or
  0x80 in force: the emulator's drive state) at the second;
- **link**: no V3 drive without a link fault trips its communication-loss protection while the session is open;
- **brake**: no brake locks (by the controller's 0x78) on a joint turning faster than :data:`BRAKE_MOVING_DPS`;
- **escape**: nothing but a :class:`~motion.errors.MotionError` comes out of the API, the loop records no error of
  its own, and the run ends within :data:`WALL_LIMIT_S` of wall time.

Seeded and reproducible (:func:`draw`); :func:`shrink` removes faults and actions from a failing schedule while it
still fails the same way, and :meth:`Schedule.describe` prints it as the literal to keep as a regression test.
"""

from __future__ import annotations

import dataclasses
import math
import random
import signal
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from motion import Arm
from motion.config import ArmConfig, load_config
from motion.config.schema import ControlMode, HaltPolicy
from motion.emulator import Fault, InjectedFault, parse_fault
from motion.emulator.drive import RunState
from motion.errors import MotionError
from motion.protocol.v3.messages import BrakeCommand
from motion.safety import ArmState

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: The example arms explored, and the control rate of their position-mode runs (torque mode keeps the example's rate,
#: to which its gains are tuned).
ARMS: dict[str, float] = {
    "arm2.yaml": 100.0,
    "arm2_rs485.yaml": 50.0,
    "arm6.yaml": 100.0,
    "arm6_v3.yaml": 100.0,
    "bench1.yaml": 100.0,
}
POLICIES = (HaltPolicy.STOP, HaltPolicy.OFF, HaltPolicy.HOLD)
#: How long the arm is faulted before its joints must stand still, s (the drives' own stop, a stop ramp).
SETTLE_S = 1.0
#: How far a joint may move once settled, or past a limit, deg.
BAND_DEG = 2.0
#: A joint turning faster than this when its brake locks fails the brake invariant, joint deg/s (the controller locks
#: at 1 deg/s read; the plant's speed is sampled once per cycle).
BRAKE_MOVING_DPS = 3.0
#: A schedule's run ends within this much wall time, s.
WALL_LIMIT_S = 120.0
#: Kinds after which a drive may have been unreachable or off by its own doing (its joint is not held to the still
#: and limit invariants from then on).
_OUT_OF_REACH = (
    InjectedFault.SILENT,
    InjectedFault.DROP,
    InjectedFault.POWER_CYCLE,
    InjectedFault.OVER_TEMPERATURE,
    InjectedFault.UNDER_VOLTAGE,
)
_LINK = (InjectedFault.SILENT, InjectedFault.DROP)


@dataclass(frozen=True)
class Schedule:
    """One explored run (see the module docstring); times are simulated seconds since connect."""

    arm: str
    policy: HaltPolicy
    mode: ControlMode
    faults: tuple[str, ...]  #: in the emulator's syntax (``KIND:MOTOR@START[-END][:PARAM]``)
    actions: tuple[tuple[float, str, tuple[float, ...]], ...]  #: (time, move|stop|hold|clear, move target)
    home: tuple[str, ...] = ()
    end_s: float = 2.0

    def describe(self) -> str:
        """The schedule as a Python literal (a regression test's data)."""
        return (
            f"Schedule({self.arm!r}, HaltPolicy.{self.policy.name}, ControlMode.{self.mode.name}, "
            f"faults={self.faults!r}, actions={self.actions!r}, home={self.home!r}, end_s={self.end_s!r})"
        )


@dataclass
class Outcome:
    """What a run found."""

    schedule: Schedule
    violations: list[str] = field(default_factory=list)
    cycles: int = 0

    @property
    def kinds(self) -> set[str]:
        """The invariants violated (the word before the colon of each violation)."""
        return {v.split(":", 1)[0] for v in self.violations}


def config_of(schedule: Schedule) -> ArmConfig:
    """The schedule's arm configuration: the example with its policy, mode and rate."""
    config = load_config(CONFIGS / schedule.arm)
    rate = ARMS[schedule.arm] if schedule.mode is ControlMode.POSITION else config.control.rate_hz
    control = dataclasses.replace(config.control, halt_policy=schedule.policy, mode=schedule.mode, rate_hz=rate)
    if schedule.arm == "arm6_v3.yaml" and config.safety.link_timeout_ms is not None:
        # five periods of the explored rate (the example's 40 ms is five of its 125 Hz)
        config = dataclasses.replace(config, safety=dataclasses.replace(config.safety, link_timeout_ms=None))
    return dataclasses.replace(config, control=control)


def draw(rng: random.Random) -> Schedule:
    """A random schedule."""
    arm = rng.choice(sorted(ARMS))
    config = load_config(CONFIGS / arm)
    ids = [j.motor_id for j in config.joints]
    tuned = all(j.kp_nm_per_deg > 0 for j in config.joints)  # torque mode needs the joints' gains
    mode = ControlMode.TORQUE if tuned and rng.random() < 0.25 else ControlMode.POSITION
    faults = tuple(_draw_fault(rng, rng.choice(ids)) for _ in range(rng.choice((1, 1, 2, 2, 3))))
    actions: list[tuple[float, str, tuple[float, ...]]] = [(0.0, "move", _target(rng, config))]
    for _ in range(rng.randint(0, 4)):
        t = round(rng.uniform(0.05, 1.8), 3)
        what = rng.choice(("move", "move", "stop", "hold", "clear", "clear"))
        actions.append((t, what, _target(rng, config) if what == "move" else ()))
    homeable = [j.name for j in config.joints if j.homing is not None]
    home = (rng.choice(homeable),) if homeable and rng.random() < 0.05 else ()
    return Schedule(arm, rng.choice(POLICIES), mode, faults, tuple(sorted(actions)), home)


def _draw_fault(rng: random.Random, motor_id: int) -> str:
    kind = rng.choice(list(InjectedFault))
    start = round(rng.choice((rng.uniform(0.0, 0.05), rng.uniform(0.0, 1.6), rng.uniform(0.0, 1.6))), 3)
    end = "" if kind is InjectedFault.POWER_CYCLE or rng.random() < 0.3 else f"-{start + rng.uniform(0.02, 0.6):.3f}"
    param = {
        InjectedFault.DELAY: f":{rng.uniform(1.0, 25.0):.1f}",
        InjectedFault.DROP: f":{rng.choice((1.0, rng.uniform(0.2, 1.0))):.2f}",
        InjectedFault.CORRUPT: ":" + rng.choice(("payload", "id", "length")),
        InjectedFault.COLLISION: f":{rng.choice((-1, 1)) * rng.uniform(0.5, 8.0):.2f}",
    }.get(kind, "")
    return f"{kind.value}:{motor_id}@{start}{end}{param}"


def _target(rng: random.Random, config: ArmConfig) -> tuple[float, ...]:
    """A random pose well inside the limits (a fifth of the range off each end)."""
    out = []
    for j in config.joints:
        span = j.position_max_deg - j.position_min_deg
        out.append(round(rng.uniform(j.position_min_deg + 0.2 * span, j.position_max_deg - 0.2 * span), 1))
    return tuple(out)


class _Checker:
    """The invariants, evaluated in a cycle hook of the arm's controller (never raises: violations are collected)."""

    def __init__(self, arm: Arm, schedule: Schedule, faults: list[Fault], outcome: Outcome) -> None:
        self.arm = arm
        self.outcome = outcome
        config = arm.config
        self.ids = [j.motor_id for j in config.joints]
        self.names = config.joint_names
        self.lower = np.array([j.position_min_deg for j in config.joints])
        self.upper = np.array([j.position_max_deg for j in config.joints])
        self.braked = [j.brake for j in config.joints]
        self.faults = faults
        self.policy = schedule.policy
        assert arm.simulation is not None
        self.drives = arm.simulation.emulator.drives
        self.v3 = hasattr(self.drives[self.ids[0]], "link_losses")
        n = len(self.ids)
        self.faulted_since = math.nan
        self.anchor = np.full(n, np.nan)
        self.inside_at_fault = np.ones(n, dtype=bool)
        self.previous_state: ArmState | None = None
        self.previous_answered: set[int] = set()
        self.brakes = [self._brake(i) for i in self.ids]
        self.losses = [self._losses(i) for i in self.ids]
        self.reported: set[str] = set()

    def _brake(self, motor_id: int) -> Any:
        return getattr(self.drives[motor_id], "brake", None)

    def _losses(self, motor_id: int) -> int:
        return int(getattr(self.drives[motor_id], "link_losses", 0))

    def _violate(self, key: str, text: str) -> None:
        if key not in self.reported:  # one report per invariant and joint
            self.reported.add(key)
            self.outcome.violations.append(text)

    def _since(self, motor_id: int, kinds: tuple[InjectedFault, ...], t: float) -> bool:
        """Whether a fault of ``kinds`` on the drive has begun by ``t``."""
        return any(f.motor_id == motor_id and f.kind in kinds and f.start_s <= t for f in self.faults)

    def _pushed(self, motor_id: int, t: float) -> bool:
        """An injected collision acts on the joint, or did within the settling time."""
        return any(
            f.motor_id == motor_id
            and f.kind is InjectedFault.COLLISION
            and f.start_s <= t
            and (f.end_s is None or t < f.end_s + SETTLE_S)
            for f in self.faults
        )

    def __call__(self, controller: Any, start_s: float, replies: list[Any]) -> None:
        try:
            self._check(start_s, replies)
        except Exception:  # a bug of the checker must not become a fault of the arm
            self.outcome.violations.append("checker: " + traceback.format_exc(limit=3))

    def _check(self, start_s: float, replies: list[Any]) -> None:
        self.outcome.cycles += 1
        t = self.arm.controller.clock.now()  # type: ignore[union-attr]  # the cycle's end: what happened in it is seen
        supervisor = self.arm.supervisor
        plant = self.arm.plant
        if supervisor is None or plant is None:
            return
        state = supervisor.state
        q_rad, qd_rad = plant.state()
        q, qd = np.degrees(q_rad), np.degrees(qd_rad)
        halted = state in (ArmState.HALTING, ArmState.HALTED)
        still_states = halted or state is ArmState.HOLDING
        answered = {r.motor_id for r in replies if r.message is not None}
        codes = supervisor.guard.codes
        for i, motor_id in enumerate(self.ids):
            name = self.names[i]
            out_of_reach = self._since(motor_id, _OUT_OF_REACH, t)
            off = halted and codes[motor_id].name == "MOTOR_OFF"  # the policy's, or a hold that oscillated
            exempt = out_of_reach or self._pushed(motor_id, t) or (off and not self.braked[i])
            # link: a V3 drive without a link fault never trips its communication-loss protection
            losses = self._losses(motor_id)
            if self.v3 and losses > self.losses[i] and not self._since(motor_id, _LINK, t):
                self._violate(f"link{motor_id}", f"link: {name}'s drive tripped its link-loss protection at {t:.3f} s")
            # brake: locked by the controller only at rest
            brake = self._brake(motor_id)
            if (
                brake is BrakeCommand.LOCK
                and self.brakes[i] is BrakeCommand.RELEASE
                and losses == self.losses[i]
                and not self._since(motor_id, (InjectedFault.POWER_CYCLE,), t)
                and abs(qd[i]) > BRAKE_MOVING_DPS
            ):
                self._violate(f"brake{motor_id}", f"brake: {name}'s brake locked at {qd[i]:.1f} deg/s at {t:.3f} s")
            self.brakes[i], self.losses[i] = brake, losses
            # halted: a drive that answers twice while the arm is halted is halted at the second
            if (
                halted
                and self.previous_state in (ArmState.HALTING, ArmState.HALTED)
                and motor_id in answered
                and motor_id in self.previous_answered
                and self.drives[motor_id].state is RunState.RUNNING
            ):
                self._violate(f"halted{motor_id}", f"halted: {name}'s drive answers and still runs at {t:.3f} s")
            # still and limits
            if not still_states or exempt:
                self.anchor[i] = np.nan
                continue
            if math.isnan(self.faulted_since) or t - self.faulted_since < SETTLE_S:
                continue
            if math.isnan(self.anchor[i]):
                self.anchor[i] = q[i]
            elif abs(q[i] - self.anchor[i]) > BAND_DEG:
                self._violate(
                    f"still{motor_id}",
                    f"still: {name} moved {q[i] - self.anchor[i]:+.2f} deg while {state.value} at {t:.3f} s",
                )
            if self.inside_at_fault[i] and not self.lower[i] - BAND_DEG <= q[i] <= self.upper[i] + BAND_DEG:
                self._violate(f"limit{motor_id}", f"limit: {name} at {q[i]:.2f} deg while {state.value} at {t:.3f} s")
        if still_states:
            if math.isnan(self.faulted_since):
                self.faulted_since = t
                self.inside_at_fault = (q >= self.lower) & (q <= self.upper)
        else:
            self.faulted_since = math.nan
            self.anchor[:] = np.nan
        self.previous_state = state
        self.previous_answered = answered


class _WallTimeout(Exception):
    """The run took longer than :data:`WALL_LIMIT_S` (a hang)."""


@contextmanager
def _wall_limit(seconds: float) -> Iterator[None]:
    def expire(_signum: int, _frame: object) -> None:
        raise _WallTimeout(f"the run did not end within {seconds:g} s of wall time")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def run(schedule: Schedule) -> Outcome:
    """Play ``schedule`` and check every invariant in every cycle."""
    outcome = Outcome(schedule)
    faults = [parse_fault(spec) for spec in schedule.faults]
    config = config_of(schedule)
    arm = Arm(config, emulate=True, faults=faults, home=schedule.home)
    with _wall_limit(WALL_LIMIT_S):
        try:
            _play(arm, schedule, faults, outcome)
        except _WallTimeout as exc:
            outcome.violations.append(f"escape: {exc}")
    return outcome


def _play(arm: Arm, schedule: Schedule, faults: list[Fault], outcome: Outcome) -> None:
    def guarded(what: str, call: Callable[[], object]) -> None:
        try:
            call()
        except MotionError:
            pass
        except _WallTimeout:
            raise
        except BaseException as exc:  # anything else escaping the API is a violation
            outcome.violations.append(f"escape: {what}: {type(exc).__name__}: {exc}")

    connected = False

    def connect() -> None:
        nonlocal connected
        arm.connect()
        connected = True

    guarded("connect", connect)
    if not connected:
        return
    try:
        assert arm.controller is not None
        arm.controller.cycle_hooks.append(_Checker(arm, schedule, faults, outcome))
        clock = arm.controller.clock

        def until(t_s: float) -> Callable[[], None]:
            return lambda: arm.sleep(max(0.0, t_s - clock.now()))

        def move(target: tuple[float, ...]) -> Callable[[], object]:
            return lambda: arm.move_to(dict(zip(arm.names, target, strict=True)), speed_scale=0.8, wait=False)

        for at, what, target in schedule.actions:
            guarded("sleep", until(at))
            action = {"move": move(target), "stop": arm.stop, "hold": arm.hold}.get(what, arm.clear)
            guarded(what, action)
        guarded("sleep", until(schedule.end_s))
    finally:
        guarded("close", arm.close)
    controller = arm.controller
    if controller is not None and controller.error is not None:
        outcome.violations.append(f"escape: the loop ended on {controller.error!r}")


def shrink(schedule: Schedule, fails: Callable[[Schedule], bool]) -> Schedule:
    """The smallest schedule found by removing faults, actions and homing one at a time while ``fails`` holds."""
    current = schedule
    changed = True
    while changed:
        changed = False
        candidates: list[Schedule] = []
        for k in range(len(current.faults)):
            candidates.append(dataclasses.replace(current, faults=current.faults[:k] + current.faults[k + 1 :]))
        for k in range(1, len(current.actions)):
            candidates.append(dataclasses.replace(current, actions=current.actions[:k] + current.actions[k + 1 :]))
        if current.home:
            candidates.append(dataclasses.replace(current, home=()))
        for candidate in candidates:
            if fails(candidate):
                current, changed = candidate, True
                break
    return current


def fails_like(kinds: set[str]) -> Callable[[Schedule], bool]:
    """Whether a schedule still violates one of ``kinds``."""
    return lambda schedule: bool(run(schedule).kinds & kinds)


def explore(seed: int, count: int, progress: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    """Run ``count`` schedules drawn from ``seed``; returns the outcomes with violations (each shrunk)."""
    rng = random.Random(seed)
    failed = []
    for _ in range(count):
        outcome = run(draw(rng))
        if progress is not None:
            progress(outcome)
        if outcome.violations:
            smallest = shrink(outcome.schedule, fails_like(outcome.kinds))
            failed.append(run(smallest) if smallest != outcome.schedule else outcome)
    return failed
