"""Braked joints whose drives cannot hold them (``motion/safety/brakes.py``): braked at once, whatever their speed, in
the cycle their drive is found unable to hold; the at-rest rule for drives that hold is ``tests/test_halted.py``'s.
On arm6_v3's emulated V3 drives in simulated time."""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import numpy as np
import pytest

from motion.api import Arm
from motion.config import ArmConfig, load_config
from motion.config.schema import ControlMode, HaltPolicy
from motion.emulator import parse_fault
from motion.emulator.drive_v3 import EmulatedDriveV3
from motion.errors import FaultKind
from motion.protocol.table import ProtocolFamily
from motion.protocol.v3.messages import BareV3, BrakeCommand, CommandV3
from motion.safety import ArmState
from motion.safety.halted import HaltGuard
from tests import fault_explorer
from tests.drive_models import draw_drives, with_drives
from tests.fault_explorer import Schedule
from tests.motion_rig import CONFIGS, requests_in_log

SHOULDER = 1  # arm6_v3's shoulder_pitch: braked, loaded by gravity (motor 2)
START_DEG = 25.0
FAULT_S = 1.0


def _arm6_v3(policy: HaltPolicy = HaltPolicy.HOLD, seed: int | None = None) -> ArmConfig:
    config = load_config(CONFIGS / "arm6_v3.yaml")
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, halt_policy=policy))
    if seed is not None:
        config = with_drives(config, draw_drives(random.Random(seed), len(config.joints)))
    return config


def _locks_to(log: Path, motor_id: int) -> list[float]:
    """When drive ``motor_id`` was sent 0x78, s of the frame log (a silent drive's too: the frame was on the wire)."""
    return [
        t
        for t, m, message in requests_in_log(log.read_text(), ProtocolFamily.V3)
        if m == motor_id and isinstance(message, BareV3) and message.command is CommandV3.LOCK_BRAKE
    ]


def _shoulder_deg(arm: Arm) -> float:
    assert arm.plant is not None
    return float(arm.plant.joint_positions_deg()[SHOULDER])


@pytest.mark.parametrize("seed", [None, 5])
@pytest.mark.parametrize(
    ("fault", "kind", "reachable"),
    [
        ("over_temperature", FaultKind.DRIVE_OVER_TEMPERATURE, True),
        ("under_voltage", FaultKind.DRIVE_LOW_VOLTAGE, True),
        ("silent", FaultKind.NO_REPLY, False),  # off the bus: hears nothing
        ("drop", FaultKind.NO_REPLY, False),  # its link lost: every request lost
        ("corrupt", FaultKind.NO_REPLY, True),  # hears us, its replies lost: not seen to hold (nor its lock's echo)
    ],
)
def test_a_braked_joint_whose_drive_cannot_hold_is_braked_in_the_cycle_it_is_found_and_stops(
    tmp_path: Path, fault: str, kind: FaultKind, reachable: bool, seed: int | None
) -> None:
    # issue: an over-temperature V3 drive does not execute the 0x81 sent every cycle, the brake locked only at rest,
    # and the shoulder fell from 25 to 341 deg (limits +-120) in 5 s with no 0x78 sent
    log = tmp_path / "frames.log"
    arm = Arm(
        _arm6_v3(seed=seed),
        emulate=True,
        emulated_protocol="v3",
        initial_deg=[0.0, START_DEG, 0.0, 0.0, 0.0, 0.0],
        faults=[parse_fault(f"{fault}:2@{FAULT_S}")],
        emulator_log=log,
    )
    with arm:
        supervisor, simulation = arm.supervisor, arm.simulation
        assert supervisor is not None and simulation is not None and arm.frame_log is not None
        period = supervisor.controller.period_s
        arm.sleep(FAULT_S + 0.3)
        # the brake command went out in the cycle that found the drive unable to hold, before that cycle's end (where
        # the arm was running, the cycle whose fault halted it)
        found = next(f for f in supervisor.faults if f.kind is kind and f.joint == "shoulder_pitch")
        on_wire = [arm.frame_log.start_s + t for t in _locks_to(log, 2)]
        assert on_wire and found.time_s <= on_wire[0] < found.time_s + period, (found, on_wire)
        # it fell at most for the flags' age (their 0x9A round) or the missed replies before it was found, and stays
        held_at = _shoulder_deg(arm)
        assert abs(held_at - START_DEG) < 1.5, held_at
        arm.sleep(1.0)
        assert _shoulder_deg(arm) == pytest.approx(held_at, abs=1e-6)
        assert supervisor.state is ArmState.HALTED
        drive = simulation.emulator.drives[2]
        assert isinstance(drive, EmulatedDriveV3) and drive.held
        # braked by our 0x78 where it hears us, else by its own link-loss stop (it hears nothing)
        assert drive.link_losses == (0 if reachable else 1)
        # what a test sees of it: the finding, the joints braked at once, when the brake command went out
        assert supervisor.brakes.unheld[2].time_s == found.time_s
        assert 2 in supervisor.guard.braked_at_once()
        assert found.time_s <= supervisor.guard.lock_sent_s[2] <= on_wire[0]


def test_under_halt_policy_off_a_braked_joint_is_braked_with_the_halt_while_it_moves(tmp_path: Path) -> None:
    # the policy turns every output off: a braked joint is braked in the halt's batch, not once at rest (0x81 until
    # its lock is acknowledged, then 0x80 as the policy says)
    log = tmp_path / "frames.log"
    arm = Arm(_arm6_v3(HaltPolicy.OFF), emulate=True, emulated_protocol="v3", emulator_log=log)
    with arm:
        supervisor, plant = arm.supervisor, arm.plant
        assert supervisor is not None and plant is not None and arm.frame_log is not None
        arm.move_to({"shoulder_pitch": 40.0}, wait=False)
        arm.sleep(0.4)
        moving_dps = float(np.degrees(plant.state()[1][SHOULDER]))
        assert abs(moving_dps) > 10.0  # mid-move
        supervisor.estop(FaultKind.ESTOP)
        halt, period = supervisor.halts[-1], supervisor.controller.period_s
        locks = _locks_to(log, 2)
        assert locks and halt.halt_sent_s <= arm.frame_log.start_s + locks[0] < halt.halt_sent_s + period  # its batch
        assert halt.halt_sent_s <= supervisor.guard.lock_sent_s[2] < halt.halt_sent_s + period
        arm.sleep(0.3)
        assert supervisor.state is ArmState.HALTED
        assert {2, 3} <= supervisor.guard.locked
        assert supervisor.guard.codes[2] == supervisor.guard.code  # 0x80 once locked
        held_at = _shoulder_deg(arm)
        arm.sleep(0.5)
        assert _shoulder_deg(arm) == pytest.approx(held_at, abs=1e-6)


def test_a_clear_releases_a_brake_locked_at_once_and_the_joint_moves_again() -> None:
    arm = Arm(
        _arm6_v3(),
        emulate=True,
        emulated_protocol="v3",
        initial_deg=[0.0, START_DEG, 0.0, 0.0, 0.0, 0.0],
        faults=[parse_fault(f"under_voltage:2@{FAULT_S}-{FAULT_S + 0.2}")],
    )
    with arm:
        supervisor, simulation = arm.supervisor, arm.simulation
        assert supervisor is not None and simulation is not None
        arm.sleep(FAULT_S + 0.5)
        assert 2 in supervisor.guard.locked and supervisor.brakes.unheld
        arm.clear()  # the supply is back: the drive recovers by itself, its output on with the next command
        assert not supervisor.brakes.unheld and not supervisor.guard.lock_sent_s
        assert simulation.emulator.drives[2].brake is BrakeCommand.RELEASE  # type: ignore[attr-defined]
        arm.move_to({"shoulder_pitch": 10.0})
        arm.sleep(0.3)
        assert arm.positions()["shoulder_pitch"] == pytest.approx(10.0, abs=0.1)


@pytest.mark.parametrize("fault", ["over_temperature:2@0.9", "under_voltage:3@0.8", "silent:2@0.9"])
@pytest.mark.parametrize("policy", [HaltPolicy.STOP, HaltPolicy.HOLD])
def test_the_explorer_finds_no_braked_joint_unbraked_or_moving_after_its_brake_command(
    fault: str, policy: HaltPolicy
) -> None:
    # a move under way when the drive cuts its output, on drawn drives
    schedule = Schedule(
        "arm6_v3.yaml",
        policy,
        ControlMode.POSITION,
        faults=(fault,),
        actions=((0.5, "move", (0.0, 40.0, -50.0, 0.0, 0.0, 0.0)),),
        end_s=2.5,
        drives=draw_drives(random.Random(17), 6),
    )
    outcome = fault_explorer.run(schedule)
    assert outcome.violations == [], outcome.violations


def test_the_explorer_sees_a_braked_joint_left_unbraked(monkeypatch: pytest.MonkeyPatch) -> None:
    # the controller as it was: no brake at once for a drive that cannot hold
    monkeypatch.setattr(HaltGuard, "braked_at_once", lambda self: [])
    schedule = Schedule(
        "arm6_v3.yaml",
        HaltPolicy.STOP,
        ControlMode.POSITION,
        faults=("over_temperature:2@0.9",),
        actions=((0.5, "move", (0.0, 40.0, -50.0, 0.0, 0.0, 0.0)),),
        end_s=2.0,
    )
    outcome = fault_explorer.run(schedule)
    assert "unbraked" in outcome.kinds, outcome.violations
