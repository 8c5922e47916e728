"""Telemetry (issue 7): the per-cycle log, the bus traces, the plot and the demo, on emulated arms."""

from __future__ import annotations

import dataclasses
import io
import json
import re
from pathlib import Path

import can
import numpy as np
import pytest
from matplotlib.image import imread
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from motion import demo
from motion.api import Arm
from motion.config import load_config
from motion.control.controller import Controller
from motion.demo import run_demo
from motion.plot import figure, plot_log
from motion.protocol import MultiTurnPositionSpeed, TorqueControl, can_frame, rs485_frame
from motion.protocol.table import ProtocolFamily
from motion.telemetry import (
    CYCLE_COLUMNS,
    FAULT_COLUMNS,
    BusTrace,
    Recorder,
    TelemetryLog,
    TelemetryOptions,
    TelemetrySession,
    load_log,
)
from motion.transport import Reply

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
CANDUMP_LINE = re.compile(r"^\(\d+\.\d{6}\) can0 [0-9A-F]{3}#[0-9A-F]{16} [TR]$")


@dataclasses.dataclass
class PositionRun:
    log: TelemetryLog
    in_memory: TelemetryLog
    small_chunks: TelemetryLog
    trace: Path
    positions: dict[str, float]
    reference_deg: np.ndarray
    seen: list[tuple[float, np.ndarray, np.ndarray]]
    t0_s: float


#: Words that name a telemetry field measuring the host's own time (not reproducible across runs).
HOST_TIME_WORDS = ("busy", "wall", "cpu", "host")


@pytest.fixture(scope="module")
def position_run(tmp_path_factory: pytest.TempPathFactory) -> PositionRun:
    """arm6 in position mode: a move, an E-stop, a few halted cycles; recorded, plus our own hook's view."""
    out = tmp_path_factory.mktemp("position")
    seen: list[tuple[float, np.ndarray, np.ndarray]] = []

    def watch(controller: Controller, start_s: float, replies: list[Reply]) -> None:
        seen.append((start_s, controller.axes.q_deg.copy(), controller.reference.position.copy()))

    options = TelemetryOptions(log=out / "run.mcap", trace=out / "run.log")
    with Arm.from_config(CONFIGS / "arm6.yaml", emulate=True, telemetry=options) as arm:
        assert arm.controller is not None and arm.telemetry is not None and arm.telemetry.recorder is not None
        small = Recorder(arm.controller, arm.supervisor, chunk_rows=7)
        arm.controller.cycle_hooks.extend([small, watch])
        arm.move_to({"base_yaw": 10.0, "wrist_roll": -15.0, "flange_roll": 20.0})
        arm.stop()
        arm.sleep(0.1)
        t0_s = arm.telemetry.recorder.t0_s
    small.detach()
    small.finish()
    assert arm.telemetry.result is not None
    return PositionRun(
        load_log(options.log),  # type: ignore[arg-type]
        arm.telemetry.result,
        small.log(),
        out / "run.log",
        arm.positions(),
        arm.controller.reference.position.copy(),
        seen,
        t0_s,
    )


def test_log_has_every_column_with_its_shape_dtype_and_unit(position_run: PositionRun) -> None:
    log = position_run.log
    assert set(log.columns) == set(CYCLE_COLUMNS) | set(FAULT_COLUMNS)
    n, joints = log.cycles, len(log.joint_names)
    assert joints == 6 and n > 100
    for name, (per_joint, dtype, unit) in CYCLE_COLUMNS.items():
        assert log[name].shape == ((n, joints) if per_joint else (n,)), name
        assert log[name].dtype == dtype, name
        assert log.meta["units"][name] == unit
    assert log.joint_names == [j.name for j in load_config(CONFIGS / "arm6.yaml").joints]
    assert [j["motor_id"] for j in log.meta["joints"]] == [1, 2, 3, 4, 5, 6]
    meta = log.meta
    assert (meta["config"], meta["mode"], meta["transport"], meta["channel"]) == ("arm6", "position", "can", "can0")
    assert meta["emulated"] is True and meta["period_s"] == pytest.approx(1 / 250)
    assert meta["following_error_limit_deg"] == 4.0 and meta["trace"] == "run.log"
    assert meta["loop"]["cycles"] >= n and meta["counters"]["1"]["replied"] > n
    for name in log.columns:  # what was written is what was recorded
        assert np.array_equal(log[name], position_run.in_memory[name], equal_nan=log[name].dtype.kind == "f"), name


def test_log_values_are_what_the_controller_saw(position_run: PositionRun) -> None:
    log = position_run.log
    last = log["q_deg"][-1]
    assert np.array_equal(last, np.array(list(position_run.positions.values())))
    assert np.array_equal(log["q_ref_deg"][-1], position_run.reference_deg)
    rows = {float(t): k for k, t in enumerate(log["t_s"])}
    assert len(position_run.seen) > 100
    for start_s, q, ref in position_run.seen:  # our own hook, appended after the recorder, cycle by cycle
        k = rows[start_s - position_run.t0_s]
        assert np.array_equal(log["q_deg"][k], q)
        assert np.array_equal(log["q_ref_deg"][k], ref)
    # a recorder attached later, with chunk boundaries every 7 rows, records the same rows from then on
    small = position_run.small_chunks
    first = int(np.nonzero(log["cycle"] == small["cycle"][0])[0][0])
    assert small.cycles > 50
    for name in CYCLE_COLUMNS:
        expected, got = log[name][first : first + small.cycles], small[name]
        if name == "t_s":  # its own time zero
            expected, got = expected + log.meta["t0_s"], got + small.meta["t0_s"]
            assert np.allclose(got, expected, rtol=0, atol=1e-9)
            continue
        if name == "latency_s":  # measured when each hook runs: the later one later
            assert (got >= expected).all()
            continue
        if name == "busy_s":  # its last row was completed by its own finish()
            expected, got = expected[:-1], got[:-1]
        assert np.array_equal(got, expected, equal_nan=expected.dtype.kind == "f"), name


def test_log_timing_commands_and_faults(position_run: PositionRun) -> None:
    log = position_run.log
    t = log["t_s"]
    assert (np.diff(t) > 0).all()
    steps = np.diff(t) / log.period_s
    assert np.allclose(steps, np.round(steps), atol=1e-6)  # absolute deadlines: on the grid
    assert np.isfinite(log["jitter_s"]).all() and (log["jitter_s"] >= 0).all()
    assert (log["latency_s"] > 0).all()
    active = log.active_rows()
    # busy is known for every cycle followed by a recorded one: not for the E-stop's detection cycle (its check
    # raised before the cycle's exchange, so no row) nor the last cycle
    assert np.isfinite(log["busy_s"][active][:-1]).all() and np.isfinite(log["busy_s"][~active][:-1]).all()
    # one fault: the E-stop, after which only status reads went out
    assert list(log["fault_kind"]) == ["stop"] and list(log["fault_action"]) == ["MOTOR_STOP"]
    assert log["fault_joint"][0] == "" and log["fault_halt_s"][0] >= log["fault_t_s"][0]
    assert active.sum() > 100 and not active[-1]
    commanded = ~np.isnan(log["cmd_angle_deg"]).any(axis=1)
    assert np.array_equal(commanded, active)
    transmission = load_config(CONFIGS / "arm6.yaml").transmission()
    motor = np.array([transmission.motor_deg(row) for row in log["q_ref_deg"][active]])
    assert np.allclose(log["cmd_angle_deg"][active], motor, atol=1e-9)
    assert (log["cmd_speed_dps"][active] > 0).all()
    assert np.isnan(log["cmd_torque_nm"]).all() and not log["limited"].any()
    assert log["fresh"][active].mean() > 0.95  # a reply now and then misses its cycle
    error = np.abs(log.following_error_deg()[active])
    assert 0.0 < error.max() < 4.0
    # the expected position is recorded; the drives trail the reference by more than they trail it (issue 18)
    assert np.array_equal(log.following_error_deg(), log["q_exp_deg"] - log["q_deg"])
    assert np.abs(log.lag_deg()[active]).max() > 3 * error.max()


def test_candump_trace_is_read_by_python_can_and_holds_the_0xa4_stream(position_run: PositionRun) -> None:
    lines = position_run.trace.read_text().splitlines()
    assert all(CANDUMP_LINE.match(line) for line in lines), lines[:3]
    messages = list(can.LogReader(position_run.trace))
    assert len(messages) == len(lines)
    assert all(m.dlc == 8 and not m.is_extended_id and m.channel == "can0" for m in messages)
    stamps = np.array([m.timestamp for m in messages])
    assert (np.diff(stamps) >= 0).all()
    assert abs(stamps[0] - position_run.log.meta["t0_wall_unix_s"]) < 1.0
    sent = [m for m in messages if not m.is_rx]
    a4 = [m for m in sent if m.data[0] == 0xA4]
    log = position_run.log
    commanded_cycles = int(log.active_rows().sum())
    assert len(a4) == commanded_cycles * 6  # one 0xA4 per joint in every cycle that commanded
    assert {m.arbitration_id for m in a4} == set(range(0x141, 0x147))
    for j in range(6):  # the last set-point on the bus is the last one in the log
        last = [m for m in a4 if m.arbitration_id == 0x141 + j][-1]
        request = can_frame.decode_request(last.arbitration_id, bytes(last.data))
        assert isinstance(request.message, MultiTurnPositionSpeed)
        final = log["cmd_angle_deg"][log.active_rows()][-1, j]
        assert request.message.angle_deg == pytest.approx(final, abs=0.005)
    replies = [m for m in messages if m.is_rx]
    assert sum(m.data[0] == 0xA4 for m in replies) >= len(a4) - 12  # the drives answer (a few late at most)
    assert any(m.data[0] == 0x81 for m in sent)  # the E-stop


def test_rs485_hex_trace_and_torque_columns(tmp_path: Path) -> None:
    options = TelemetryOptions(log=tmp_path / "rs485.mcap", trace=tmp_path / "rs485.txt")
    with Arm.from_config(CONFIGS / "arm2_rs485.yaml", emulate=True, telemetry=options) as arm:
        arm.sleep(0.3)
    log = load_log(tmp_path / "rs485.mcap")
    assert log.meta["mode"] == "torque" and log.meta["transport"] == "rs485" and log.cycles > 10
    active = log.active_rows()
    assert np.isfinite(log["cmd_torque_nm"][active]).all() and np.isnan(log["cmd_angle_deg"]).all()
    torque_requests = 0
    for line in (tmp_path / "rs485.txt").read_text().splitlines():
        stamp, direction, *octets = line.split(" ")
        assert re.fullmatch(r"\(\d+\.\d{6}\)", stamp) and direction in {"T", "R"}
        raw = bytes(int(octet, 16) for octet in octets)
        if direction == "T":
            _, message = rs485_frame.decode_request(raw)
            torque_requests += isinstance(message, TorqueControl)
    assert torque_requests == int(active.sum()) * 2  # one 0xA1 per joint in every cycle that commanded


def test_bus_trace_across_chunks() -> None:
    trace = BusTrace(chunk_frames=3)
    frames = [(0.5 + k, k % 2 == 1, 0x141 + k, bytes([0xA4, k, 0, 0, 0, 0, 0, 0])) for k in range(7)]
    for frame in frames:
        trace(*frame)
    trace(10.0, True, None, b"\x3e\x9c")
    assert len(trace) == 8
    assert [tuple(f) for f in trace][:7] == [(*frame, 0) for frame in frames]
    text = io.StringIO()
    trace.write_candump(text, "vcan 1")
    lines = text.getvalue().splitlines()
    assert lines[0] == "(0.500000) vcan_1 141#A400000000000000 T" and len(lines) == 7
    assert lines[1].endswith(" R")
    text = io.StringIO()
    trace.write_hex(text)
    assert text.getvalue().splitlines()[-1] == "(10.000000) R 3E 9C"


def test_a_bus_trace_keeps_each_frames_bus() -> None:
    # an arm of several buses: the tap of each bus records its frames as that bus's, and the files name it
    trace = BusTrace(chunk_frames=2)
    left, right = trace.on_bus(0), trace.on_bus(1)
    left(0.5, False, 0x141, b"\xa4")
    right(0.6, False, 0x141, b"\xa4")
    right(0.7, True, 0x141, b"\x9c")
    trace(0.8, True, None, b"\x3e")
    assert [(f.time_s, f.bus) for f in trace] == [(0.5, 0), (0.6, 1), (0.7, 1), (0.8, 0)]
    text = io.StringIO()
    trace.write_candump(text, ["left", "right arm"])
    assert text.getvalue().splitlines() == [
        "(0.500000) left 141#A4 T",
        "(0.600000) right_arm 141#A4 T",
        "(0.700000) right_arm 141#9C R",
    ]
    text = io.StringIO()
    trace.write_hex(text, ["left", "right"])  # (buses of both transports: the CAN frames as candump lines among them)
    assert text.getvalue().splitlines()[1:] == [
        "(0.600000) right 141#A4 T",
        "(0.700000) right 141#9C R",
        "(0.800000) left R 3E",
    ]


def test_plot_draws_the_log(position_run: PositionRun, tmp_path: Path) -> None:
    log = position_run.log
    fig = figure(log)
    joints = len(log.joint_names)
    assert len(fig.axes) == 5 * joints + 1
    error = log.following_error_deg()
    for j in range(joints):
        position, velocity, current, following, collision = fig.axes[5 * j : 5 * j + 5]
        assert np.array_equal(position.lines[0].get_xdata(), log["t_s"] + log.period_s)
        assert np.array_equal(position.lines[0].get_ydata(), log["q_ref_deg"][:, j])
        assert np.array_equal(position.lines[1].get_ydata(), log["q_deg"][:, j])
        assert np.array_equal(position.lines[2].get_ydata(), log["q_exp_deg"][:, j])
        assert np.array_equal(velocity.lines[1].get_ydata(), log["qd_dps"][:, j])
        assert np.array_equal(current.lines[0].get_ydata(), log["iq_a"][:, j])
        assert np.array_equal(following.lines[0].get_ydata(), error[:, j])
        # the following-error limit, then the E-stop
        assert [np.asarray(line.get_ydata())[0] for line in following.lines[1:3]] == [4.0, -4.0]
        assert np.asarray(following.lines[3].get_xdata())[0] == log["fault_t_s"][0]
        assert np.array_equal(collision.lines[0].get_ydata(), log["collision_signal_nm"][:, j], equal_nan=True)
        assert np.array_equal(collision.lines[1].get_ydata(), log["residual_nm"][:, j], equal_nan=True)
        # the threshold in force, cycle by cycle: never below the configured one, above it where the bound is
        in_force = log["collision_limit_nm"][:, j]
        assert np.array_equal(collision.lines[2].get_ydata(), in_force, equal_nan=True)
        configured = log.meta["collision_threshold_nm"][j]
        seen = in_force[np.isfinite(in_force)]
        assert seen.size and (seen >= configured).all()
    assert (log["collision_limit_nm"] > np.array(log.meta["collision_threshold_nm"])).any()
    timing = fig.axes[-1]
    assert np.array_equal(timing.lines[0].get_ydata(), log["jitter_s"] * 1e6)

    png = tmp_path / "run.png"
    plot_log(position_run.trace.with_suffix(".mcap"), png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    image = imread(png)
    width, height = fig.get_size_inches() * fig.dpi
    assert image.shape[:2] == (round(height), round(width))
    # a different log gives a different picture
    other = TelemetryLog({**log.columns, "q_deg": log["q_deg"] + 5.0}, log.meta)
    plot_log(other, tmp_path / "other.png")
    assert not np.array_equal(imread(tmp_path / "other.png"), image)


def test_a_version_3_log_loads_without_expected_positions(position_run: PositionRun, tmp_path: Path) -> None:
    log = position_run.log
    dropped = ("q_exp_deg", "collision_limit_nm", "state")
    columns = {name: array for name, array in log.columns.items() if name not in dropped}
    TelemetryLog(columns, {**log.meta, "version": 3}).export_npz(tmp_path / "v3.npz")
    old = load_log(tmp_path / "v3.npz")
    assert np.isnan(old["q_exp_deg"]).all() and old["q_exp_deg"].shape == log["q_deg"].shape
    assert np.array_equal(old.following_error_deg(), log.lag_deg())  # what version 3 called the following error
    assert np.isnan(old["collision_limit_nm"]).all() and not old["state"].any()
    plot_log(old, tmp_path / "v3.png")


def test_empty_and_invalid_logs(tmp_path: Path) -> None:
    config = load_config(CONFIGS / "arm2.yaml")
    with TelemetrySession(TelemetryOptions(log=tmp_path / "sub" / "empty.mcap"), config):
        pass  # the arm never connected
    log = load_log(tmp_path / "sub" / "empty.mcap")
    assert log.cycles == 0 and log["q_deg"].shape == (0, 2) and log.joint_names == ["shoulder", "elbow"]
    plot_log(log, tmp_path / "empty.png")
    assert (tmp_path / "empty.png").stat().st_size > 0
    (tmp_path / "text.npz").write_text("not a log")
    np.savez(tmp_path / "bare.npz", t_s=np.zeros(3))
    for name in ("text.npz", "bare.npz"):
        with pytest.raises(ValueError, match="not a telemetry log"):
            load_log(tmp_path / name)
    with pytest.raises(OSError):
        load_log(tmp_path / "missing.npz")


@pytest.mark.parametrize("drives", list(ProtocolFamily))
def test_demo_runs_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str], drives: ProtocolFamily) -> None:
    assert run_demo(tmp_path / "demo", drives=drives) == 0
    out = capsys.readouterr().out
    kind = {
        ProtocolFamily.V2: "CAN drives of the older protocol (CAN v2.3 / RS485 v1.62) at 250 Hz",
        ProtocolFamily.V3: "CAN drives of the V3-driver protocol (V4.2) at 125 Hz",
    }[drives]
    assert f"on emulated {kind}" in out
    for name in ("position", "torque"):
        for suffix in (".mcap", ".log", ".png"):
            path = tmp_path / "demo" / f"{name}{suffix}"
            assert path.stat().st_size > 1000, path
            assert str(path) in out
        log = load_log(tmp_path / "demo" / f"{name}.mcap")
        with AnyReader([tmp_path / "demo" / f"{name}.mcap"]) as reader:  # (a reader we did not write: issue 34)
            (states,) = [c for c in reader.connections if c.topic == "/joint_states"]
            assert states.msgtype == "sensor_msgs/msg/JointState" and states.msgcount == log.cycles > 100
            _, _, raw = next(iter(reader.messages(connections=[states])))
            assert list(reader.deserialize(raw, states.msgtype).name) == log.joint_names  # type: ignore[attr-defined]
        assert log.meta["mode"] == name and list(log["fault_kind"]) == ["close"]
        assert log.meta["protocol"] == drives.value
        assert np.abs(log.following_error_deg()[log.active_rows()]).max() < log.meta["following_error_limit_deg"]
    assert "max following error" in out and "jitter p50/p99/max" in out
    # simulated time: a second run writes the same messages, bit for bit; the metadata differs in the wall-clock start
    assert run_demo(tmp_path / "again", quiet=True, drives=drives) == 0
    for name in ("position", "torque"):
        first, second = (_messages_and_meta(tmp_path / run / f"{name}.mcap") for run in ("demo", "again"))
        assert first[0] == second[0] and len(first[0]) > 1000
        host = {k for k in first[1] if any(word in k for word in HOST_TIME_WORDS)}
        assert host == {"t0_wall_unix_s"}
        assert {k: v for k, v in first[1].items() if k not in host} == {
            k: v for k, v in second[1].items() if k not in host
        }


def _messages_and_meta(path: Path) -> tuple[list[tuple[str, int, bytes]], dict[str, object]]:
    with path.open("rb") as stream:
        reader = make_reader(stream)
        messages = [(channel.topic, m.log_time, bytes(m.data)) for _, channel, m in reader.iter_messages()]
        (meta,) = [json.loads(r.metadata["meta"]) for r in reader.iter_metadata()]
    return messages, meta


def test_demo_reports_a_motion_fault_and_still_writes_its_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def faulty_path(arm: Arm) -> None:
        arm.move_to({"base_yaw": 2.0})
        arm.stop()  # an E-stop: the next motion command raises the fault
        arm.move_to({"base_yaw": 0.0})

    monkeypatch.setattr(demo, "_follow_path", faulty_path)
    assert run_demo(tmp_path, quiet=True) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and "motion fault in the position run: stop" in captured.err
    assert (tmp_path / "position.png").stat().st_size > 1000 and not (tmp_path / "torque.mcap").exists()
    assert list(load_log(tmp_path / "position.mcap")["fault_kind"]) == ["stop"]
