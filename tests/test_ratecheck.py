"""The rate check at connect (issue 11): measured, never assumed; a rate that cannot be held is refused before
anything moves, naming ``control.rate_hz``, the figures and the highest rate that holds.

In simulated time the bus model decides (exact figures); against ``rmd-motion emulate`` in its own process the
check measures this host and the pty in real time (tests marked ``realtime``: they assert what must hold on any
host, never a speed)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from motion.api import Arm
from motion.compose import build_controller, check_rate, feedforward_for, rehearsal_watchdog
from motion.config import ArmConfig
from motion.config.schema import ControlMode
from motion.control.ratecheck import MAX_SAMPLES, MIN_SAMPLES, RateCheck, RateError, StatusRounds, measure_rate
from motion.emulator import Fault, FrameLog, InjectedFault, TimingModel
from motion.emulator.arm import arm_emulator
from motion.emulator.simulated import SimulatedBus, SimulatedClock, Simulation
from motion.errors import ConfigError, FaultKind, MotionFault
from motion.protocol import Bare, Command, WireProtocol
from motion.protocol.table import ADDRESS_STRIDE
from motion.transport import Reply, Request
from tests.motion_rig import CONFIGS, arm_config, skip_if_rate_refused
from tests.test_cli import TORQUE_MIN_RATE_HZ

ROOT = Path(__file__).resolve().parent.parent
#: The lowest rate the moving test runs at (as tests/test_cli.py).
MIN_RATE_HZ = 50.0


def _simulated(config: ArmConfig, latency_s: float, log: Path) -> tuple[Simulation, FrameLog, SimulatedBus]:
    emulator, _ = arm_emulator(config)
    simulation = Simulation(emulator, timing=TimingModel(latency_s))
    frame_log = FrameLog(log, clock=simulation.now)
    simulation.frame_log = frame_log
    return simulation, frame_log, SimulatedBus(simulation)


def test_simulated_slow_drives_refuse_500_hz_and_name_the_rate_that_holds(tmp_path: Path) -> None:
    # (position mode: torque mode's PD floor is tests/test_stability.py's)
    config = arm_config("arm2.yaml", rate_hz=500, mode=ControlMode.POSITION)
    simulation, log, bus = _simulated(config, 0.003, tmp_path / "frames.log")
    with log, bus:
        controller = build_controller(config, bus, clock=SimulatedClock(simulation))
        controller.read_positions()
        with pytest.raises(RateError) as info:
            check_rate(controller, config)
    error = info.value
    assert isinstance(error, ConfigError) and error.key_path == "control.rate_hz"
    check = error.check
    assert check.simulated and check.host_p99_s == 0.0
    # 3 requests out, 3 replies back at 1 Mbit/s (~0.12 ms each) after 3 ms of drive latency
    assert 0.0033 < check.round_trip_p99_s < 0.0040
    highest = check.highest_rate_hz
    assert highest == pytest.approx(0.8 / (check.round_trip_p99_s * 1.5) // 5 * 5)
    assert f"highest rate that holds is {highest:g} Hz" in str(error) and "control.rate_hz" in str(error)
    assert f"set control.rate_hz to {check.recommended_rate_hz:g} Hz or lower" in str(error)
    sent = [line for line in (tmp_path / "frames.log").read_text().splitlines() if " IN " in line]
    assert sent and all(": 9c " in line or ": 9a " in line or ": 92 " in line for line in sent)  # reads only
    # at the proposed rate the check passes
    slower = dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=highest))
    simulation, log, bus = _simulated(slower, 0.003, tmp_path / "frames2.log")
    with log, bus:
        controller = build_controller(slower, bus, clock=SimulatedClock(simulation))
        controller.read_positions()
        assert check_rate(controller, slower).holds


def test_margin_is_configurable_and_validated(tmp_path: Path) -> None:
    config = arm_config("arm2.yaml", rate_hz=500)
    simulation, log, bus = _simulated(config, 0.0005, tmp_path / "frames.log")
    with log, bus:
        controller = build_controller(config, bus, clock=SimulatedClock(simulation))
        controller.read_positions()
        strict = measure_rate(controller, margin=3.0)
        loose = measure_rate(controller, margin=1.0)
    assert loose.round_trip_p99_s == pytest.approx(strict.round_trip_p99_s, rel=0.05)  # same exchange, bar stuff bits
    assert loose.highest_rate_hz > strict.highest_rate_hz
    with pytest.raises(ValueError, match="margin"):
        measure_rate(controller, margin=0.5)
    text = (CONFIGS / "arm2.yaml").read_text().replace("rate_hz:", "rate_margin: 0.9\n  rate_hz:")
    bad = tmp_path / "arm2.yaml"
    bad.write_text(text)
    (tmp_path / "arm6.urdf").write_text((CONFIGS / "arm6.urdf").read_text())
    from motion.config import load_config

    with pytest.raises(ConfigError, match=r"control\.rate_margin"):
        load_config(bad)


def test_the_host_work_measured_is_a_guarded_cycle_rehearsed_on_the_measuring_replies(tmp_path: Path) -> None:
    config = arm_config("arm6.yaml", mode=ControlMode.TORQUE)  # feed-forward and collision observer: Pinocchio twice
    simulation, log, bus = _simulated(config, 0.0002, tmp_path / "frames.log")
    with log, bus:
        clock = SimulatedClock(simulation)
        controller = build_controller(config, bus, feedforward=feedforward_for(config), clock=clock)
        controller.read_positions()
        watchdog = rehearsal_watchdog(config, controller)
        assert watchdog.observer is not None
        seen: list[tuple[int, float]] = []

        def rehearse(replies: list[Reply], now_s: float) -> None:
            seen.append((sum(r.message is not None for r in replies), now_s))
            watchdog.rehearse(replies, now_s)

        check = measure_rate(controller, samples=4, rehearse=rehearse)
    # one rehearsal per exchange, on all of its replies (a state read per joint and the status read), in time order
    assert [n for n, _ in seen] == [len(config.joints) + 1] * 4 and check.samples == 4
    assert [t for _, t in seen] == sorted(t for _, t in seen)
    # the watchdog ran every monitor: the observer stepped and the following check tracked the rest reference
    assert np.isfinite(watchdog.residual_nm).all()
    assert np.isfinite(controller.tracking.expected_deg).all()
    sent = [line for line in (tmp_path / "frames.log").read_text().splitlines() if " IN " in line]
    assert all(": 9c " in line or ": 9a " in line or ": 92 " in line for line in sent), sent  # nothing but reads


def test_a_fault_seen_while_rehearsing_is_left_to_the_first_cycle(tmp_path: Path) -> None:
    config = arm_config("arm2.yaml", rate_hz=200)
    hot = Fault(InjectedFault.OVER_TEMPERATURE, 2, start_s=0.0)
    # connect's rate check saw the hot drive and did not raise
    with Arm(config, emulate=True, faults=[hot]) as arm, pytest.raises(MotionFault) as info:
        arm.move_to({"shoulder": 10.0})
    # the drive's flag and the measured temperature both say so; the first cycles' watchdog saw it, not the check's
    assert info.value.kind in (FaultKind.DRIVE_OVER_TEMPERATURE, FaultKind.TEMPERATURE), info.value
    assert info.value.joint == "elbow"


def test_rate_check_arithmetic() -> None:
    check = RateCheck(
        rate_hz=200, reply_budget=0.8, margin=1.5, round_trip_p99_s=0.002, host_p99_s=0.001, samples=10, simulated=False
    )
    # bounds: 0.8 / 0.003 = 266.7 Hz and 1 / 0.0045 = 222.2 Hz -> 220 Hz; recommended 0.8 x 220 = 176 -> 175 Hz
    assert check.highest_rate_hz == 220.0 and check.holds
    assert check.recommended_rate_hz == 175.0
    # below 20 Hz in whole Hz (a long RS485 line): 0.8 / 0.135 = 5.9 Hz -> 5 Hz; recommended 0.8 x 5.9 = 4.7 -> 4 Hz
    slow = dataclasses.replace(check, round_trip_p99_s=0.09, host_p99_s=0.0)
    assert slow.highest_rate_hz == 5.0 and slow.recommended_rate_hz == 4.0
    slowest = dataclasses.replace(check, round_trip_p99_s=0.4, host_p99_s=0.0)  # 0.8 / 0.6 = 1.3 Hz -> 1 Hz
    assert slowest.highest_rate_hz == 1.0 and slowest.recommended_rate_hz == 1.0  # not 0 Hz
    assert not dataclasses.replace(check, rate_hz=225).holds
    assert "holds" in check.summary()
    # the recommendation is based on the lower end of the spread between the measurement's quarters
    spread = dataclasses.replace(check, spread_hz=(150.0, 300.0))
    assert spread.highest_rate_hz == 220.0 and spread.recommended_rate_hz == 120.0  # 0.8 x 150
    assert "150 to 300 Hz by each quarter of the 10 exchanges" in spread.summary()
    assert dataclasses.replace(check, spread_hz=(250.0, 300.0)).recommended_rate_hz == 175.0  # (never above 0.8 x 220)


@pytest.mark.realtime
def test_the_real_time_check_measures_long_enough_and_reports_its_spread(tmp_path: Path) -> None:
    # at least MIN_SAMPLES exchanges and MEASURE_S, at most MAX_SAMPLES; the quarters' spread around the whole's figure
    copy = tmp_path / "arm2.yaml"
    # (position mode: 20 Hz holds on any host, and arm2's velocity limits unwrap above 12 Hz; torque mode's figures
    # are measured all the same)
    text = (CONFIGS / "arm2.yaml").read_text()
    copy.write_text(text.replace("rate_hz: 500", "rate_hz: 20").replace("mode: torque", "mode: position"))
    link = tmp_path / "can"
    with _emulator(copy, link, tmp_path / "frames.log"):
        result = _cli("check", "--config", copy, "--interface", "slcan", "--channel", link, "--json")
        assert result.returncode == 0, result.stderr  # 20 Hz holds on any host
        figures = json.loads(result.stdout)["modes"]
        for mode in figures.values():
            assert MIN_SAMPLES <= mode["samples"] <= MAX_SAMPLES
            low, high = mode["spread_hz"]
            # (every quarter may hold more than the whole: the whole's p99 round trip and p99 host work can come
            # from different quarters, and the whole takes both; the recommendation takes the lower of the two)
            assert low <= high
            floor = mode["stable_from_hz"] or 0.0  # torque mode: the PD loop's floor (tests/test_stability.py)
            recommended = mode["recommended_rate_hz"]
            if recommended < floor:  # (none: this host holds no rate up to the floor)
                assert recommended == 0.0 and mode["highest_rate_hz"] < floor
            else:
                assert recommended <= max(1.0, 0.8 * low, math.ceil(floor / 5.0) * 5.0)


@contextlib.contextmanager
def _emulator(config: Path, link: Path, log: Path, *extra: str) -> Iterator[None]:
    """``rmd-motion emulate`` of ``config`` on a slcan pty at ``link`` (its frames to ``log``) while in the block."""
    command: list[str | Path] = [sys.executable, "-m", "motion.cli", "emulate", "--config", config]
    emulator = subprocess.Popen(
        [*command, "--slcan-link", link, "--log", log, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert emulator.stdout is not None
        while not emulator.stdout.readline().startswith("emulating motors"):
            assert emulator.poll() is None, "the emulator did not start"
        yield
    finally:
        emulator.terminate()
        emulator.communicate(timeout=10)


def _cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "motion.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=ROOT,
    )


@pytest.mark.realtime
def test_cli_move_at_a_rate_the_bus_cannot_hold_exits_2_before_moving(tmp_path: Path) -> None:
    config = tmp_path / "arm2.yaml"
    config.write_text((CONFIGS / "arm2.yaml").read_text())
    assert "rate_hz: 500" in config.read_text()
    link, log = tmp_path / "can", tmp_path / "frames.log"
    with _emulator(config, link, log, "--latency-ms", "3"):
        bus = ("--interface", "slcan", "--channel", link)
        result = _cli("move", "--config", config, *bus, "shoulder=5")
        assert result.returncode == 2, result.stderr
        if "no rate this host and bus hold keeps torque mode's PD loop stable" in result.stderr:
            return  # (a host that holds less than the torque loop's floor: refused is right, nothing moved)
        assert "control.rate_hz" in result.stderr and "highest rate that holds is" in result.stderr
        highest = float(result.stderr.split("highest rate that holds is ")[1].split(" Hz")[0])
        assert 0 < highest < 500
        moved = [line for line in log.read_text().splitlines() if " IN " in line and ": 9c " not in line]
        assert all(": 9a " in line or ": 92 " in line for line in moved), moved  # nothing but reads was sent
        checked = _cli("check", "--config", config, *bus)
        assert checked.returncode == 2 and "does not hold" in checked.stdout
        if highest < MIN_RATE_HZ:  # so slow or busy a host that it holds no rate this test moves at: refused is right
            return
        # the rate the message recommends (room for the spread between measurements), at most 200 Hz
        recommended = float(result.stderr.split("set control.rate_hz to ")[1].split(" Hz")[0])
        assert recommended < highest
        rate = max(MIN_RATE_HZ, min(200.0, recommended))
        text = config.read_text().replace("rate_hz: 500", f"rate_hz: {rate:g}")
        if rate < TORQUE_MIN_RATE_HZ:  # arm2's torque-mode gains are tuned for its 500 Hz: at the rate a loaded host
            text = text.replace("mode: torque", "mode: position")  # holds, the drives close the loop (as in test_cli)
        config.write_text(text)
        result = _cli("move", "--config", config, *bus, "shoulder=5")
        skip_if_rate_refused(result)
        assert result.returncode == 0, result.stderr
        reached = float(result.stdout.split("shoulder=")[1].split()[0])
        # just done: the drive's own loop still settling (1.03 deg past it once, at the lower rate a loaded host holds)
        assert abs(reached - 5.0) < 2.0, result.stdout


@pytest.mark.parametrize(
    ("drives", "period_s", "wires", "per_bus"),
    [
        ((6,), 0.004, (WireProtocol.CAN,), [1]),  # 12 reads, each drive's within 50 ms: one a cycle at 250 Hz
        ((6,), 0.02, (WireProtocol.CAN,), [6]),  # at 50 Hz, half of them each cycle
        ((6, 6), 0.01, (WireProtocol.CAN, WireProtocol.RS485), [3, 1]),  # the line: one a cycle whatever the rate
        ((2, 5, 3), 0.0125, (WireProtocol.RS485, WireProtocol.CAN, WireProtocol.CAN), [1, 3, 2]),
    ],
)
def test_each_bus_takes_its_status_reads_round_by_its_own_count(
    drives: tuple[int, ...], period_s: float, wires: tuple[WireProtocol, ...], per_bus: list[int]
) -> None:
    reads_of = (Command.READ_STATUS_1, Command.READ_MULTI_TURN_ANGLE)
    addresses = [bus * ADDRESS_STRIDE + m for bus, count in enumerate(drives) for m in range(1, count + 1)]
    rounds = StatusRounds([(a, [Request(a, Bare(c)) for c in reads_of]) for a in addresses], period_s, wires)
    assert [count for _, count in rounds.rounds] == per_bus and rounds.per_cycle == sum(per_bus)
    every = [Request(a, Bare(c)) for a in addresses for c in reads_of]
    promised = {request: rounds.cycles_until(request) for request in every}  # before the first cycle
    went: dict[Request, int] = {}
    for cycle in range(1, 2 * max(drives) + 1):
        batch = rounds.next()
        # each bus's own count of its own reads, every cycle
        assert [sum(r.motor_id // ADDRESS_STRIDE == bus for r in batch) for bus in range(len(drives))] == per_bus
        for request in batch:
            went.setdefault(request, cycle)
    assert went == promised  # every read came round, in the cycle cycles_until said
    with pytest.raises(ValueError, match="not one of the status reads"):
        rounds.cycles_until(Request(99, Bare(Command.READ_STATUS_1)))
