"""The control cycle's hot path (issue 12) computes what the array formulas compute, bit for bit, and the transport's
reused slot plans match replies exactly as a fresh plan would.

The scalar paths (0xA4 set-points, torque PD and current limiting, encoder unwrapping) are checked against the
numpy expressions they replaced; the slot plans against batches of many shapes on the simulated bus (the real
matching code of :class:`~motion.transport.base.Transport`, with emulated drives answering).
"""

from __future__ import annotations

import dataclasses
import uuid
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motion.compose import build_controller, open_bus
from motion.config import load_config
from motion.config.schema import ControlMode
from motion.control.axes import AxisSpec, AxisStates
from motion.control.controller import Controller
from motion.control.setpoints import PositionSetpoints
from motion.emulator import Emulator
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.errors import EncodeError
from motion.protocol import (
    Bare,
    Command,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnAngle,
    MultiTurnPositionSpeed,
    Status1,
    TorqueControl,
)
from motion.trajectory import State
from motion.transmission import ArmTransmission, Transmission
from motion.transport.base import Request
from tests.motion_rig import CONFIGS

FINITE = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)
GEAR = st.sampled_from([1.0, 6.0, 9.0, 36.0, 101.0 / 3.0])
TRANSMISSIONS = st.lists(
    st.builds(
        Transmission,
        gear_ratio=GEAR,
        direction=st.sampled_from([1, -1]),
        zero_offset_deg=st.floats(-180.0, 180.0),
        torque_constant_nm_per_a=st.sampled_from([0.1, 0.23, 1.0 / 3.0]),
        current_limit_a=st.sampled_from([5.0, 15.0, 32.0]),
    ),
    min_size=1,
    max_size=6,
)


def _controller(mode: ControlMode) -> Iterator[Controller]:
    config = load_config(CONFIGS / "arm6.yaml")
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, mode=mode))
    with open_bus(config, interface="virtual", channel=uuid.uuid4().hex, bitrate=None) as bus:
        yield build_controller(config, bus, feedforward=lambda q, qd, qdd: np.sin(q) + 0.01 * qd - 0.001 * qdd)


@pytest.fixture(scope="module")
def position() -> Iterator[Controller]:
    yield from _controller(ControlMode.POSITION)


@pytest.fixture(scope="module")
def torque() -> Iterator[Controller]:
    yield from _controller(ControlMode.TORQUE)


def _states(n: int) -> st.SearchStrategy[State]:
    vector = st.lists(FINITE, min_size=n, max_size=n).map(np.array)
    return st.builds(State, vector, vector, vector)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_position_setpoints_are_the_array_formulas(position: Controller, data: st.DataObject) -> None:
    ref = data.draw(_states(6))
    requests = position.build_requests(ref)
    options, transmission = position.options, position.transmission
    angle = transmission.motor_deg(ref.position)
    speed = np.abs(transmission.motor_rate(ref.velocity)) * options.speed_headroom
    builder = position.builder
    assert isinstance(builder, PositionSetpoints)
    speed += builder.speed_floor_dps
    speed = np.minimum(speed, np.minimum(65535.0, builder.speed_limit_dps))  # the field, the joint's limit
    messages = [r.message for r in requests]
    assert all(isinstance(m, MultiTurnPositionSpeed) for m in messages)
    assert [m.angle_deg for m in messages] == angle.tolist()  # type: ignore[attr-defined]
    assert [m.max_speed_dps for m in messages] == speed.tolist()  # type: ignore[attr-defined]
    assert position.setpoints.motor_angle_deg.tolist() == angle.tolist()
    assert position.setpoints.max_speed_dps.tolist() == speed.tolist()
    assert [r.motor_id for r in requests] == list(position.ids)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_torque_setpoints_are_the_array_formulas(torque: Controller, data: st.DataObject) -> None:
    ref = data.draw(_states(6))
    axes = torque.axes
    axes.q_deg[:] = data.draw(st.lists(FINITE, min_size=6, max_size=6))
    axes.qd_dps[:] = data.draw(st.lists(FINITE, min_size=6, max_size=6))
    requests = torque.build_requests(ref)
    tau = torque.kp * (ref.position - axes.q_deg) + torque.kd * (ref.velocity - axes.qd_dps)
    assert torque.feedforward is not None
    tau += torque.feedforward(axes.q_deg, ref.velocity, ref.acceleration)
    assert torque.torque_nm.tolist() == tau.tolist()
    raw, limited = _iq_raw_limited_reference(torque.transmission, tau)
    assert torque.limited.tolist() == limited.tolist()
    multi = next(r.message for r in requests if isinstance(r.message, MultiMotorTorque))
    singles = {r.motor_id: r.message for r in requests if isinstance(r.message, TorqueControl)}
    amps = (raw * 32 / 2000).tolist()
    assert [multi.iq1_a, multi.iq2_a, multi.iq3_a, multi.iq4_a] == amps[:4]
    assert [singles[5].iq_a, singles[6].iq_a] == amps[4:]


def _iq_raw_limited_reference(arm: ArmTransmission, torque: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The array form the per-joint loop replaced: rint, limit, clip."""
    nm_per_a = np.array([t.nm_per_a for t in arm.transmissions])
    limit = np.array([t.iq_raw_limit for t in arm.transmissions], dtype=float)
    raw = np.rint(torque / nm_per_a * (2000 / 32))
    limited = np.abs(raw) > limit
    return np.clip(raw, -limit, limit).astype(np.int64), limited


@settings(max_examples=300, deadline=None)
@given(transmissions=TRANSMISSIONS, data=st.data())
def test_iq_raw_limited_is_the_array_form(transmissions: list[Transmission], data: st.DataObject) -> None:
    arm = ArmTransmission(transmissions)
    n = len(transmissions)
    torque = np.array(data.draw(st.lists(st.floats(-500.0, 500.0), min_size=n, max_size=n)))
    raw, limited = arm.iq_raw_limited(torque)
    expected_raw, expected_limited = _iq_raw_limited_reference(arm, torque)
    assert raw.dtype == np.int64 and raw.tolist() == expected_raw.tolist()
    assert limited.tolist() == expected_limited.tolist()
    assert arm.iq_raw_limited_list(torque.tolist()) == (expected_raw.tolist(), expected_limited.tolist())


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_iq_raw_limited_names_the_joint_of_a_torque_that_is_not_finite(bad: float) -> None:
    arm = ArmTransmission([Transmission(9.0, 1, 0.0, 0.1)] * 3, names=("a", "b", "c"))
    with pytest.raises(EncodeError, match="joint b"):
        arm.iq_raw_limited_list([1.0, bad, 2.0])


@settings(max_examples=100, deadline=None)
@given(
    transmissions=TRANSMISSIONS,
    bits=st.sampled_from([12, 14, 16, 18]),
    data=st.data(),
)
def test_absorb_is_the_array_arithmetic(transmissions: list[Transmission], bits: int, data: st.DataObject) -> None:
    n = len(transmissions)
    arm = ArmTransmission(transmissions)
    axes = AxisStates([AxisSpec(f"j{i}", i + 1, bits) for i in range(n)], arm)
    counts = float(1 << min(bits, 16))
    encoder = np.zeros(n, dtype=np.int64)
    motor_deg = np.array(data.draw(st.lists(st.floats(-1e4, 1e4), min_size=n, max_size=n)))
    speed = np.zeros(n)  # the last reported speeds, and when (NaN: the anchor's, nothing to predict from)
    last_s = np.full(n, np.nan)
    for i in range(n):
        axes.initialise(i, float(motor_deg[i]), 0)
    for cycle in range(data.draw(st.integers(1, 20))):
        # Some axes answer with a MotorState, some with something else, some not at all.
        replies = []
        answered = []
        for i in range(n):
            kind = data.draw(st.sampled_from(["state", "state", "other", "none"]))
            state = MotorState(
                Command.TORQUE,
                data.draw(st.integers(-128, 127)),
                data.draw(st.integers(-2000, 2000)) * 32 / 2000,
                data.draw(st.integers(-32768, 32767)),
                data.draw(st.integers(0, int(counts) - 1)),
            )
            message = {"state": state, "other": MultiTurnAngle(1.0), "none": None}[kind]
            replies.append((i + 1, Bare(Command.READ_STATUS_2), message, 0.5 * cycle if message else None))
            if kind == "state":
                answered.append((i, state))
        axes.absorb(replies)
        fresh = np.zeros(n, dtype=bool)
        for i, state in answered:  # the array arithmetic the per-axis loop replaced
            delta = state.encoder - int(encoder[i])
            since_s = 0.5 * cycle - last_s[i]
            # the way round the speeds at both ends predict
            expected = 0.0 if np.isnan(since_s) else (speed[i] + state.speed_dps) * since_s * counts / 720.0
            delta -= round((delta - expected) / counts) * int(counts)
            speed[i], last_s[i] = float(state.speed_dps), 0.5 * cycle
            encoder[i] = state.encoder
            motor_deg[i] += delta * 360.0 / np.float64(counts)
            fresh[i] = True
            t = transmissions[i]
            assert axes.q_deg[i] == t.joint_deg(float(motor_deg[i]))
            assert axes.qd_dps[i] == t.joint_rate(float(state.speed_dps))
            assert (axes.iq_a[i], axes.temperature_c[i]) == (state.iq_a, state.temperature_c)
            assert axes.last_reply_s[i] == 0.5 * cycle
        assert axes.motor_deg.tolist() == motor_deg.tolist()
        assert axes.encoder.tolist() == encoder.tolist()
        assert axes.fresh.tolist() == fresh.tolist()


# --- slot plans ----------------------------------------------------------------------------------------------


def _batch(shape: int) -> list[Request]:
    """One of many batch shapes: set-points for a rotating subset, status reads, repeated keys, the 0x280 frame."""
    requests = [Request(m, MultiTurnPositionSpeed(float(shape), 100.0)) for m in (5, 6, 7) if shape % m]
    requests.append(Request(1 + shape % 7, Bare(Command.READ_STATUS_1)))
    if shape % 3 == 0:
        requests.append(Request(2, Bare(Command.READ_STATUS_2)))
        requests.append(Request(2, Bare(Command.READ_STATUS_2)))  # the same key twice: answered first-in, first-out
    if shape % 4 == 0:
        requests.append(Request(1, MultiMotorTorque(0.0, 0.0, 0.0, 0.0)))
    return requests


def test_reused_slot_plans_match_every_reply_to_its_request() -> None:
    emulator = Emulator(range(1, 8))
    simulation = Simulation(emulator)
    with SimulatedBus(simulation) as bus:
        for cycle in range(300):  # more shapes than a transport keeps plans for, each one seen several times
            requests = _batch(cycle % 97)
            replies = bus.transact(requests, simulation.now_s + 0.01)
            expected: list[tuple[int, Message, type[Message]]] = []
            for request in requests:
                if isinstance(request.message, MultiMotorTorque):
                    expected += [(m, request.message, MotorState) for m in (1, 2, 3, 4)]
                else:
                    kind = Status1 if request.message == Bare(Command.READ_STATUS_1) else MotorState
                    expected.append((request.motor_id, request.message, kind))
            assert [(r.motor_id, r.request, type(r.message)) for r in replies] == expected, f"cycle {cycle}"
            assert all(r.received_s is not None for r in replies)
            simulation.sleep_until(simulation.now_s + 0.001)
        for motor_id, counters in bus.counters.items():
            assert counters.sent == counters.replied > 0, motor_id
            assert (counters.timeouts, counters.stale_frames, counters.bad_frames) == (0, 0, 0), motor_id
        assert len({tuple(_batch(k)) for k in range(97)}) > 64  # the plan cache was emptied on the way
