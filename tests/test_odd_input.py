"""Odd input refused before anything is queued or sent, with a message naming the value (issue 30): the API's
arguments, a program's numbers, the codec's values, a URDF's masses and axes. Each case crashed, hung or was accepted
before."""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kinematics.model import build_arm
from motion import Arm
from motion.cli import main
from motion.config import load_config
from motion.errors import ConfigError, EncodeError, PlanningError
from motion.protocol import can_frame, rs485_frame
from motion.protocol.messages import MultiTurnPositionSpeed, SpeedControl, TorqueControl
from motion.safety import ArmState
from tests.motion_rig import CONFIGS

ARM6 = CONFIGS / "arm6.yaml"


@pytest.fixture(scope="module")
def arm() -> Iterator[Arm]:
    with Arm(load_config(ARM6), emulate=True) as arm:
        yield arm


def _refused(arm: Arm, call: Callable[[], object], error: type[Exception], match: str) -> None:
    """``call`` raises ``error`` matching ``match``, and the arm neither moved nor faulted."""
    assert arm.supervisor is not None and arm.controller is not None
    before = arm.controller.reference.position.copy()
    with pytest.raises(error, match=match):
        call()
    arm.sleep(0.05)
    assert arm.supervisor.state is ArmState.READY, arm.supervisor.fault
    assert arm.controller.idle
    np.testing.assert_array_equal(arm.controller.reference.position, before)


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        # Ruckig's result -101 (a duration beyond its limits), unknown to its Python module: was a ValueError in the
        # control cycle, and the arm halted with `exception`
        (lambda a: a.move_to({"base_yaw": 40.0}, speed_scale=1e-5, wait=False), PlanningError, "Ruckig.*-101"),
        (lambda a: a.follow([{"base_yaw": 40.0}], speed_scale=1e-5, wait=False), PlanningError, "-101"),
        # was a handle that moved (the scale is checked when the loop plans, too late to say so)
        (lambda a: a.follow([{"base_yaw": 2.0}], speed_scale=2, wait=False), PlanningError, r"2.0 .*\(0, 1\]"),
        (lambda a: a.move_to({"base_yaw": 2.0}, speed_scale=0.0), PlanningError, r"0.0 .*\(0, 1\]"),
        (lambda a: a.move_to({"base_yaw": 2.0}, speed_scale="0.5"), PlanningError, "'0.5' is not a number"),
        (lambda a: a.move_to({"base_yaw": 2.0}, speed_scale=True), PlanningError, "True is not a number"),
        # was accepted (float("30"))
        (lambda a: a.move_to({"shoulder_pitch": "30"}), PlanningError, r"\['shoulder_pitch'\]: '30' is not a number"),
        (lambda a: a.move_to({"shoulder_pitch": math.nan}), PlanningError, "shoulder_pitch.*not a finite"),
        # was AttributeError: 'list' object has no attribute 'items'
        (lambda a: a.move_to([1.0, 2.0]), PlanningError, "a mapping of joint names to degrees.*got list"),
        (lambda a: a.move_to({"knee": 1.0}), PlanningError, "unknown joint 'knee'; joints: base_yaw"),
        # was numpy's ValueError (inhomogeneous shape)
        (lambda a: a.follow([[0.0] * 6, [1.0, 2.0]]), PlanningError, r"waypoints\[1\]: .*6 angles.*got \[1.0, 2.0\]"),
        (lambda a: a.follow([[0.0] * 5 + ["x"]]), PlanningError, r"waypoints\[0\]\[5\]: 'x' is not a number"),
        (lambda a: a.follow([]), PlanningError, "at least one waypoint"),
        (lambda a: a.follow({"base_yaw": 1.0}), PlanningError, "a list of waypoints is expected, got dict"),
        (lambda a: a.sleep(math.nan), ValueError, "duration_s: nan is not a duration"),
        (lambda a: a.sleep(-1.0), ValueError, "duration_s: -1.0 is not a duration"),
        (lambda a: a.sleep(math.inf), ValueError, "duration_s: inf"),
    ],
    ids=lambda value: value.__name__ if isinstance(value, type) else None,
)
def test_the_api_refuses_odd_arguments_before_anything_is_queued(
    arm: Arm, call: Callable[[Arm], object], error: type[Exception], match: str
) -> None:
    _refused(arm, lambda: call(arm), error, match)


def test_accepted_numbers_of_any_real_type_plan_as_floats(arm: Arm) -> None:
    # numpy's scalars are numbers (np.float32(0.5) was refused as "outside the valid range (0, 1]")
    half: Any = np.float32(0.5)
    two: Any = np.float32(2.0)
    zero: Any = np.int64(0)
    arm.move_to({"base_yaw": two}, speed_scale=half)
    assert arm.positions()["base_yaw"] == pytest.approx(2.0, abs=0.05)
    arm.move_to({"base_yaw": zero}, speed_scale=1)
    assert arm.positions()["base_yaw"] == pytest.approx(0.0, abs=0.05)


def test_a_wait_with_a_nan_timeout_is_refused_and_does_not_run_for_ever(arm: Arm) -> None:
    handle = arm.move_to({"base_yaw": 1.0}, wait=False)
    outcome: list[BaseException] = []

    def wait() -> None:
        try:
            handle.wait(timeout_s=math.nan)
        except BaseException as exc:
            outcome.append(exc)

    # (in simulated time a wait that never ends runs cycles for ever in its thread: a thread, joined with a timeout)
    waiter = threading.Thread(target=wait, daemon=True)
    waiter.start()
    waiter.join(10.0)
    assert not waiter.is_alive() and len(outcome) == 1
    assert isinstance(outcome[0], ValueError) and "timeout_s: nan is not a duration" in str(outcome[0])
    assert handle.wait(timeout_s=5.0)


@pytest.mark.parametrize(
    "message",
    [TorqueControl(1e308), SpeedControl(1e308), MultiTurnPositionSpeed(1e308, 100.0), MultiTurnPositionSpeed(1, 1e308)],
    ids=["torque", "speed", "angle", "max_speed"],
)
@pytest.mark.parametrize("encode", [can_frame.encode_request, rs485_frame.encode_request], ids=["can", "rs485"])
def test_a_value_beyond_every_field_is_an_encode_error(encode: Callable[[Any, int], object], message: Any) -> None:
    # was OverflowError: cannot convert float infinity to integer (1e308 times the field's scale)
    with pytest.raises(EncodeError, match=r"1e\+308 is outside the valid range"):
        encode(message, 1)


@pytest.mark.parametrize("where", ["move", "wait", "speed_scale"])
def test_a_program_with_a_400_digit_number_exits_2_naming_the_key(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, where: str
) -> None:
    huge = "9" * 400
    step = {
        "move": f"  - move: {{shoulder: {huge}}}\n",
        "wait": f"  - wait: {huge}\n",
        "speed_scale": f"  - move: {{shoulder: 10}}\n    speed_scale: {huge}\n",
    }[where]
    program = tmp_path / "program.yaml"
    program.write_text("steps:\n" + step)
    code = main(["run", "--config", "arm2.yaml", "--emulate", str(program)])
    err = capsys.readouterr().err
    assert code == 2, err
    key = {"move": "steps[0].move.shoulder", "wait": "steps[0].wait", "speed_scale": "steps[0].speed_scale"}[where]
    assert key in err and "an integer of 400 digits" in err, err
    assert "Traceback" not in err


_LINK = """<link name="{name}"><inertial><origin xyz="0 0 0.1"/><mass value="{mass}"/>
<inertia ixx="{ixx}" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>"""
_JOINT = """<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>
<origin xyz="0 0 0.1"/><axis xyz="{axis}"/><limit lower="-3" upper="3" effort="10" velocity="3"/></joint>"""


@pytest.mark.parametrize(
    ("mass", "ixx", "axis", "match"),
    [
        ("1.0", "0.01", "0 0 1", None),  # well formed: it builds
        ("-1.0", "0.01", "0 0 1", "link 'upper': mass '-1.0' kg"),  # was gravity 1.5e32 N·m
        ("nan", "0.01", "0 0 1", "link 'upper': mass 'nan' kg"),
        ("1.0", "-0.01", "0 0 1", "link 'upper': inertia ixx='-0.01'"),
        ("1.0", "0.01", "0 0 0", "joint 'elbow': axis '0 0 0'"),  # was a joint gravity never loads
        ("1.0", "0.01", "0 a 1", "joint 'elbow' axis: xyz='0 a 1' is not a list of numbers"),
    ],
)
def test_a_urdf_with_a_negative_mass_or_a_zero_axis_is_refused_naming_it(
    tmp_path: Path, mass: str, ixx: str, axis: str, match: str | None
) -> None:
    urdf = tmp_path / "arm.urdf"
    links = _LINK.format(name="base", mass="1.0", ixx="0.01") + _LINK.format(name="upper", mass=mass, ixx=ixx)
    links += _LINK.format(name="fore", mass="1.0", ixx="0.01")
    joints = _JOINT.format(name="shoulder", parent="base", child="upper", axis="0 1 0")
    joints += _JOINT.format(name="elbow", parent="upper", child="fore", axis=axis)
    urdf.write_text(f'<robot name="arm">{links}{joints}</robot>')
    config = load_config(CONFIGS / "arm2.yaml")  # (its joints are shoulder and elbow)
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, urdf=urdf, chain=()))
    if match is None:
        assert build_arm(config).model.nv == 2
        return
    with pytest.raises(ConfigError, match=r"model\.urdf") as info:
        build_arm(config)
    assert match in str(info.value)
