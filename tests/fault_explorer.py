"""The fault-schedule explorer (issue 29): random fault schedules and user actions on the example arms, in simulated
time, with the safety invariants checked in every control cycle.

A :class:`Schedule` is a configuration, a halt policy and control mode, the emulated drives (most often drawn by
:mod:`tests.drive_models`: loop tuning, torque constant, inertia, friction and reply latency that differ from the
configured model, so that the halted state's constants are tested on drives we did not tune for), the emulator's
faults (any kind, at any instant: during connect, a move, a hold, a halt, a clear) and user actions (move, stop,
hold, clear) at given times, and optionally a joint homed at connect. :func:`run` plays it and returns the
violations of:

- **still**: once the arm has been faulted (halting, halted or holding) for :data:`SETTLE_S`, every joint its halt
  holds comes to rest (slower than :data:`ANCHOR_DPS` within :data:`RESTLESS_S`) and then moves no more than
  :data:`BAND_DEG` from there, nor leaves its limits by more than that if it came to rest inside them. Not held: a
  joint whose drive could not be reached, seen, or may have switched itself off (silent, dropped, corrupt,
  power-cycled, over-temperature, under-voltage), an unbraked joint under 0x80 (it falls or coasts: documented), and
  every joint while an injected collision pushes the arm or a joint nothing holds swings it (then for
  :data:`SETTLE_S`), and for :data:`UNHELD_GRACE_S` a joint its drive's own hold swings (released with 0x80 by then
  where gravity allows; a release the plant did not show the need for is a violation);
- **halted**: while the arm is halting or halted, every drive that answered in two cycles in a row is halted (0x81 or
  0x80 in force: the emulator's drive state) at the second (not a drive that loses requests at random: its answer to
  a read says nothing of the halt it lost, which goes out again every cycle until it is acknowledged);
- **link**: no V3 drive without a link fault trips its communication-loss protection while the session is open;
- **brake**: no brake locks (by the controller's 0x78) on a joint turning faster than :data:`BRAKE_MOVING_DPS`, but
  for one the controller brakes at once (its drive cannot hold it, or ``halt_policy: off``:
  ``HaltGuard.braked_at_once``);
- **unbraked**: a braked joint whose drive has cut its own output (over-temperature, under-voltage) gets its brake
  within the age of its flags and two cycles (while its drive can be reached);
- **unheld**: no braked joint the controller brakes at once keeps moving (faster than :data:`BRAKE_MOVING_DPS`) a
  cycle after its brake command (``HaltGuard.lock_sent_s``) went out (while its drive can be reached);
- **overspeed**: no joint reads faster than its overspeed limit (the watchdog's ``overspeed_limit_dps``: its velocity
  limit × its margin) in a cycle the watchdog checks it (ready, moving, holding) without the arm halting in that
  cycle (seen by the next cycle's look: the hooks run before the cycle's evaluation);
- **angle**: in every cycle, the controller's angle of each joint whose drive's sample reached it equals the plant's
  when the drive sampled it, within the encoder's resolution (a count of the encoder at each end, or 0.01 deg of a V3
  drive's reading) of the offset its anchoring at connect left (the joint's motion between the two reads that anchor
  it), unless the arm is faulted saying why (its drive restarted: its frame is lost); after a silence too (no turn the
  encoder missed is kept). Not held: a joint whose turns the controller knows are unconfirmed while its link is
  faulted and :data:`UNSURE_CYCLES` cycles after (its 0x92 read lost), one whose motor turned faster than its speed
  field tells until its turns are confirmed, and one whose restart a silence or such a spin hid (docs/protocol.md:
  an older drive's only sign is its first-turn reading);
- **escape**: nothing but a :class:`~motion.errors.MotionError` comes out of the API, the loop records no error of
  its own, and the run ends within :data:`WALL_LIMIT_S` of wall time.

Seeded and reproducible (:func:`draw`); :func:`shrink` removes faults and actions from a failing schedule while it
still fails the same way, and :meth:`Schedule.describe` prints it as the literal to keep as a regression test.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import multiprocessing
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
from motion.config.schema import ControlMode, HaltPolicy, ProtocolSetting
from motion.emulator import Fault, InjectedFault, parse_fault
from motion.emulator.drive import RunState
from motion.emulator.timing import TimingModel
from motion.errors import FaultKind, MotionError
from motion.protocol import Command, MotorState, MultiTurnAngle, WireProtocol
from motion.protocol.table import Direction, field_range
from motion.protocol.v3.messages import CommandV3, Runtime
from motion.safety import ArmState
from motion.safety.halted import RESTLESS_S as RESTLESS_RELEASE_S
from motion.safety.halted import SWING_DPS
from motion.safety.states import HALT_STATES
from tests.drive_models import DriveDraw, draw_drives, with_drives

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: bimanual.yaml with its left bus's drives of the older generation and its right bus's of driver V3
#: (``buses.left.protocol: v2``, ``buses.right.protocol: v3``), explored in position mode
#: (the example's torque gains are tuned for 250 Hz, more than V3's frames on the right bus hold).
MIXED = "bimanual.yaml+v3"
#: The example arms explored, and the control rate of their position-mode runs (torque mode keeps the example's rate,
#: to which its gains are tuned).
ARMS: dict[str, float] = {
    "arm2.yaml": 100.0,
    "arm2_rs485.yaml": 50.0,
    "arm6.yaml": 100.0,
    "arm6_v3.yaml": 100.0,
    "bench1.yaml": 100.0,
    "bimanual.yaml": 100.0,  # (two buses: a fault on either halts both)
    MIXED: 100.0,  # (the right arm's drives of driver V3, the left's of the older generation)
}
POLICIES = (HaltPolicy.STOP, HaltPolicy.OFF, HaltPolicy.HOLD)
#: How long the arm is faulted (or a joint undisturbed) before its joints are held to the invariants, s: the drives'
#: own stop from full speed or a stop ramp takes a few tenths of a second.
SETTLE_S = 0.6
#: How far a joint may move once settled, or past a limit, deg.
BAND_DEG = 2.0
#: A joint turning faster than this when its brake locks fails the brake invariant, joint deg/s (the controller locks
#: at 1 deg/s read; the plant's speed is sampled once per cycle).
BRAKE_MOVING_DPS = 3.0
#: A joint slower than this has come to rest where its halt left it (its anchor), deg/s.
ANCHOR_DPS = 5.0
#: A held joint that has not come to rest this long after it settled fails the still invariant, s.
RESTLESS_S = 0.5
#: A joint nothing holds (released under 0x80) swinging faster than this disturbs the others, deg/s.
DISTURBING_DPS = 5.0
#: A joint its drive's own hold swings (the plant shows two swings since it last stood) is not held to the still band
#: for this long, s: the controller sees six swings or a second of running on and releases it where gravity allows
#: (:mod:`motion.safety.halted`); after that, it is held to the band again.
UNHELD_GRACE_S = 2.0
#: A schedule's run ends within this much wall time, s: a hang, not a slow host (a schedule that homes a joint runs
#: tens of simulated seconds of seeking: 87 s of wall time seen on one CPU shared with three busy loops).
WALL_LIMIT_S = 900.0
#: Kinds after which a drive may have switched itself off (its joint is not held to the still and limit invariants
#: from then on: nothing but a clear, which these faults refuse, turns it on again).
_SWITCHED_OFF = (InjectedFault.POWER_CYCLE, InjectedFault.OVER_TEMPERATURE, InjectedFault.UNDER_VOLTAGE)
#: Kinds that keep the controller from reaching or seeing a drive (its joint is not held to the still and limit
#: invariants while they act and for :data:`SETTLE_S` after).
_UNREACHABLE = (InjectedFault.SILENT, InjectedFault.DROP, InjectedFault.CORRUPT)
#: Swings (one way, then the other, faster than 10 deg/s) the plant shows of a joint the controller released with
#: 0x80 because its drive's hold swung it: below this, the release is a violation.
SWINGS_SEEN = 4
_LINK = (InjectedFault.SILENT, InjectedFault.DROP)
#: The states whose cycles the watchdog checks the speeds in (not COMPLYING: the arm yields to a collision).
_EVALUATED = (ArmState.READY, ArmState.MOVING, ArmState.HOLDING)
#: Kinds that move or pin joints from outside (a push, an obstruction): the arm is not held to the still invariant
#: while they act and for :data:`SETTLE_S` after (a drive's hold pulls a joint an obstruction pinned off its hold
#: position back once the obstruction is gone: its hold working, not the arm moving by itself).
_EXTERNAL = (InjectedFault.COLLISION, InjectedFault.BLOCKED)
#: A joint faster than this has left the emulated plant's model, deg/s (100 turns a second: no RMD joint turns so
#: fast; the plant models no end stops, and a joint pushed with nothing resisting it spins up without bound, to
#: infinite and NaN states): what follows is not checked (:attr:`Outcome.left_model_s`).
PLANT_MODEL_DPS = 36000.0
#: The older drives' speed field's largest value, motor deg/s: a motor beyond it is beyond what its drive reports (and
#: than any RMD motor turns); its encoder is followed by the speed it reports, so not held to the angle invariant until
#: its turns are confirmed again.
SPEED_FIELD_MAX_DPS = field_range(Command.READ_STATUS_2, Direction.REPLY, WireProtocol.CAN, "speed_dps")[1]
#: Cycles in a row a joint's turns may stay unconfirmed (its 0x92 read missed) outside a link fault before its angle is
#: held to the plant's again.
UNSURE_CYCLES = 3
#: The shortest link timeout a V3 arm takes, ms (the default at 250 Hz and above): a quarter of the arm6_v3
#: schedules have it.
LINK_TIMEOUT_MIN_MS = 20.0
#: The share of schedules whose drives are drawn (:mod:`tests.drive_models`) rather than as configured.
DRAWN_DRIVES = 0.75


@dataclass(frozen=True)
class Schedule:
    """One explored run (see the module docstring); times are simulated seconds since connect."""

    arm: str
    policy: HaltPolicy
    mode: ControlMode
    faults: tuple[str, ...]  #: in the emulator's syntax (``KIND:MOTOR@START[-END][:PARAM]``)
    actions: tuple[tuple[float, str, tuple[float, ...]], ...]  #: (time, move|stop|hold|clear, move target)
    home: tuple[str, ...] = ()
    end_s: float = 2.2
    #: The emulated drives (:mod:`tests.drive_models`); None: as the example configures them.
    drives: DriveDraw | None = None
    #: A V3 arm's ``safety.link_timeout_ms`` (None: the default, five periods of the explored rate).
    link_timeout_ms: float | None = None

    def describe(self) -> str:
        """The schedule as a Python literal (a regression test's data)."""
        drives = "None" if self.drives is None else self.drives.describe()
        return (
            f"Schedule({self.arm!r}, HaltPolicy.{self.policy.name}, ControlMode.{self.mode.name}, "
            f"faults={self.faults!r}, actions={self.actions!r}, home={self.home!r}, end_s={self.end_s!r}, "
            f"drives={drives}, link_timeout_ms={self.link_timeout_ms!r})"
        )


@dataclass
class Outcome:
    """What a run found."""

    schedule: Schedule
    violations: list[str] = field(default_factory=list)
    cycles: int = 0
    #: When the emulated plant left its model (a joint faster than :data:`PLANT_MODEL_DPS`), s; None: it never did.
    left_model_s: float | None = None

    @property
    def kinds(self) -> set[str]:
        """The invariants violated (the word before the colon of each violation)."""
        return {v.split(":", 1)[0] for v in self.violations}


def config_of(schedule: Schedule) -> ArmConfig:
    """The schedule's arm configuration: the example with its policy, mode, rate and emulated drives."""
    config = load_arm(schedule.arm)
    if schedule.drives is not None:
        config = with_drives(config, schedule.drives)
    rate = ARMS[schedule.arm] if schedule.mode is ControlMode.POSITION else config.control.rate_hz
    control = dataclasses.replace(config.control, halt_policy=schedule.policy, mode=schedule.mode, rate_hz=rate)
    if schedule.arm == "arm6_v3.yaml":
        # by default five periods of the explored rate (the example's 40 ms is five of its 125 Hz)
        safety = dataclasses.replace(config.safety, link_timeout_ms=schedule.link_timeout_ms)
        config = dataclasses.replace(config, safety=safety)
    return dataclasses.replace(config, control=control)


def load_arm(arm: str) -> ArmConfig:
    """The example configuration ``arm`` names (:data:`MIXED`: bimanual.yaml with drives of both generations)."""
    if arm != MIXED:
        return load_config(CONFIGS / arm)
    config = load_config(CONFIGS / "bimanual.yaml")
    left, right = config.buses
    left = dataclasses.replace(left, protocol=ProtocolSetting.V2)
    return dataclasses.replace(config, buses=(left, dataclasses.replace(right, protocol=ProtocolSetting.V3)))


def draw(rng: random.Random) -> Schedule:
    """A random schedule."""
    arm = rng.choice(sorted(ARMS))
    config = load_arm(arm)
    ids = [j.address for j in config.joints]  # (an arm on several buses: a fault names its drive by address)
    tuned = all(j.kp_nm_per_deg > 0 for j in config.joints) and arm != MIXED  # torque mode needs the joints' gains
    mode = ControlMode.TORQUE if tuned and rng.random() < 0.25 else ControlMode.POSITION
    faults = tuple(_draw_fault(rng, rng.choice(ids)) for _ in range(rng.choice((1, 1, 2, 2, 3))))
    actions: list[tuple[float, str, tuple[float, ...]]] = [(0.0, "move", target_pose(rng, config))]
    for _ in range(rng.randint(0, 4)):
        t = round(rng.uniform(0.05, 1.8), 3)
        what = rng.choice(("move", "move", "stop", "hold", "clear", "clear"))
        actions.append((t, what, target_pose(rng, config) if what == "move" else ()))
    homeable = [j.name for j in config.joints if j.homing is not None]
    home = (rng.choice(homeable),) if homeable and rng.random() < 0.05 else ()
    drives = draw_drives(rng, len(ids)) if rng.random() < DRAWN_DRIVES else None
    link = LINK_TIMEOUT_MIN_MS if arm == "arm6_v3.yaml" and rng.random() < 0.25 else None
    return Schedule(
        arm, rng.choice(POLICIES), mode, faults, tuple(sorted(actions)), home, drives=drives, link_timeout_ms=link
    )


def _draw_fault(rng: random.Random, motor_id: int) -> str:
    kind = rng.choice(list(InjectedFault))
    start = round(rng.choice((rng.uniform(0.0, 0.05), rng.uniform(0.0, 1.6), rng.uniform(0.0, 1.6))), 3)
    end = "" if kind is InjectedFault.POWER_CYCLE or rng.random() < 0.3 else f"-{start + rng.uniform(0.02, 0.6):.3f}"
    param = {
        InjectedFault.DELAY: f":{rng.uniform(1.0, 25.0):.1f}",
        InjectedFault.DROP: f":{rng.choice((1.0, rng.uniform(0.2, 1.0))):.2f}",
        InjectedFault.CORRUPT: ":" + rng.choice(("payload", "id", "length")),
        InjectedFault.COLLISION: f":{rng.choice((-1, 1)) * rng.uniform(0.5, 8.0):.2f}",
        # half of them between the controller's limit (70 degC in the examples) and the drive's own (80 degC): the
        # arm holds, or halts, for a motor the drive itself still runs
        InjectedFault.OVER_TEMPERATURE: f":{rng.uniform(71.0, 79.0):.1f}" if rng.random() < 0.5 else "",
    }.get(kind, "")
    return f"{kind.value}:{motor_id}@{start}{end}{param}"


def target_pose(rng: random.Random, config: ArmConfig) -> tuple[float, ...]:
    """A random pose well inside the limits (a fifth of the range off each end)."""
    out = []
    for j in config.joints:
        span = j.position_max_deg - j.position_min_deg
        out.append(round(rng.uniform(j.position_min_deg + 0.2 * span, j.position_max_deg - 0.2 * span), 1))
    return tuple(out)


class _Checker:
    """The invariants, evaluated in a cycle hook of the arm's controller (never raises: violations are collected);
    brake locks are seen by every drive's own command handling (in the loop and at close), link-loss trips once more
    after the arm closed (connect, homing and close included)."""

    def __init__(self, arm: Arm, schedule: Schedule, faults: list[Fault], outcome: Outcome) -> None:
        self.arm = arm
        self.outcome = outcome
        config = arm.config
        self.ids = [j.address for j in config.joints]
        self.names = config.joint_names
        # one count of the encoder at the joint (the uint16 fields carry the top 16 bits), and a V3 reading's 0.01 deg
        self.resolution_deg = np.array(
            [360.0 / 2 ** min(j.encoder_bits, 16) / abs(j.gear_ratio) + 0.01 for j in config.joints]
        )
        self.angle_pending: dict[int, str] = {}  # an angle found off, a violation unless a restart explains it
        n = len(self.ids)
        self.hidden = [False] * n  # a restart a link fault hid (see _hidden_restart)
        self.restarted_s = [math.nan] * n
        self.read_since_restart = [False] * n
        self.unsure = [0] * n  # cycles in a row each joint's axis has not been anchored
        # the controller's axes and each joint's error at its first comparison: the two reads that anchor an axis at
        # connect (0x92, then a state read) are a moment apart, and the joint's motion between them stays in its angle
        self.anchored_axes: Any = None
        self.anchor_error_deg: list[float] = []
        self.lower = np.array([j.position_min_deg for j in config.joints])
        self.upper = np.array([j.position_max_deg for j in config.joints])
        self.braked = [j.brake for j in config.joints]
        self.faults = faults
        self.off_policy = schedule.policy is HaltPolicy.OFF
        assert arm.simulation is not None and arm.plant is not None
        self.drives = arm.simulation.emulator.drives
        n = len(self.ids)
        self.faulted_since = math.nan
        self.anchor = np.full(n, np.nan)  # where the halt left each joint (NaN: not yet at rest)
        self.held_since = np.full(n, np.nan)  # since when each joint is held, undisturbed (NaN: exempt now)
        self.inside = np.ones(n, dtype=bool)  # whether it was inside its limits once it settled
        self.swings = [0] * n  # the plant's own count of each joint's swings since it last stood still
        self.swing_sign = [0.0] * n
        self.slow_since = [math.nan] * n
        self.swing_start = [math.nan] * n  # when each joint's swings since it last stood began
        self.released = [False] * n  # released with 0x80, and seen swinging or running on then
        self.fast_since = [math.inf] * n  # since when each joint moves faster than SWING_DPS, without a pause
        self.ran = [False] * n  # whether its drive has run (been turned on) since connect
        self.previous_state: ArmState | None = None
        self.previous_answered: set[int] = set()
        assert arm.supervisor is not None
        self.overspeed_limit = arm.supervisor.watchdog.overspeed_limit_dps
        self.overspeed_seen: str | None = None  # a joint read beyond it in the previous cycle, evaluated: which
        self.reported: set[str] = set()
        #: The violations found before the plant left its model.
        self.kept = 0
        #: Each drive's link-loss trips seen so far (a new one while no link fault acts on it is a violation).
        self.link_losses = {motor_id: getattr(self.drives[motor_id], "link_losses", 0) for motor_id in self.ids}
        for i, motor_id in enumerate(self.ids):
            if self.braked[i]:
                self._watch_brake(i, self.drives[motor_id])
        controller, supervisor = arm.controller, arm.supervisor
        assert controller is not None and supervisor is not None
        self.period_s = controller.period_s
        # the oldest a drive's flags get (each bus's round of status reads), and the cycle that sees them
        rounds = max(math.ceil(len(reads) / count) for reads, count in supervisor.status_rounds.rounds)
        self.unbraked_grace_s = (rounds + 2) * self.period_s
        self.cut_since = [math.nan] * n  # since when each braked joint's drive has its output cut, its brake released
        self.reads_angle = [f.angle_every_cycle for f in controller.families]
        self.samples: list[collections.deque[tuple[float, float, bool]]] = [
            collections.deque(maxlen=64) for _ in range(n)
        ]
        self.unreported = [False] * n  # a joint beyond its speed field since its turns were last confirmed
        for i, motor_id in enumerate(self.ids):
            self._watch_samples(i, self.drives[motor_id])

    def _watch_brake(self, i: int, drive: Any) -> None:
        """Every 0x78 the drive executes, with its joint's speed then (the plant's)."""
        execute = drive._execute_v3
        plant = self.arm.plant
        assert plant is not None

        def observed(command: Any, message: Any, now_s: float) -> None:
            if command is CommandV3.LOCK_BRAKE:
                speed = float(np.degrees(plant.state()[1][i]))
                supervisor = self.arm.supervisor
                at_once = supervisor is not None and self.ids[i] in supervisor.guard.braked_at_once()
                if abs(speed) > BRAKE_MOVING_DPS and not at_once:
                    self._violate(f"brake{i}", f"brake: {self.names[i]}'s brake locked at {speed:.1f} deg/s")
            execute(command, message, now_s)

        drive._execute_v3 = observed

    def _violate(self, key: str, text: str) -> None:
        if key not in self.reported:  # one report per invariant and joint
            self.reported.add(key)
            self.outcome.violations.append(text)

    def check_link(self, motor_id: int, name: str, t: float) -> None:
        """A link-loss trip of the drive since the last look, while no link fault acts on it (or did within
        :data:`SETTLE_S`), is a violation: a trip long after its silence ended is the controller's own silence."""
        losses = getattr(self.drives[motor_id], "link_losses", 0)
        if losses > self.link_losses[motor_id]:
            self.link_losses[motor_id] = losses
            if not self._acting(t, _LINK, motor_id):
                self._violate(f"link{motor_id}", f"link: {name}'s drive tripped its link-loss protection by {t:.3f} s")

    def _since(self, motor_id: int, kinds: tuple[InjectedFault, ...], t: float) -> bool:
        """Whether a fault of ``kinds`` on the drive has begun by ``t``."""
        return any(f.motor_id == motor_id and f.kind in kinds and f.start_s <= t for f in self.faults)

    def _acting(self, t: float, kinds: tuple[InjectedFault, ...], motor_id: int | None = None) -> bool:
        """Whether a fault of ``kinds`` (on the drive, or on any) acts at ``t`` or did within :data:`SETTLE_S`."""
        return any(
            f.kind in kinds
            and (motor_id is None or f.motor_id == motor_id)
            and f.start_s <= t
            and (f.end_s is None or t < f.end_s + SETTLE_S)
            for f in self.faults
        )

    def __call__(self, controller: Any, start_s: float, replies: list[Any]) -> None:
        try:
            self._check(replies)
        except Exception:  # a bug of the checker must not become a fault of the arm
            self.outcome.violations.append("checker: " + traceback.format_exc(limit=3))

    def _check(self, replies: list[Any]) -> None:
        self.outcome.cycles += 1
        supervisor, plant, controller = self.arm.supervisor, self.arm.plant, self.arm.controller
        if supervisor is None or plant is None or controller is None:
            return
        t = controller.clock.now()  # the cycle's end: what happened in it is seen
        state = supervisor.state
        q_rad, qd_rad = plant.state()
        q, qd = np.degrees(q_rad), np.degrees(qd_rad)
        if self.outcome.left_model_s is not None:
            return
        if not np.all(np.abs(qd) <= PLANT_MODEL_DPS):  # (NaN included)
            self.outcome.left_model_s = t
            self.kept = len(self.outcome.violations)
            return
        self._check_overspeed(controller, state, t)
        halted = state in (ArmState.HALTING, ArmState.HALTED)
        still_states = halted or state is ArmState.HOLDING
        answered = {r.motor_id for r in replies if r.message is not None}
        for i, motor_id in enumerate(self.ids):
            self.ran[i] = self.ran[i] or self.drives[motor_id].state is not RunState.OFF
        free = [self._free(i, motor_id, halted, supervisor.guard.codes, t) for i, motor_id in enumerate(self.ids)]
        gone = [
            self._since(motor_id, _SWITCHED_OFF, t) or self._acting(t, _UNREACHABLE, motor_id) for motor_id in self.ids
        ]
        # a push on one joint (or an obstruction) moves the whole arm (within the stiffness of the drives' holds),
        # and so does a joint nothing holds (released, switched off, or out of reach) that swings
        disturbed = self._acting(t, _EXTERNAL) or any(
            (f or g) and abs(v) > DISTURBING_DPS for f, g, v in zip(free, gone, qd, strict=True)
        )
        if not still_states:
            self.faulted_since = math.nan
        elif math.isnan(self.faulted_since):
            self.faulted_since = t
        self._check_angles(replies, t)
        for i, motor_id in enumerate(self.ids):
            self._count_swing(i, float(qd[i]), t)
            name = self.names[i]
            self.check_link(motor_id, name, t)
            if (
                halted
                and self.previous_state in (ArmState.HALTING, ArmState.HALTED)
                and motor_id in answered
                and motor_id in self.previous_answered
                and self.drives[motor_id].state is RunState.RUNNING
                and not self._acting(t, (InjectedFault.DROP,), motor_id)  # (a dropped halt: sent again next cycle)
            ):
                self._violate(f"halted{i}", f"halted: {name}'s drive answers and still runs at {t:.3f} s")
            if self.braked[i]:
                self._check_braked(i, motor_id, t, float(qd[i]), supervisor.guard)
            if disturbed or free[i] or gone[i] or self._returning(motor_id, t):
                self.anchor[i] = self.held_since[i] = np.nan
                continue
            self._check_held(i, t, float(q[i]), float(qd[i]), state, still_states)
        self.previous_state = state
        self.previous_answered = answered

    def _check_braked(self, i: int, motor_id: int, t: float, qd: float, guard: Any) -> None:
        """Braked joint ``i``: braked once its drive has cut its own output, and still a cycle after a brake command
        sent at once (both where its drive can be reached: a command it does not hear cannot stop it)."""
        if self._acting(t, _UNREACHABLE, motor_id):
            self.cut_since[i] = math.nan
            return
        drive = self.drives[motor_id]
        name = self.names[i]
        if drive.errors and drive.state is RunState.OFF and not getattr(drive, "held", False):
            if math.isnan(self.cut_since[i]):
                self.cut_since[i] = t
            elif t - self.cut_since[i] > self.unbraked_grace_s:
                since = self.cut_since[i]
                self._violate(f"unbraked{i}", f"unbraked: {name}'s drive cut its output by {since:.3f} s, no brake")
        else:
            self.cut_since[i] = math.nan
        sent = guard.lock_sent_s.get(motor_id)
        if sent is None or t < sent + self.period_s or motor_id not in guard.braked_at_once():
            return
        if abs(qd) > BRAKE_MOVING_DPS:
            self._violate(
                f"unheld{i}", f"unheld: {name} moves at {qd:+.1f} deg/s at {t:.3f} s, its brake command at {sent:.3f} s"
            )

    def _check_overspeed(self, controller: Any, state: ArmState, t: float) -> None:
        """A joint read beyond its overspeed limit in the previous cycle, which the watchdog evaluated, has the arm
        halting now; and this cycle's reading, for the next look."""
        if self.overspeed_seen is not None and state not in HALT_STATES and state is not ArmState.BUS_LOST:
            self._violate("overspeed", f"overspeed: {self.overspeed_seen}, and the arm is {state.value} at {t:.3f} s")
        self.overspeed_seen = None
        if state in _EVALUATED:
            speed = np.abs(controller.axes.qd_dps)
            beyond = np.flatnonzero(speed > self.overspeed_limit)
            if len(beyond):
                i = int(beyond[0])
                self.overspeed_seen = (
                    f"{self.names[i]} read at {controller.axes.qd_dps[i]:+.1f} deg/s (limit "
                    f"{self.overspeed_limit[i]:.1f}) while {state.value} at {t:.3f} s"
                )
    def _watch_samples(self, i: int, drive: Any) -> None:
        """The plant's angle of joint ``i`` whenever its drive samples what the controller's angle comes from (the
        encoder of a state reply; a V3 drive: its 0x92 reading)."""
        respond = drive.respond
        kind = MultiTurnAngle if self.reads_angle[i] else MotorState
        plant = self.arm.plant
        assert plant is not None

        def sampled(message: Any, now_s: float, transport: Any) -> Any:
            reply = respond(message, now_s, transport)
            if reply.__class__ is kind:  # (configuration angles and order; and whether the drive could tell its speed)
                reported = abs(drive.speed_dps) < SPEED_FIELD_MAX_DPS or self.reads_angle[i]
                self.samples[i].append((_sample_key(reply), float(plant.joint_positions_deg()[i]), reported))
            return reply

        drive.respond = sampled

    def _check_angles(self, replies: list[Any], t: float) -> None:
        """The controller's angle of every joint whose drive's sample reached it in the cycle against the plant's
        when the drive sampled it, unless the arm is faulted because the joint's drive restarted, or its restart was
        hidden (:meth:`_hidden_restart`)."""
        controller, supervisor = self.arm.controller, self.arm.supervisor
        assert controller is not None and supervisor is not None
        axes = controller.axes
        q_deg = axes.q_deg
        if axes is not self.anchored_axes:  # (connect's, or a homing's new frame: anchored anew)
            self.anchored_axes = axes
            self.anchor_error_deg = [math.nan] * len(self.names)
        for i, name in enumerate(self.names):
            # (the cycle's hooks run before its watchdog: a restart this cycle shows has its fault by the next one)
            pending = self.angle_pending.pop(i, None)
            if name in supervisor.lost_frames or self._hidden_restart(i, replies, t):
                continue
            if pending is not None:
                self._violate(f"angle{i}", pending)
            # a joint whose turns the controller knows are not sure (the 0x92 that confirms them did not come in this
            # exchange: lost with the link, or past its window on a busy RS485 line; it asks again in every exchange)
            # is given as long as its link is faulted and UNSURE_CYCLES cycles in a row after that to confirm them
            linked = self._linked(self.ids[i], t)
            self.unsure[i] = 0 if axes.anchored[i] or linked else self.unsure[i] + 1
            if not axes.anchored[i] and (linked or self.unsure[i] <= UNSURE_CYCLES):
                continue
            kind = MultiTurnAngle if self.reads_angle[i] else MotorState
            taken = [r.message for r in replies if r.motor_id == self.ids[i] and r.message.__class__ is kind]
            if not taken:
                continue
            # the sample the reply the controller took came from (a late one too: a delayed reply answers a later
            # request), the newest that matches
            key = _sample_key(taken[-1])
            at, reported = next(
                ((deg, told) for k, deg, told in reversed(self.samples[i]) if abs(k - key) < 0.005), (None, True)
            )
            if not reported:  # (a motor faster than its drive's speed field carries: no RMD motor turns so fast)
                self.unreported[i] = True
            if at is None or (self.unreported[i] and not axes.anchored[i]):
                continue
            self.unreported[i] = False
            error = float(q_deg[i]) - at
            if math.isnan(self.anchor_error_deg[i]):
                self.anchor_error_deg[i] = error
            if not abs(error - self.anchor_error_deg[i]) <= 2.0 * self.resolution_deg[i]:
                self.angle_pending[i] = (
                    f"angle: the controller reads {name} at {q_deg[i]:.3f} deg where it was at "
                    f"{at:.3f} deg when its drive sampled it ({error:+.3f}) at {t:.3f} s, its drive "
                    "not restarted"
                )

    def _hidden_restart(self, i: int, replies: list[Any], t: float) -> bool:
        """Whether joint ``i``'s drive restarted and went unheard (a link fault), or its motor turned faster than its
        speed field tells, before one of its restart reads (0x92, V3: 0xB1) reached the controller: a restart whose
        sign a silence (or a spin) hid, while its joint moves on (an older drive's first-turn reading is its only
        sign, docs/protocol.md), is not asked of the controller."""
        motor_id = self.ids[i]
        latest = max(
            (f.start_s for f in self.faults if f.motor_id == motor_id and f.kind is InjectedFault.POWER_CYCLE),
            default=math.inf,
        )
        if self.hidden[i] or latest > t:
            return self.hidden[i]
        if latest != self.restarted_s[i]:  # (a restart since the last look: no read of it yet)
            self.restarted_s[i], self.read_since_restart[i] = latest, False
        # (a drive heard, its motor within what its speed field tells: a reading then shows the restart)
        telling = not self._linked(motor_id, t) and (not self.samples[i] or self.samples[i][-1][2])
        read = any(r.motor_id == motor_id and r.message.__class__ in (MultiTurnAngle, Runtime) for r in replies)
        if telling and read:
            self.read_since_restart[i] = True
        elif not telling and not self.read_since_restart[i]:
            self.hidden[i] = True
        return self.hidden[i]

    def _linked(self, motor_id: int, t: float) -> bool:
        """Whether a link fault (silent, drop, corrupt) acts on the drive at ``t``."""
        return any(f.motor_id == motor_id and f.kind in _UNREACHABLE and f.active(t) for f in self.faults)

    def _returning(self, motor_id: int, t: float) -> bool:
        """Whether the drive holds with 0x81 a point its joint was pushed away from (a collision or an obstruction
        acted on it) and runs it back there, the supervisor having kept that hold (``hold_failed``, "kept at 0x81":
        gravity loads the joint): its hold working, not the arm moving by itself. A joint pushed turns past its drive's
        peak torque comes back at the drive's top speed, for longer than :data:`SETTLE_S` (found on a wrist pitch:
        released, it would fall)."""
        drive = self.drives[motor_id]
        hold = getattr(drive, "_hold_deg", None)
        if drive.state is not RunState.STOPPED or hold is None or not self._since(motor_id, _EXTERNAL, t):
            return False
        # only once the supervisor has judged it and kept its hold (gravity loads it): a joint it may release is held
        # to being released, as any other (a checker that let every run back pass would not see a release missed)
        supervisor = self.arm.supervisor
        name = self.names[self.ids.index(motor_id)]
        kept = supervisor is not None and any(
            f.kind is FaultKind.HOLD_FAILED and f.joint == name and "kept at 0x81" in f.detail
            for f in supervisor.faults
        )
        if not kept:
            return False
        gap = float(hold - drive._shaft_deg)
        return abs(gap) > BAND_DEG * float(drive.model.gear_ratio) and gap * float(drive._speed_dps) > 0

    def _free(self, i: int, motor_id: int, halted: bool, codes: Any, t: float) -> bool:
        """Whether joint ``i`` is one its halt leaves free: an unbraked joint under ``halt_policy: off``, one whose
        drive was never turned on (it powers up off: a halt leaves it off), or one the controller released with 0x80
        because its drive's hold did not hold it (checked here: the plant saw it swing or run on)."""
        if halted and not self.ran[i] and not self.braked[i]:
            return True
        if not halted or codes[motor_id].name != "MOTOR_OFF" or self.braked[i]:
            self.released[i] = False
            return False
        restless = t - self.fast_since[i] >= 0.8 * RESTLESS_RELEASE_S
        if self.off_policy or self.released[i] or self.swings[i] >= SWINGS_SEEN or restless:
            self.released[i] = True  # (what it was released for was seen; it coasts to rest since)
            return True
        self._violate(f"release{i}", f"release: {self.names[i]} released with 0x80 at {t:.3f} s without swinging")
        return True

    def _count_swing(self, i: int, qd: float, t: float) -> None:
        """The plant's count of joint ``i``'s swings since it last stood (slower than :data:`ANCHOR_DPS` for 50 ms)."""
        if abs(qd) <= SWING_DPS:
            self.fast_since[i] = math.inf
        elif math.isinf(self.fast_since[i]):
            self.fast_since[i] = t
        if abs(qd) <= ANCHOR_DPS:
            if math.isnan(self.slow_since[i]):
                self.slow_since[i] = t
            elif t - self.slow_since[i] >= 0.05:
                self.swings[i], self.swing_sign[i] = 0, 0.0
            return
        self.slow_since[i] = math.nan
        sign = math.copysign(1.0, qd)
        if abs(qd) > 10.0 and sign != self.swing_sign[i]:
            if self.swings[i] == 0:
                self.swing_start[i] = t
            self.swings[i] += 1
            self.swing_sign[i] = sign

    def _check_held(self, i: int, t: float, q: float, qd: float, state: ArmState, still_states: bool) -> None:
        """Joint ``i``, held and undisturbed: inside its limits (in every state) once settled if it was then; while the
        arm is faulted, once settled, it comes to rest (its anchor) and stays there."""
        name = self.names[i]
        if math.isnan(self.held_since[i]):
            self.held_since[i] = t
            self.inside[i] = True
        if t < self.held_since[i] + SETTLE_S:
            self.inside[i] = self.inside[i] and bool(self.lower[i] <= q <= self.upper[i])
            return
        if self.inside[i] and not self.lower[i] - BAND_DEG <= q <= self.upper[i] + BAND_DEG:
            self._violate(f"limit{i}", f"limit: {name} at {q:.2f} deg while {state.value} at {t:.3f} s")
        if not still_states or (self.swings[i] >= 2 and t - self.swing_start[i] <= UNHELD_GRACE_S):
            # (a joint its drive's own hold swings: the controller has UNHELD_GRACE_S to see it and release it)
            self.anchor[i] = np.nan
            return
        settled_s = max(self.faulted_since, self.held_since[i]) + SETTLE_S
        if t < settled_s:
            return
        if math.isnan(self.anchor[i]):
            if abs(qd) <= ANCHOR_DPS:  # where its halt left it
                self.anchor[i] = q
            elif t - settled_s > RESTLESS_S:
                self._violate(
                    f"still{i}", f"still: {name} still moves at {qd:+.1f} deg/s while {state.value} at {t:.3f} s"
                )
            return
        if abs(q - self.anchor[i]) > BAND_DEG:
            self._violate(
                f"still{i}", f"still: {name} moved {q - self.anchor[i]:+.2f} deg while {state.value} at {t:.3f} s"
            )


class _WallTimeout(BaseException):
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


def _sample_key(message: Any) -> float:
    """What tells a drive's samples apart: the encoder of a state reply, the angle of a 0x92 reply."""
    return float(message.angle_deg if isinstance(message, MultiTurnAngle) else message.encoder)


def run(schedule: Schedule) -> Outcome:
    """Play ``schedule`` and check every invariant in every cycle."""
    outcome = Outcome(schedule)
    faults = [parse_fault(spec) for spec in schedule.faults]
    config = config_of(schedule)
    arm = Arm(config, emulate=True, faults=faults, home=schedule.home)
    if schedule.drives is not None:  # the drives' reply latency, in the simulation connect builds
        _with_latency(arm, schedule.drives.latency_s)
    with _wall_limit(WALL_LIMIT_S):
        try:
            kept = _play(arm, schedule, faults, outcome)
        except _WallTimeout as exc:
            outcome.violations.append(f"escape: {exc}")
            kept = None
    if outcome.left_model_s is not None and kept is not None:
        # what the emulation did after its plant left its model (speeds no joint has: no end stops are modelled, and
        # its state runs to infinity and NaN) says nothing of the controller
        del outcome.violations[kept:]
    return outcome


def _with_latency(arm: Arm, latency_s: float) -> None:
    """Have the simulation ``arm.connect`` builds answer with ``latency_s`` (before its first exchange)."""
    start = arm._start_simulation

    def started() -> Any:
        transport, clock = start()
        assert arm.simulation is not None
        arm.simulation.timing = TimingModel(latency_s)
        return transport, clock

    arm._start_simulation = started  # type: ignore[method-assign]


def _play(arm: Arm, schedule: Schedule, faults: list[Fault], outcome: Outcome) -> int | None:
    """Play the schedule; returns how many violations were found before the plant left its model (None: it never
    did, or no checker ran)."""

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
    checker = None
    try:
        if connected:
            assert arm.controller is not None
            checker = _Checker(arm, schedule, faults, outcome)
            arm.controller.cycle_hooks.append(checker)
            _act(arm, schedule, guarded)
    finally:
        guarded("close", arm.close)
    controller, supervisor = arm.controller, arm.supervisor
    if controller is not None and controller.error is not None:
        outcome.violations.append(f"escape: the loop ended on {controller.error!r}")
    if supervisor is not None:
        errors = [f for f in supervisor.faults if f.kind is FaultKind.EXCEPTION]
        if errors:  # an exception in the control cycle is a bug, halted or not
            outcome.violations.append(f"escape: an exception in the loop: {errors[0]}")
    if arm.simulation is not None:  # (also when connect failed: what it did to the drives)
        drives = arm.simulation.emulator.drives
        if checker is not None:  # trips at close: as in the loop
            for motor_id, name in zip(checker.ids, checker.names, strict=True):
                checker.check_link(motor_id, name, arm.simulation.now_s)
        else:
            linked = {f.motor_id for f in faults if f.kind in _LINK}
            for motor_id, drive in sorted(drives.items()):
                if getattr(drive, "link_losses", 0) and motor_id not in linked:
                    outcome.violations.append(f"link: drive {motor_id} tripped its link-loss protection in the session")
    return None if checker is None else checker.kept


def _act(arm: Arm, schedule: Schedule, guarded: Callable[[str, Callable[[], object]], None]) -> None:
    """The schedule's user actions at their times, then the wait to its end."""
    assert arm.controller is not None
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


def drawn(seed: int, k: int) -> Schedule:
    """Schedule ``k`` of the draw ``seed`` (each from its own generator: reproduced alone, in any order)."""
    return draw(random.Random(seed * 1_000_003 + k))


def explore_one(seed: int, k: int, shrinking: bool = True) -> Outcome:
    """Run schedule ``k`` of the draw ``seed``; a failing one shrunk to its smallest form (``shrinking``)."""
    logging.disable(logging.CRITICAL)  # (every injected fault is logged: in a worker, nobody reads it)
    outcome = run(drawn(seed, k))
    if outcome.violations and shrinking:
        smallest = shrink(outcome.schedule, fails_like(outcome.kinds))
        if smallest != outcome.schedule:
            outcome = run(smallest)
    return outcome


def _explore_one(args: tuple[int, int, bool]) -> Outcome:
    return explore_one(*args)


def explore(seed: int, count: int, *, first: int = 0, jobs: int = 1, shrinking: bool = True) -> Iterator[Outcome]:
    """Run schedules ``first .. first + count - 1`` of the draw ``seed`` in ``jobs`` worker processes (1: in this
    one); yields every outcome as it comes."""
    work = [(seed, k, shrinking) for k in range(first, first + count)]
    if jobs == 1:
        yield from map(_explore_one, work)
        return
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        yield from pool.imap_unordered(_explore_one, work)
