"""Benchmark of issue 5: CPU time of one control cycle, and the achieved rate and jitter against emulated drives.

Run by hand from the repository root (takes about 1-2 minutes and prints Markdown tables)::

    .venv/bin/python bench/cycle_bench.py            # both parts
    .venv/bin/python bench/cycle_bench.py --part cpu # only the CPU time per cycle
    .venv/bin/python bench/cycle_bench.py --part live --seconds 10

Part 1 (``cpu``) times the controller's own work in a cycle for synthetic arms of 1, 2, 4, 6 and 12 axes in
position and torque mode, with no bus at all: sample the reference, build the batch (torque mode: PD + Pinocchio
feed-forward + current limiting), encode the CAN frames, absorb pre-built replies. It also times the whole
``Controller.cycle`` on the real :class:`~motion.transport.can_transport.CanTransport` whose python-can bus is
replaced by an instantaneous loopback, which adds the transport's slot matching and the decoding of the replies.

Part 2 (``live``) runs ``rmd-motion emulate`` in another process and the controller's fixed-rate loop in this one,
holding position, and prints the loop statistics and the transport counters.

Every arm comes from a configuration mapping generated here (a chain of N revolute links with masses and inertias)
and validated by :func:`motion.config.parse_config`, so each N goes through the real config -> controller path.
See bench/README.md for what each figure means.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import math
import os
import platform
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import timeit
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import IO, Any, cast

import numpy as np
from numpy.typing import NDArray

from motion.compose import build_controller, feedforward_for, open_bus
from motion.config import ArmConfig, parse_config
from motion.config.schema import ControlMode
from motion.control.controller import Controller, Feedforward
from motion.control.scheduler import LoopStatistics
from motion.emulator import DEFAULT_PID, DriveModel
from motion.emulator.timing import DEFAULT_LATENCY_S, can_frame_bits
from motion.protocol import (
    Acceleration,
    Bare,
    CanFrame,
    Command,
    Message,
    MotorState,
    MultiTurnAngle,
    MultiTurnPositionSpeed,
    Status1,
    TorqueControl,
    can_frame,
    rs485_frame,
)
from motion.protocol.compiled import CODECS, frozen_builder
from motion.protocol.messages import ErrorFlags
from motion.protocol.rs485_frame import rs485_frame_time_s
from motion.protocol.table import (
    CAN_ID_BASE,
    CAN_MULTI_TORQUE_ID,
    MULTI_TORQUE_MOTOR_IDS,
    Direction,
    WireProtocol,
)
from motion.trajectory import State
from motion.transport.base import MotorCounters, Reply, Transport
from motion.transport.can_transport import CanTransport

AXES = (1, 2, 4, 6, 12)
MODES = (ControlMode.POSITION, ControlMode.TORQUE)
CAN_BITRATE = 1_000_000
RS485_BAUD = 115_200
#: Encoder resolution of the drives ``rmd-motion emulate`` runs by default.
EMULATE_ENCODER_BITS = 14
#: How long to wait for the emulator process to print its attachment, s.
EMULATOR_START_TIMEOUT_S = 20.0
NS_PER_US = 1000.0
#: Radius of the synthetic arms' links (solid cylinders), m.
LINK_RADIUS_M = 0.03


# ---------------------------------------------------------------------------------------------------- configs


def _axis(i: int) -> list[float]:
    """Joint axes of a typical arm, repeated: yaw, pitch, pitch, roll, pitch, roll."""
    return [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]][i % 6]


def arm_mapping(
    n_axes: int,
    *,
    mode: ControlMode,
    rate_hz: float,
    gear_ratio: float,
    bus: dict[str, object],
) -> dict[str, object]:
    """An arm configuration mapping (what the YAML file would hold): a chain of ``n_axes`` revolute links.

    Links are solid cylinders along z, each 15 % shorter and 20 % lighter than the one before; motor ids are 1..n
    in joint order, every other joint is mounted mirrored (direction -1).
    """
    chain: list[dict[str, object]] = []
    joints: list[dict[str, object]] = []
    offset_m = 0.1  # base height of the first joint
    for i in range(n_axes):
        length_m = 0.30 * 0.85**i
        mass_kg = 2.0 * 0.8**i
        across = mass_kg * (3 * LINK_RADIUS_M**2 + length_m**2) / 12.0  # solid cylinder
        along = mass_kg * LINK_RADIUS_M**2 / 2.0
        chain.append(
            {
                "joint": f"j{i + 1}",
                "origin_xyz_m": [0.0, 0.0, offset_m],
                "origin_rpy_rad": [0.0, 0.0, 0.0],
                "axis": _axis(i),
                "mass_kg": mass_kg,
                "com_xyz_m": [0.0, 0.0, length_m / 2.0],
                "inertia_kgm2": {"ixx": across, "ixy": 0.0, "ixz": 0.0, "iyy": across, "iyz": 0.0, "izz": along},
            }
        )
        offset_m = length_m
        joints.append(
            {
                "name": f"j{i + 1}",
                "motor_id": i + 1,
                "gear_ratio": gear_ratio,
                "direction": 1 if i % 2 == 0 else -1,
                "zero_offset_deg": 0.0,
                "torque_constant_nm_per_a": 0.1,
                "current_limit_a": 20.0,
                "encoder_bits": EMULATE_ENCODER_BITS,
                "position_min_deg": -150.0,
                "position_max_deg": 150.0,
                "velocity_limit_dps": 90.0,
                "acceleration_limit_dps2": 360.0,
                "jerk_limit_dps3": 3000.0,
                "kp_nm_per_deg": 0.5,
                "kd_nm_per_dps": 0.02,
                "temperature_limit_c": 70.0,
            }
        )
    return {
        "name": f"bench{n_axes}",
        "bus": bus,
        "control": {
            "halt_policy": "hold",
            "mode": mode.value,
            "rate_hz": rate_hz,
            "gravity_feedforward": True,
            "inertia_feedforward": True,
        },
        "model": {"gravity_m_s2": [0.0, 0.0, -9.81], "chain": chain, "tip_xyz_m": [0.0, 0.0, offset_m]},
        "safety": {"following_error_deg": 5.0, "min_voltage_v": 20.0},
        "joints": joints,
    }


def can_bus_mapping(channel: str = "bench", interface: str = "virtual") -> dict[str, object]:
    """A ``bus:`` section for CAN at 1 Mbit/s."""
    return {"transport": "can", "interface": interface, "channel": channel, "bitrate": CAN_BITRATE}


def rs485_bus_mapping(port: str) -> dict[str, object]:
    """A ``bus:`` section for RS485 at 115200 baud."""
    return {"transport": "rs485", "port": port, "baudrate": RS485_BAUD}


def synthetic_config(
    n_axes: int,
    *,
    mode: ControlMode = ControlMode.POSITION,
    rate_hz: float = 1000.0,
    gear_ratio: float = 9.0,
    bus: dict[str, object] | None = None,
) -> ArmConfig:
    """A validated :class:`ArmConfig` for a synthetic ``n_axes`` arm (see :func:`arm_mapping`)."""
    mapping = arm_mapping(
        n_axes, mode=mode, rate_hz=rate_hz, gear_ratio=gear_ratio, bus=bus if bus is not None else can_bus_mapping()
    )
    return parse_config(mapping, source=f"<bench arm of {n_axes} axes>")


# ---------------------------------------------------------------------------------------------------- part 0


@dataclass(frozen=True)
class CodecRow:
    """One frame through the codec against the bare struct of the same bytes, ns per call (best of the repeats)."""

    what: str
    codec_ns: float
    fast_path_ns: float
    bare_ns: float
    object_ns: float

    @property
    def object_ratio(self) -> float:
        """What building the object the codec hands back costs alone, against the bare struct."""
        return self.object_ns / self.bare_ns

    @property
    def ratio(self) -> float:
        return self.codec_ns / self.bare_ns


def _best_ns(statements: Sequence[str], names: dict[str, object], number: int, repeat: int) -> list[float]:
    """ns per call of each statement, best of ``repeat`` rounds; the statements take turns within each round, so
    that a busy moment of the machine falls on all of them alike."""
    timers = [timeit.Timer(statement, globals=names) for statement in statements]
    best = [math.inf] * len(timers)
    for _ in range(repeat):
        for i, timer in enumerate(timers):
            best[i] = min(best[i], timer.timeit(number) / number * 1e9)
    return best


#: Part 0's frames: the control cycle's requests and replies (and a reply with an enum of flags).
CODEC_CASES: tuple[tuple[str, Direction, Message], ...] = (
    ("encode 0xA4 request (position)", Direction.REQUEST, MultiTurnPositionSpeed(123.45, 270.0)),
    ("encode 0xA1 request (torque)", Direction.REQUEST, TorqueControl(1.25)),
    ("decode 0xA4 reply (state)", Direction.REPLY, MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, 0.416, -12, 1234)),
    ("decode 0x9A reply (status 1)", Direction.REPLY, Status1(Command.READ_STATUS_1, 35, 24.1, ErrorFlags.NONE)),
)


def run_codec(number: int = 10_000, repeat: int = 15) -> list[CodecRow]:
    """Part 0: ``can_frame.encode_request`` / ``decode_reply`` of the control cycle's frames against a bare
    precompiled ``struct.Struct`` packing the same raw values into the same bytes / unpacking the same bytes.

    The codec's own fast path (the compiled encoder / decoder of :mod:`motion.protocol.compiled`, without the
    frame around it) is timed as well. Every statement is timed the same way (``timeit``, best of ``repeat`` rounds
    in which they take turns).
    """
    rows: list[CodecRow] = []
    for what, direction, message in CODEC_CASES:
        request = direction is Direction.REQUEST
        frame = (can_frame.encode_request if request else can_frame.encode_reply)(message, 3)
        layout = CODECS[WireProtocol.CAN, direction].layouts[frame.data[0]]
        assert layout is not None
        bare = struct.Struct(layout.packer.format)  # the same layout, built here: the baseline
        raw = bare.unpack(frame.data)
        assert bare.pack(*raw) == frame.data
        assert can_frame.decode_reply(frame.arbitration_id, frame.data)[1] == message or request
        names = {
            "encode": can_frame.encode_request,
            "decode": can_frame.decode_reply,
            "fast_encode": layout.encode,
            "fast_decode": layout.decode,
            "m": message,
            "i": frame.arbitration_id,
            "d": frame.data,
            "pack": bare.pack,
            "unpack": bare.unpack,
            "raw": raw,
            # the object the codec hands back, built from ready values by the fastest constructor (slots set directly)
            "new_frame": frozen_builder(CanFrame),
            "new_message": frozen_builder(message.__class__),
            "values": tuple(getattr(message, f.name) for f in dataclasses.fields(message)),
        }
        statements = (
            ("encode(m, 3)", "fast_encode(m)", "pack(*raw)", "new_frame(i, d)")
            if request
            else ("decode(i, d)", "fast_decode(d)", "unpack(d)", "new_message(*values)")
        )
        rows.append(CodecRow(what, *_best_ns(statements, names, number, repeat)))
    return rows


def print_codec(rows: Sequence[CodecRow]) -> None:
    """Print the part 0 table (Markdown)."""
    print("\n### 0. One CAN frame through the codec against the bare `struct` of the same bytes, ns per call\n")
    print(
        "| frame | `can_frame` codec | the compiled fast path alone | bare `struct.Struct` "
        "| **codec / bare** | the object it returns, built alone (frame / message) | object alone / bare |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r.what} | {r.codec_ns:.0f} | {r.fast_path_ns:.0f} | {r.bare_ns:.0f} "
            f"| **{r.ratio:.1f}x** | {r.object_ns:.0f} | {r.object_ratio:.1f}x |"
        )


# ---------------------------------------------------------------------------------------------------- part 1


def _reply_state(command: Command, motor_id: int) -> MotorState:
    """What a drive holding still would answer (encoder values differ per motor so that nothing is trivially 0)."""
    return MotorState(command, 31, 0.42, 0, (1000 * motor_id) % (1 << EMULATE_ENCODER_BITS))


def _replies_to(frame: CanFrame) -> tuple[CanFrame, ...]:
    """The reply frames emulated drives send to one request frame."""
    if frame.arbitration_id == CAN_MULTI_TORQUE_ID:
        return tuple(can_frame.encode_reply(_reply_state(Command.TORQUE, m), m) for m in MULTI_TORQUE_MOTOR_IDS)
    motor_id = frame.arbitration_id - CAN_ID_BASE
    command = Command(frame.data[0])
    reply: Message
    if command is Command.READ_MULTI_TURN_ANGLE:
        reply = MultiTurnAngle(0.0)
    elif command is Command.READ_PID:  # read at connect for the following-error check's model
        reply = DEFAULT_PID
    elif command is Command.READ_ACCELERATION:
        reply = Acceleration(command, DriveModel().acceleration_dps2)
    else:
        reply = _reply_state(command, motor_id)
    return (can_frame.encode_reply(reply, motor_id),)


class LoopbackEndpoint:
    """Stands in for python-can: every frame sent is answered at once by canned reply frames (no wire, no thread).

    The replies to a (frame id, command byte) are encoded once and then replayed, so the time spent here is a
    dictionary look-up and a deque, not the drives' work.
    """

    def __init__(self) -> None:
        self._queue: deque[CanFrame] = deque()
        self._canned: dict[tuple[int, int], tuple[CanFrame, ...]] = {}
        self.interface = "loopback"
        self.channel = "bench"

    def send(self, frame: CanFrame, timeout_s: float | None = None) -> None:
        """Queue the replies to ``frame``."""
        key = (frame.arbitration_id, frame.data[0])
        replies = self._canned.get(key)
        if replies is None:
            replies = self._canned[key] = _replies_to(frame)
        self._queue.extend(replies)

    def recv(self, timeout_s: float | None) -> tuple[CanFrame, float] | None:
        """The next queued reply, or None at once."""
        return (self._queue.popleft(), 0.0) if self._queue else None

    def close(self) -> None:
        """Nothing to release."""


def loopback_transport() -> CanTransport:
    """The real CAN transport (encoding, slot matching, decoding) on an instantaneous loopback instead of a bus."""
    # The only seam between CanTransport and python-can is its port; injecting a loopback keeps every line of the
    # transport's own code in the measurement.
    return CanTransport.over(LoopbackEndpoint())


def _percentile_us(values_ns: Sequence[int] | NDArray[np.int64], q: float) -> float:
    return float(np.percentile(np.asarray(values_ns), q)) / NS_PER_US


@dataclass
class CpuCase:
    """One (axes, mode) case of part 1, its inputs and its samples (ns per cycle, per stage)."""

    n_axes: int
    mode: ControlMode
    controller: Controller
    ff: Feedforward | None
    replies: list[Reply]
    states: list[State]
    base_s: float
    duration_s: float
    frames: int = 0
    reply_frames: int = 0
    wire_us: float = 0.0
    stages: dict[str, list[int]] = field(default_factory=dict)
    cpu_ns: dict[str, int] = field(default_factory=dict)
    cycles: dict[str, int] = field(default_factory=dict)

    def reference_time(self, k: int) -> float:
        """Controller time of sample ``k``: inside the middle 90 % of the planned move, wrapping around."""
        return self.base_s + self.duration_s * (0.05 + 0.9 * (k % 997) / 997)


#: Stages of part 1: the controller's pure parts, their sum, the feed-forward alone, the loopback transact() alone
#: and the whole cycle().
STAGES = ("sample", "build", "encode", "absorb", "controller", "feedforward", "transact", "cycle")
#: A cycle's move goes from 0 to these joint angles (alternating by joint), deg.
MOVE_TARGET_DEG = (60.0, -45.0)


def make_cpu_case(n_axes: int, mode: ControlMode, rate_hz: float) -> CpuCase:
    """The controller of a synthetic arm on the loopback transport, started up and moving.

    The move is planned once and anchored one hour ahead on the monotonic clock, so that the deadlines the cycles
    hand to the transport are never reached (the loopback answers at once anyway) and the reference always moves.
    """
    config = synthetic_config(n_axes, mode=mode, rate_hz=rate_hz)
    ff = feedforward_for(config)  # torque mode: gravity and inertia; position mode: none
    controller = build_controller(config, loopback_transport(), feedforward=ff)
    controller.read_positions()
    follower = controller.follower
    assert follower is not None
    target = [MOVE_TARGET_DEG[i % 2] for i in range(n_axes)]
    base_s = time.monotonic() + 3600.0
    path = follower.move_to(base_s, target)
    states = [path.sample(path.duration_s * (0.05 + 0.9 * i / 255)) for i in range(256)]
    # The replies of one cycle, decoded as the transport hands them over (absorb() is timed on these).
    requests = controller.build_requests(states[0])
    replies = controller.bus.transact(requests, time.monotonic() + 1.0)
    if not all(r.ok for r in replies):
        raise RuntimeError("the loopback left a request unanswered")
    frames = [can_frame.encode_request(r.message, r.motor_id) for r in requests]
    reply_frames = [f for frame in frames for f in _replies_to(frame)]
    wire_bits = sum(can_frame_bits(f.arbitration_id, f.data) for f in frames + reply_frames)
    case = CpuCase(n_axes, mode, controller, ff, replies, states, base_s, path.duration_s)
    case.frames, case.reply_frames = len(frames), len(reply_frames)
    case.wire_us = wire_bits / CAN_BITRATE * 1e6
    case.stages = {name: [] for name in STAGES}
    return case


def run_stage_batch(case: CpuCase, cycles: int, offset: int) -> None:
    """Time ``cycles`` cycles of the controller's pure parts, stage by stage."""
    controller, follower = case.controller, case.controller.follower
    assert follower is not None
    replies, ff, states = case.replies, case.ff, case.states
    encode = can_frame.encode_request
    clock = time.perf_counter_ns
    stages = case.stages
    s_sample, s_build, s_encode, s_absorb = stages["sample"], stages["build"], stages["encode"], stages["absorb"]
    s_total, s_ff = stages["controller"], stages["feedforward"]
    times = [case.reference_time(offset + k) for k in range(cycles)]
    cpu0 = time.process_time_ns()
    for k in range(cycles):
        t0 = clock()
        ref = follower.sample(times[k])
        t1 = clock()
        requests = controller.build_requests(ref)
        t2 = clock()
        for request in requests:
            encode(request.message, request.motor_id)
        t3 = clock()
        controller.absorb(replies)
        t4 = clock()
        s_sample.append(t1 - t0)
        s_build.append(t2 - t1)
        s_encode.append(t3 - t2)
        s_absorb.append(t4 - t3)
        s_total.append(t4 - t0)
    cpu_ns = time.process_time_ns() - cpu0
    if ff is not None:  # the feed-forward alone (it also runs inside build above)
        q = controller.axes.q_deg
        for k in range(cycles):
            state = states[(offset + k) % len(states)]
            t5 = clock()
            ff(q, state.velocity, state.acceleration)
            s_ff.append(clock() - t5)
    # transact() alone on the loopback: encoding again, slot plan, sends, reply decoding, matching, Reply objects.
    bus, s_transact, far_s = controller.bus, stages["transact"], time.monotonic() + 3600.0
    requests = controller.build_requests(states[offset % len(states)])
    for _ in range(cycles):
        t6 = clock()
        bus.transact(requests, far_s)
        s_transact.append(clock() - t6)
    case.cpu_ns["controller"] = case.cpu_ns.get("controller", 0) + cpu_ns
    case.cycles["controller"] = case.cycles.get("controller", 0) + cycles


def run_cycle_batch(case: CpuCase, cycles: int, offset: int) -> None:
    """Time ``cycles`` whole ``Controller.cycle`` calls on the loopback transport."""
    controller = case.controller
    period_s = 1.0 / controller.options.rate_hz
    cycle = controller.cycle
    clock = time.perf_counter_ns
    samples = case.stages["cycle"]
    times = [case.reference_time(offset + k) for k in range(cycles)]
    cpu0 = time.process_time_ns()
    for k in range(cycles):
        deadline_s = times[k]
        t0 = clock()
        cycle(offset + k, deadline_s - period_s, deadline_s)
        samples.append(clock() - t0)
    case.cpu_ns["cycle"] = case.cpu_ns.get("cycle", 0) + time.process_time_ns() - cpu0
    case.cycles["cycle"] = case.cycles.get("cycle", 0) + cycles


def run_cpu(cycles: int, rounds: int) -> list[CpuCase]:
    """Part 1: every case, interleaved in ``rounds`` rounds so that machine noise hits every case alike."""
    cases = [make_cpu_case(n, mode, 1000.0) for mode in MODES for n in AXES]
    batch = max(1, cycles // rounds)
    for case in cases:  # warm-up (first calls fill caches), then forget
        run_stage_batch(case, 50, 0)
        run_cycle_batch(case, 50, 0)
        case.stages = {name: [] for name in STAGES}
        case.cpu_ns.clear()
        case.cycles.clear()
    for r in range(rounds):
        for case in cases:
            run_stage_batch(case, batch, r * batch)
            run_cycle_batch(case, batch, r * batch)
    for case in cases:
        if case.controller.bus.counters and any(c.timeouts for c in case.controller.bus.counters.values()):
            raise RuntimeError(f"{case.n_axes} axes {case.mode.value}: the loopback transport timed out")
        case.controller.bus.close()
    return cases


def _fit_per_axis(cases: Sequence[CpuCase], stage: str) -> tuple[float, float]:
    """Least-squares ``p50 = fixed + per_axis * N`` over the cases of one mode, µs."""
    n = np.array([c.n_axes for c in cases], dtype=float)
    p50 = np.array([_percentile_us(c.stages[stage], 50) for c in cases])
    per_axis, fixed = np.polyfit(n, p50, 1)
    return float(fixed), float(per_axis)


def _p50_ratio(a: CpuCase, b: CpuCase, stage: str) -> float:
    return _percentile_us(a.stages[stage], 50) / _percentile_us(b.stages[stage], 50)


def print_cpu(cases: Sequence[CpuCase]) -> None:
    """Print the part 1 tables (Markdown)."""
    print("\n### 1. CPU time of one control cycle, µs (no bus: nothing is waited for)\n")
    print(
        "| axes | mode | frames out / in | wire time @ 1 Mbit/s | sample | build | (FF alone) | encode | absorb "
        "| **controller p50 / p99** | CPU mean | transact() alone | **cycle() p50 / p99** | CPU mean "
        "| **cycle() p50 / wire time** |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for c in cases:
        s = c.stages
        ff = f"{_percentile_us(s['feedforward'], 50):.1f}" if s["feedforward"] else "-"
        cpu_ctrl = c.cpu_ns["controller"] / c.cycles["controller"] / NS_PER_US
        cpu_cycle = c.cpu_ns["cycle"] / c.cycles["cycle"] / NS_PER_US
        print(
            f"| {c.n_axes} | {c.mode.value} | {c.frames} / {c.reply_frames} | {c.wire_us:.0f} "
            f"| {_percentile_us(s['sample'], 50):.1f} | {_percentile_us(s['build'], 50):.1f} | {ff} "
            f"| {_percentile_us(s['encode'], 50):.1f} | {_percentile_us(s['absorb'], 50):.1f} "
            f"| **{_percentile_us(s['controller'], 50):.0f} / {_percentile_us(s['controller'], 99):.0f}** "
            f"| {cpu_ctrl:.0f} | {_percentile_us(s['transact'], 50):.0f} "
            f"| **{_percentile_us(s['cycle'], 50):.0f} / {_percentile_us(s['cycle'], 99):.0f}** | {cpu_cycle:.0f} "
            f"| **{_percentile_us(s['cycle'], 50) / c.wire_us * 100:.1f} %** |"
        )
    print("\nStage columns are p50. Cost per axis: least-squares fit of the p50 over N; 12-axis / 1-axis ratio:\n")
    print("| mode | measured | fixed, µs | per axis, µs | 12 axes / 1 axis |")
    print("|---|---|---:|---:|---:|")
    for mode in MODES:
        mine = [c for c in cases if c.mode is mode]
        for stage in ("controller", "cycle"):
            fixed, per_axis = _fit_per_axis(mine, stage)
            ratio = _percentile_us(mine[-1].stages[stage], 50) / _percentile_us(mine[0].stages[stage], 50)
            print(f"| {mode.value} | {stage} | {fixed:.1f} | {per_axis:.1f} | {ratio:.1f}x |")
    torque = {c.n_axes: c for c in cases if c.mode is ControlMode.TORQUE}
    position = {c.n_axes: c for c in cases if c.mode is ControlMode.POSITION}
    ratios = ", ".join(f"{n}: {_p50_ratio(torque[n], position[n], 'controller'):.1f}x" for n in AXES)
    print(f"\nTorque / position controller p50, by axes: {ratios}")


# ---------------------------------------------------------------------------------------------------- part 2


@dataclass(frozen=True)
class LiveCase:
    """One run of part 2."""

    link: str  # "slcan" or "rs485"
    n_axes: int
    rate_hz: float
    bus_time: bool

    @property
    def label(self) -> str:
        return f"{'CAN (slcan)' if self.link == 'slcan' else 'RS485'}{' --bus-time' if self.bus_time else ''}"


@dataclass
class LiveResult:
    """What one run of part 2 measured."""

    case: LiveCase
    stats: LoopStatistics
    totals: MotorCounters
    complete_share: float
    host_cpu_share: float
    emulator_cpu_share: float
    wire_ms: float
    budget_ms: float
    emulator_report: str
    done_p50_s: float
    done_p99_s: float
    send_us: float
    read_us: float
    error: str | None = None


def emulate_command() -> list[str]:
    """``rmd-motion emulate`` of this interpreter's environment."""
    script = Path(sys.executable).with_name("rmd-motion")
    if script.exists():
        return [str(script), "emulate"]
    found = shutil.which("rmd-motion")
    return [found, "emulate"] if found else [sys.executable, "-m", "motion.emulator"]


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all threads), s; NaN where /proc is missing."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return math.nan
    fields = stat[stat.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextlib.contextmanager
def emulator_process(case: LiveCase, link: Path, log: IO[bytes]) -> Iterator[subprocess.Popen[bytes]]:
    """Run ``rmd-motion emulate`` for ``case`` until the block ends (then SIGTERM, like Ctrl-C)."""
    command = [*emulate_command(), "--ids", f"1-{case.n_axes}", f"--{case.link}-link", str(link)]
    if case.bus_time:
        command.append("--bus-time")
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=log, bufsize=0)
    try:
        assert process.stdout is not None
        fd, seen, end = process.stdout.fileno(), b"", time.monotonic() + EMULATOR_START_TIMEOUT_S
        while b"emulating motors" not in seen:
            remaining = end - time.monotonic()
            if remaining <= 0 or process.poll() is not None:
                raise RuntimeError(f"{' '.join(command)} did not start: {seen.decode(errors='replace')}")
            if select.select([fd], [], [], remaining)[0]:
                seen += os.read(fd, 4096)
        yield process
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _live_wire_ms(controller: Controller, case: LiveCase) -> float:
    """Time one cycle's frames occupy the bus (CAN bits at 1 Mbit/s; RS485 bytes at 115200 baud + reply latency)."""
    requests = controller.build_requests(controller.reference)
    replies = [_reply_state(Command.MULTI_TURN_POSITION_SPEED, r.motor_id) for r in requests]
    if case.link == "slcan":
        bits = 0
        for request, reply in zip(requests, replies, strict=True):
            out = can_frame.encode_request(request.message, request.motor_id)
            back = can_frame.encode_reply(reply, request.motor_id)
            bits += can_frame_bits(out.arbitration_id, out.data) + can_frame_bits(back.arbitration_id, back.data)
        return bits / CAN_BITRATE * 1e3
    seconds = 0.0
    for request, reply in zip(requests, replies, strict=True):
        size = len(rs485_frame.encode_request(request.message, request.motor_id))
        size += len(rs485_frame.encode_reply(reply, request.motor_id))
        seconds += rs485_frame_time_s(size, RS485_BAUD) + DEFAULT_LATENCY_S
    return seconds * 1e3


#: Time a 0x9C reply (the frame slcan_host_costs reads) occupies a 1 Mbit/s CAN bus, stuff bits included, µs.
SLCAN_REPLY_WIRE_US = (
    can_frame_bits(CAN_ID_BASE + 1, can_frame.encode_reply(_reply_state(Command.READ_STATUS_2, 1), 1).data)
    / CAN_BITRATE
    * 1e6
)


def _slcan_reader() -> str:
    """Which slcan reader this process uses (the project's shim while python-can lacks the fix, see slcan_shim)."""
    from motion.transport import slcan_shim  # here: it imports pyserial, which only the live part needs

    release = version("python-can")
    return f"the slcan shim, python-can {release}" if slcan_shim.needs_shim() else f"python-can {release}'s own"


def slcan_host_costs(bus: Transport, n_axes: int, period_s: float, repeats: int = 101) -> tuple[float, float]:
    """What slcan costs this process per frame: (send wall time, read CPU time), µs, medians.

    Sends one status read (0x9C) per drive, sleeps one control period (as the loop waits between cycles, so the
    wake-up and the caches are the loop's), then times taking the replies in (``CanEndpoint.recv``: the slcan
    reader, the parsing, the frame), in this thread's CPU time. A round whose replies had not all arrived after the
    period is left out (it would time a wait, not a read).
    """
    endpoint = cast(CanTransport, bus).port
    frames = [can_frame.encode_request(Bare(Command.READ_STATUS_2), m) for m in range(1, n_axes + 1)]
    sends: list[float] = []
    reads: list[float] = []
    for _ in range(repeats):
        start = time.perf_counter()
        for frame in frames:
            endpoint.send(frame, 0.1)
        sends.append((time.perf_counter() - start) / len(frames))
        time.sleep(period_s)
        cpu0, count = time.thread_time(), 0
        while endpoint.recv(0.0) is not None:
            count += 1
        spent = time.thread_time() - cpu0
        if count == len(frames):
            reads.append(spent / count)
        else:  # the rest of the replies are late: take them in before the next round
            while count < len(frames) and endpoint.recv(0.1) is not None:
                count += 1
    return float(np.median(sends)) * 1e6, float(np.median(reads)) * 1e6 if reads else math.nan


def run_live_case(case: LiveCase, seconds: float) -> LiveResult:
    """Hold position for ``seconds`` at ``case.rate_hz`` against emulated drives in another process."""
    with tempfile.TemporaryDirectory(prefix="rmd-bench-") as tmp:
        link = Path(tmp) / f"{case.link}-link"
        log_path = Path(tmp) / "emulator.log"
        with log_path.open("wb") as log, emulator_process(case, link, log) as process:
            bus_section = can_bus_mapping(str(link), "slcan") if case.link == "slcan" else rs485_bus_mapping(str(link))
            # ``rmd-motion emulate`` drives: gear ratio 1, 14-bit encoders, angle 0 at start; the config matches.
            config = synthetic_config(
                case.n_axes, mode=ControlMode.POSITION, rate_hz=case.rate_hz, gear_ratio=1.0, bus=bus_section
            )
            overrides: dict[str, Any] = (
                {"interface": "slcan", "channel": str(link), "bitrate": CAN_BITRATE, "sleep_after_open": 0}
                if case.link == "slcan"
                else {"port": str(link)}
            )
            with open_bus(config, **overrides) as bus:
                controller = build_controller(config, bus)
                controller.read_positions()
                wire_ms = _live_wire_ms(controller, case)
                complete: list[bool] = []
                done_s: list[float] = []  # scheduled start -> replies absorbed, per cycle

                def record(_controller: Controller, start_s: float, replies: list[Reply]) -> None:
                    done_s.append(time.monotonic() - start_s)
                    complete.append(all(r.ok for r in replies))

                controller.cycle_hooks.append(record)
                host0, emu0, wall0 = time.process_time(), _cpu_seconds(process.pid), time.monotonic()
                controller.start()
                time.sleep(seconds)
                stats = controller.shutdown()
                wall = time.monotonic() - wall0
                host_cpu = (time.process_time() - host0) / wall
                emu_cpu = (_cpu_seconds(process.pid) - emu0) / wall
                error = None if controller.error is None else f"{type(controller.error).__name__}: {controller.error}"
                frame_costs = (
                    slcan_host_costs(bus, case.n_axes, 1.0 / case.rate_hz)
                    if case.link == "slcan"
                    else (math.nan, math.nan)
                )
                totals = MotorCounters()
                for counters in bus.counters.values():
                    totals.sent += counters.sent
                    totals.replied += counters.replied
                    totals.timeouts += counters.timeouts
                    totals.bad_frames += counters.bad_frames
                    totals.stale_frames += counters.stale_frames
        report = " ".join(
            line.strip() for line in log_path.read_text(errors="replace").splitlines() if "requests," in line
        )
    return LiveResult(
        case=case,
        stats=stats,
        totals=totals,
        complete_share=sum(complete) / len(complete) if complete else 0.0,
        host_cpu_share=host_cpu,
        emulator_cpu_share=emu_cpu,
        wire_ms=wire_ms,
        budget_ms=controller.options.reply_budget / case.rate_hz * 1e3,
        emulator_report=report,
        done_p50_s=float(np.percentile(done_s, 50)) if done_s else math.nan,
        done_p99_s=float(np.percentile(done_s, 99)) if done_s else math.nan,
        send_us=frame_costs[0],
        read_us=frame_costs[1],
        error=error,
    )


def live_cases() -> list[LiveCase]:
    """CAN for 2 and 6 axes at 500 Hz and 1 kHz, without and with bus time; RS485 for 2 axes at 100 Hz."""
    cases = [
        LiveCase("slcan", n, rate, bus_time) for bus_time in (False, True) for n in (2, 6) for rate in (500.0, 1000.0)
    ]
    cases += [LiveCase("rs485", 2, 100.0, bus_time) for bus_time in (False, True)]
    return cases


def parse_case(text: str) -> LiveCase:
    """``LINK:AXES@HZ`` with an optional ``+bus-time`` (``slcan:6@500``, ``rs485:2@100+bus-time``)."""
    spec, plus, extra = text.partition("+")
    link, _, rest = spec.partition(":")
    axes, _, rate = rest.partition("@")
    if link not in ("slcan", "rs485") or not axes.isdigit() or not rate or (plus and extra != "bus-time"):
        raise argparse.ArgumentTypeError(f"{text!r}: expected LINK:AXES@HZ[+bus-time], LINK slcan or rs485")
    return LiveCase(link, int(axes), float(rate), bool(plus))


def print_live(results: Sequence[LiveResult]) -> None:
    """Print the part 2 table (Markdown)."""
    print("\n### 2. Achieved rate and jitter against `rmd-motion emulate` in another process (position hold)\n")
    print(
        "| link | axes | target Hz | achieved Hz | jitter p50 / p99 / max, µs | busy p99, µs "
        "| start → replies in, p50 / p99, µs | wire / budget, ms "
        "| overruns (skipped) | sent / replied | timeouts | stale | all replies in time | CPU host / emulator |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in results:
        s, t = r.stats, r.totals
        print(
            f"| {r.case.label} | {r.case.n_axes} | {r.case.rate_hz:g} | {s.achieved_rate_hz:.1f} "
            f"| {s.jitter_p50_s * 1e6:.0f} / {s.jitter_p99_s * 1e6:.0f} / {s.jitter_max_s * 1e6:.0f} "
            f"| {s.busy_p99_s * 1e6:.0f} | {r.done_p50_s * 1e6:.0f} / {r.done_p99_s * 1e6:.0f} "
            f"| {r.wire_ms:.2f} / {r.budget_ms:.1f} "
            f"| {s.overruns} ({s.skipped_cycles}) | {t.sent} / {t.replied} | {t.timeouts} | {t.stale_frames} "
            f"| {r.complete_share * 100:.1f} % | {r.host_cpu_share * 100:.0f} % / {r.emulator_cpu_share * 100:.0f} % |"
        )
    print(
        f"\nHost cost of slcan per frame ({_slcan_reader()}), measured after each CAN run (medians of 101 rounds; "
        f"the replies read one control period after the requests, in this thread's CPU time), against the "
        f"time the reply occupies a 1 Mbit/s bus ({SLCAN_REPLY_WIRE_US:.0f} µs):\n"
    )
    print(
        "| link | axes | target Hz | send, µs wall (tcdrain waits for the emulator to read) | read one reply, µs CPU "
        "| **read CPU / wire time** |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for r in results:
        if r.case.link == "slcan":
            print(
                f"| {r.case.label} | {r.case.n_axes} | {r.case.rate_hz:g} | {r.send_us:.0f} | {r.read_us:.0f} "
                f"| **{r.read_us / SLCAN_REPLY_WIRE_US * 100:.0f} %** |"
            )
    print("\nEmulator's own counts (stderr at exit), and the error that ended a loop early:")
    for r in results:
        ended = f" **loop ended by {r.error}**" if r.error else ""
        print(f"- {r.case.label}, {r.case.n_axes} axes @ {r.case.rate_hz:g} Hz: {r.emulator_report or '(none)'}{ended}")


# ---------------------------------------------------------------------------------------------------- main


def _timer_overhead_ns() -> float:
    clock = time.perf_counter_ns
    samples = []
    for _ in range(10_000):
        t0 = clock()
        samples.append(clock() - t0)
    return float(np.median(samples))


def _machine() -> str:
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    return (
        f"{datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}; {model}, {os.cpu_count()} logical CPUs; "
        f"{platform.system()} {platform.release()}; Python {platform.python_version()}, numpy {np.__version__}, "
        f"pin {version('pin')}, ruckig {version('ruckig')}, python-can {version('python-can')}; load average {load}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its tables; returns the exit code."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument(
        "--part", choices=("all", "codec", "cpu", "live"), default="all", help="what to run (default all)"
    )
    parser.add_argument("--cycles", type=int, default=4000, help="timed cycles per case in part 1 (default 4000)")
    parser.add_argument("--rounds", type=int, default=20, help="interleaved rounds in part 1 (default 20)")
    parser.add_argument("--seconds", type=float, default=5.0, help="loop run time per case in part 2 (default 5)")
    parser.add_argument(
        "--case",
        type=parse_case,
        action="append",
        metavar="LINK:AXES@HZ[+bus-time]",
        help="run only these cases in part 2 (repeatable), e.g. slcan:6@500",
    )
    args = parser.parse_args(argv)
    if args.cycles < args.rounds or args.rounds < 1 or args.seconds <= 0:
        parser.error("need --cycles >= --rounds >= 1 and --seconds > 0")

    print(f"## rmd-motion cycle benchmark\n\n{_machine()}")
    print(f"perf_counter_ns overhead (median of back-to-back calls): {_timer_overhead_ns():.0f} ns")
    codec: list[CodecRow] = []
    cases: list[CpuCase] = []
    results: list[LiveResult] = []
    if args.part in ("all", "codec"):
        codec = run_codec()
        print_codec(codec)
    if args.part in ("all", "cpu"):
        started = time.monotonic()
        cases = run_cpu(args.cycles, args.rounds)
        print_cpu(cases)
        print(f"\n(part 1 took {time.monotonic() - started:.0f} s)")
    if args.part in ("all", "live"):
        started = time.monotonic()
        for case in args.case or live_cases():
            print(f"  running {case.label}, {case.n_axes} axes @ {case.rate_hz:g} Hz ...", file=sys.stderr, flush=True)
            results.append(run_live_case(case, args.seconds))
        print_live(results)
        print(f"\n(part 2 took {time.monotonic() - started:.0f} s)")
    print_ratios(codec, cases, results)
    return 0


def print_ratios(codec: Sequence[CodecRow], cases: Sequence[CpuCase], results: Sequence[LiveResult]) -> None:
    """The ratios of this run that issue 12 sets targets for (codec vs bare struct, host time vs wire time)."""
    print("\n### Ratios of this run\n")
    for row in codec:
        print(
            f"- codec, {row.what}: {row.codec_ns:.0f} ns = **{row.ratio:.1f}x** the bare struct "
            f"({row.bare_ns:.0f} ns); the object it returns, "
            f"built alone: {row.object_ratio:.1f}x"
        )
    for c in cases:
        if c.n_axes in (6, 12):
            p50 = _percentile_us(c.stages["cycle"], 50)
            print(
                f"- cycle() p50, {c.n_axes} axes {c.mode.value}: {p50:.0f} µs = **{p50 / c.wire_us * 100:.1f} %** "
                f"of the {c.wire_us:.0f} µs its frames occupy a 1 Mbit/s bus"
            )
    _print_targets(codec, cases, results)
    for r in results:
        if r.case.link == "slcan" and not math.isnan(r.read_us):
            print(
                f"- slcan, after {r.case.label} {r.case.n_axes} axes @ {r.case.rate_hz:g} Hz: "
                f"{r.read_us:.0f} µs host CPU per received frame = **{r.read_us / SLCAN_REPLY_WIRE_US * 100:.0f} %** "
                f"of its {SLCAN_REPLY_WIRE_US:.0f} µs on the wire; {r.complete_share * 100:.1f} % of cycles complete"
            )


#: Issue 12's targets on the machines of bench/README.md (the slow 2-vCPU machine is ~3.8x slower per cycle).
ENCODE_TARGET_X = 3.0
DECODE_TARGET_X = 5.0
CYCLE_TARGET_US = 30.0  # 6 axes, position mode: <= 7 % of its wire time there
CYCLE_TARGET_WIRE_US = 1450.0  # that case's wire time at 1 Mbit/s (torque mode and 12 axes: the same share of theirs)
SLCAN_TARGET_US = 30.0
COMPLETE_TARGET = 0.99


def _verdict(ok: bool) -> str:
    return "met" if ok else "**not met**"


def _print_targets(codec: Sequence[CodecRow], cases: Sequence[CpuCase], results: Sequence[LiveResult]) -> None:
    """Issue 12's targets against this run's figures (the parts that ran)."""
    if codec:
        encode = [r.ratio for r in codec if r.what.startswith("encode")]
        decode = [r.ratio for r in codec if r.what.startswith("decode")]
        shown = ", ".join(f"{x:.1f}x" for x in encode + decode)
        ok = max(encode) <= ENCODE_TARGET_X and max(decode) <= DECODE_TARGET_X
        limits = f"encode <= {ENCODE_TARGET_X:g}x, decode <= {DECODE_TARGET_X:g}x"
        print(f"- target: codec {limits}: {_verdict(ok)} ({shown})")
    share = CYCLE_TARGET_US / CYCLE_TARGET_WIRE_US  # the same share of the wire time for the other cases
    for c in cases:
        p50 = _percentile_us(c.stages["cycle"], 50)
        if c.n_axes == 6 and c.mode is ControlMode.POSITION:
            ok = p50 <= CYCLE_TARGET_US
            print(f"- target: cycle() p50, 6 axes position <= {CYCLE_TARGET_US:g} µs: {_verdict(ok)} ({p50:.0f} µs)")
        elif c.n_axes in (6, 12):
            limit = share * c.wire_us
            print(
                f"- target (scaled alike: {share * 100:.2f} % of the wire time): cycle() p50, {c.n_axes} axes "
                f"{c.mode.value} <= {limit:.0f} µs: {_verdict(p50 <= limit)} ({p50:.0f} µs)"
            )
    for r in results:
        issue_case = (r.case.n_axes, r.case.rate_hz) in ((6, 500.0), (2, 1000.0))
        if r.case.link == "slcan" and not math.isnan(r.read_us) and not r.case.bus_time and issue_case:
            ok = r.read_us <= SLCAN_TARGET_US and r.complete_share >= COMPLETE_TARGET
            print(
                f"- target: slcan {r.case.n_axes} axes @ {r.case.rate_hz:g} Hz, <= {SLCAN_TARGET_US:g} µs per frame "
                f"and >= {COMPLETE_TARGET * 100:g} % of cycles complete: {_verdict(ok)}"
            )


if __name__ == "__main__":
    sys.exit(main())
