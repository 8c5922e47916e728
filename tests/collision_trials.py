"""Collision trials on emulated arms (issue 14), shared by the tests and ``bench/collision_trials.py``.

A trial runs a motion in simulated time, applies an external torque step to one joint through the emulated arm's
dynamics at a chosen instant, and reports when and where the collision fault came, and whether every axis halted.
The latency counts control cycles from the first cycle that can see the torque (1: that very cycle), as
``tests/test_safety.py`` counts detection.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from motion.api import Arm
from motion.config import ArmConfig
from motion.config.schema import ControlMode
from motion.demo import TORQUE_TARGET_DEG, WAYPOINTS_DEG
from motion.emulator import Fault, InjectedFault, RunState
from motion.errors import MotionFault
from motion.safety import ArmState

#: The step, as a share of the joint's peak torque (torque constant × gear ratio × current limit).
STEP_SHARE = 0.15
#: How long a trial runs the control cycles after the onset, waiting for the fault, s (simulated).
DETECTION_WAIT_S = 0.5

Motion = Callable[[Arm], object]


def demo_path(speed_scale: float = 1.0) -> Motion:
    """The demo's waypoint path (position mode in arm6)."""
    return lambda arm: arm.follow(WAYPOINTS_DEG, speed_scale=speed_scale, wait=False)


def torque_move(speed_scale: float = 1.0) -> Motion:
    """The demo's torque-mode move."""
    return lambda arm: arm.move_to(
        dict(zip(arm.names, TORQUE_TARGET_DEG, strict=True)), speed_scale=speed_scale, wait=False
    )


def torque_variant(config: ArmConfig) -> ArmConfig:
    """``config`` in torque mode with gravity feed-forward (as the demo's torque run)."""
    control = dataclasses.replace(config.control, mode=ControlMode.TORQUE, gravity_feedforward=True)
    return dataclasses.replace(config, control=control)


def without_thresholds(config: ArmConfig) -> ArmConfig:
    """``config`` with no collision threshold (the observer still runs with ``observe_collisions``)."""
    return dataclasses.replace(config, joints=tuple(j.without_collision_threshold() for j in config.joints))


def with_thresholds(config: ArmConfig, thresholds_nm: Sequence[float]) -> ArmConfig:
    """``config`` with these collision thresholds, one per joint, N·m."""
    joints = tuple(
        dataclasses.replace(j, collision_threshold_nm=float(t), collision_threshold_torque_nm=None)
        for j, t in zip(config.joints, thresholds_nm, strict=True)
    )
    return dataclasses.replace(config, joints=joints)


def mismatched(config: ArmConfig, *, torque_constant: float = 1.0, friction: float = 1.0) -> ArmConfig:
    """``config`` whose emulated drives differ from its model: true torque constant and friction scaled."""
    joints = tuple(
        dataclasses.replace(
            j,
            emulation=dataclasses.replace(
                j.emulation,
                torque_constant_nm_per_a=j.torque_constant_nm_per_a * torque_constant,
                viscous_friction_nm_per_dps=j.emulation.viscous_friction_nm_per_dps * friction,
                coulomb_friction_nm=j.emulation.coulomb_friction_nm * friction,
            ),
        )
        for j in config.joints
    )
    return dataclasses.replace(config, joints=joints)


@dataclass
class Run:
    """A run without collision: its duration, the largest collision signal per joint and any fault."""

    duration_s: float
    signal_peak_nm: np.ndarray
    fault: MotionFault | None
    final_deg: list[float]
    #: The largest |signal| over the threshold in force per joint (over the bound where a joint is not watched).
    limit_share_peak: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    #: With a ``margin``: the largest |signal| per joint of the cycles where the margin times it exceeded the bound
    #: (what ``collision-calibrate`` proposes a floor from; 0: none did).
    beyond_nm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


def nominal_run(
    config: ArmConfig,
    motion: Motion,
    *,
    initial_deg: Sequence[float] | None = None,
    settle_s: float = 0.3,
    arm: Arm | None = None,
    margin: float = 1.0,
) -> Run:
    """Run ``motion`` to its end (plus ``settle_s``) with the observer on; the largest |signal| per joint (on ``arm``,
    not connected yet, where given: an emulated arm of ``config`` observing collisions), and the largest of those
    whose ``margin`` times left the bound."""
    if arm is None:
        arm = Arm(config, emulate=True, observe_collisions=True, initial_deg=initial_deg)
    n = len(config.joints)
    peak, share, limit, beyond, signal = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    fault = None
    with arm:
        supervisor = arm.supervisor
        assert supervisor is not None and arm.controller is not None
        watchdog = supervisor.watchdog

        def record(*_: object) -> None:
            if watchdog.collision_armed:
                np.abs(watchdog.collision_signal_nm, out=signal)
                np.fmax(peak, signal, out=peak)
                np.copyto(limit, watchdog.collision_limit_nm)
                np.copyto(limit, watchdog.collision_bound_nm, where=~np.isfinite(limit))
                np.fmax(share, signal / limit, out=share)
                np.fmax(beyond, signal, out=beyond, where=signal * margin > watchdog.collision_bound_nm)

        arm.controller.cycle_hooks.append(record)
        start = arm.controller.clock.now()
        try:
            motion(arm)
            supervisor.wait(60.0)
            arm.sleep(settle_s)
        except MotionFault as exc:
            fault = exc
        duration = arm.controller.clock.now() - start
        final = list(arm.positions().values())
    record()
    return Run(duration, peak, fault, final, share, beyond)


@dataclass
class Trial:
    """One collision trial."""

    joint: str
    onset_s: float
    torque_nm: float
    fault: MotionFault | None
    latency_cycles: int | None
    halted: bool
    state: ArmState

    @property
    def detected(self) -> bool:
        """A collision fault came."""
        return self.fault is not None and self.fault.kind == "collision"

    @property
    def isolated(self) -> bool:
        """It names this joint and no other."""
        return self.detected and self.fault is not None and self.fault.joints == (self.joint,)


def collision_trial(
    config: ArmConfig,
    motion: Motion,
    joint: int,
    onset_s: float,
    *,
    share: float = STEP_SHARE,
    sign: float = 1.0,
    initial_deg: Sequence[float] | None = None,
    arm: Arm | None = None,
) -> Trial:
    """Start ``motion``, apply ``sign × share × peak torque`` to ``joint`` (joint angle sense) ``onset_s`` later
    (on ``arm``, not connected yet, where given: an emulated arm of ``config``)."""
    spec = config.joints[joint]
    torque = sign * share * spec.peak_torque_nm
    arm = Arm(config, emulate=True, initial_deg=initial_deg) if arm is None else arm
    with arm:
        supervisor, controller, emulator = arm.supervisor, arm.controller, arm.emulator
        assert supervisor is not None and controller is not None and emulator is not None
        motion(arm)
        arm.sleep(onset_s)
        if supervisor.fault is not None:  # a false positive before the onset
            return Trial(spec.name, onset_s, torque, supervisor.fault, None, False, supervisor.state)
        first = controller.loop.next_cycle
        # the emulator's torque is in the drive's positive sense; direction -1 turns the joint the other way
        emulator.add_fault(
            Fault(InjectedFault.COLLISION, spec.motor_id, emulator.time_s, value=spec.direction * torque)
        )
        # the cycles run on whether or not the motion ends meanwhile (a collision after the last set-point of a move
        # acts on a held joint: supervisor.wait would return at once, and no cycle would see it)
        controller.wait_for(lambda: supervisor.fault is not None, DETECTION_WAIT_S)
        fault = supervisor.fault
        latency = supervisor.halts[0].cycle - first + 1 if supervisor.halts else None
        state = supervisor.state
        stopped = (RunState.STOPPED, RunState.OFF)
        halted = state is ArmState.COMPLYING or (
            state in (ArmState.HALTING, ArmState.HALTED)
            and all(drive.state in stopped for drive in emulator.drives.values())
        )
    return Trial(spec.name, onset_s, torque, fault, latency, halted, state)


# ---------------------------------------------------------------------------------------------- in real time


@dataclass
class RealtimeTrial:
    """One collision trial against the emulator in its own process (real time, over a pty).

    ``latency_cycles`` counts the joint's control frames (0xA4 / 0xA1 / 0x280) that the emulated drive received from
    the onset on, up to the first halt (0x81 or 0x80): the cycles that ran with the torque acting, the detection
    cycle included (the halt goes out in the cycle that detects it); both ends are the emulator's own clock.
    """

    joint: str
    onset_s: float  # the emulator's clock
    fault: MotionFault | None
    latency_cycles: int | None
    moving_at_onset: bool

    @property
    def isolated(self) -> bool:
        """A collision fault naming this joint and no other."""
        return self.fault is not None and self.fault.kind == "collision" and self.fault.joints == (self.joint,)


def log_frames(log: Path) -> list[tuple[float, str, str]]:
    """(time, CAN id, payload hex; upper case) of every request in an emulator frame log."""
    frames = []
    for line in log.read_text().splitlines():
        fields = line.split(maxsplit=3)
        if len(fields) == 4 and fields[1] == "IN":
            ident, _, data = fields[3].split(" | ")[0].partition(":")
            frames.append((float(fields[0]), ident.strip().upper(), data.strip().upper()))
    return frames


def frame_latency(log: Path, motor_id: int, onset_s: float) -> tuple[int | None, bool]:
    """From an emulator frame log: the motor's control frames from ``onset_s`` to its first halt, and whether a
    control frame of the motion had come before the onset (the arm was moving, not only holding)."""
    own = f"{0x140 + motor_id:X}"
    count, before = 0, 0
    for t, ident, data in log_frames(log):
        command = data[:2]
        if ident == own and command in {"80", "81"} and t >= onset_s:
            return count, before > 0
        control = ident == "280" or (ident == own and command in {"A1", "A4"})
        if control:
            if t >= onset_s:
                count += 1
            else:
                before += 1
    return None, before > 0


def realtime_trial(
    config: ArmConfig, motion: Motion, joint: int, onset_s: float, log: Path, *, share: float = STEP_SHARE
) -> RealtimeTrial:
    """Start the emulator process with a torque step of ``share × peak torque`` on ``joint`` at ``onset_s`` of its
    own clock, connect (``RateError`` when the host cannot hold the configured rate), start ``motion`` and wait
    for the fault."""
    spec = config.joints[joint]
    fault = Fault(InjectedFault.COLLISION, spec.motor_id, onset_s, value=spec.direction * share * spec.peak_torque_nm)
    arm = Arm(config, emulate="realtime", faults=[fault], emulator_log=log)
    arm.connect()
    caught: MotionFault | None = None
    with contextlib.closing(arm):
        try:
            motion(arm)
            assert arm.supervisor is not None
            arm.supervisor.wait(onset_s + 10.0)
        except MotionFault as exc:
            caught = exc
    latency, moving = frame_latency(log, spec.motor_id, onset_s)
    return RealtimeTrial(spec.name, onset_s, caught, latency, moving)
