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
#: How long a trial waits for the fault after the onset, s (simulated).
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
    return dataclasses.replace(
        config, joints=tuple(dataclasses.replace(j, collision_threshold_nm=None) for j in config.joints)
    )


def with_thresholds(config: ArmConfig, thresholds_nm: Sequence[float]) -> ArmConfig:
    """``config`` with these collision thresholds, one per joint, N·m."""
    joints = tuple(
        dataclasses.replace(j, collision_threshold_nm=float(t))
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


def nominal_run(
    config: ArmConfig, motion: Motion, *, initial_deg: Sequence[float] | None = None, settle_s: float = 0.3
) -> Run:
    """Run ``motion`` to its end (plus ``settle_s``) with the observer on; the largest |signal| per joint."""
    arm = Arm(config, emulate=True, observe_collisions=True, initial_deg=initial_deg)
    peak = np.zeros(len(config.joints))
    fault = None
    with arm:
        supervisor = arm.supervisor
        assert supervisor is not None and arm.controller is not None
        watchdog = supervisor.watchdog

        def record(*_: object) -> None:
            if watchdog.collision_armed:
                np.fmax(peak, np.abs(watchdog.collision_signal_nm), out=peak)

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
    return Run(duration, peak, fault, final)


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
) -> Trial:
    """Start ``motion``, apply ``sign × share × peak torque`` to ``joint`` (joint angle sense) ``onset_s`` later."""
    spec = config.joints[joint]
    torque = sign * share * spec.peak_torque_nm
    arm = Arm(config, emulate=True, initial_deg=initial_deg)
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
        with contextlib.suppress(MotionFault):
            supervisor.wait(DETECTION_WAIT_S)
        fault = supervisor.fault
        latency = supervisor.halts[0].cycle - first + 1 if supervisor.halts else None
        state = supervisor.state
        stopped = (RunState.STOPPED, RunState.OFF)
        halted = state is ArmState.COMPLYING or (
            state in (ArmState.HALTING, ArmState.HALTED)
            and all(drive.state in stopped for drive in emulator.drives.values())
        )
    return Trial(spec.name, onset_s, torque, fault, latency, halted, state)
