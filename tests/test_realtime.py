"""Real time where real time is the point: the drives emulated in a process of their own on a slcan pseudo-terminal,
the guarded loop in its own thread here, at a rate the rate check accepts on this host.

What must hold on any host is asserted, never how fast the host is: a bus closed under a running loop halts every
axis before the port is released, and nothing moves the drives after that.
"""

from __future__ import annotations

import dataclasses
import os
import re
import time
from pathlib import Path

import pytest

from motion.api import Arm
from motion.config import load_config
from motion.config.schema import ControlMode
from motion.control.ratecheck import RateError
from motion.errors import PortHeld
from motion.safety import ArmState
from motion.transport import CanTransport
from tests.motion_rig import CONFIGS
from tests.test_cli import cli, running_emulator

pytestmark = pytest.mark.realtime

#: The lowest rate the test moves at; a host that holds none at or above it gets the test skipped, with the figures.
MIN_RATE_HZ = 50.0
#: A frame the emulated drives received: time, then "IN", the adapter, "<CAN id>: <payload bytes>".
_RECEIVED = re.compile(r"^\s*(\d+\.\d+) IN\s+\S+\s+([0-9a-f]{3}): ([0-9a-f]{2})")


def _connect(tmp_path: Path, log: Path) -> Arm:
    """arm2 at 100 Hz, or at 0.6x the highest rate the rate check measured if 100 Hz does not hold here, in position
    mode (arm2's torque gains need 143 Hz: tests/test_stability.py)."""
    source = (CONFIGS / "arm2.yaml").read_text().replace("mode: torque", "mode: position")
    rate, why = 100.0, ""
    for _ in range(2):
        path = tmp_path / "arm2.yaml"
        path.write_text(source.replace("rate_hz: 500", f"rate_hz: {rate:g}"))
        arm = Arm(load_config(path), emulate="realtime", emulator_log=log)
        try:
            return arm.connect()
        except RateError as refused:
            why = str(refused)
            rate = 5.0 * round(0.6 * refused.check.highest_rate_hz / 5.0)
            if rate < MIN_RATE_HZ:
                break
    pytest.skip(f"no rate of at least {MIN_RATE_HZ:g} Hz holds on this host just now: {why}")


def test_closing_the_bus_under_a_running_loop_halts_every_axis_before_the_port_goes(tmp_path: Path) -> None:
    log = tmp_path / "frames.log"
    arm = _connect(tmp_path, log)
    try:
        assert arm.supervisor is not None and arm.bus is not None
        arm.move_to({"shoulder": 60.0, "elbow": -60.0}, speed_scale=0.5, wait=False)
        time.sleep(0.3)  # real time: the loop thread streams the move meanwhile
        supervisor, controller = arm.supervisor, arm.supervisor.controller
        assert supervisor.state is ArmState.MOVING
        arm.bus.close()  # from this thread, under the running loop
        states = {supervisor.state}  # (a set: mypy narrowed the state to MOVING above)
        assert states == {ArmState.HALTED}
        assert supervisor.fault is not None and supervisor.fault.kind == "bus_closing"
        assert not controller.loop.running
    finally:
        arm.close()
    received = [_RECEIVED.match(line) for line in log.read_text().splitlines()]
    frames = [(float(m[1]), int(m[2], 16) - 0x140, int(m[3], 16)) for m in received if m is not None]
    setpoints = [(t, motor) for t, motor, code in frames if code in (0xA1, 0xA4)]
    stops = {motor: t for t, motor, code in reversed(frames) if code == 0x81}
    assert set(stops) == {1, 2}, "every axis received 0x81"
    assert len(setpoints) > 10, "the move was streaming when the bus closed"
    last_stop = max(stops.values())
    assert all(t < min(stops.values()) for t, _ in setpoints), "no set-point after the first 0x81"
    assert last_stop - min(stops.values()) < controller.period_s  # one cycle's batch


def test_an_arm_runs_on_a_transport_the_caller_made(tmp_path: Path) -> None:
    # issue 32 §3: Arm(config, bus=...) takes a transport made elsewhere (here a python-can slcan bus on the pty of
    # `rmd-motion emulate`) instead of opening the configured one, and closes it with the arm
    config = load_config(CONFIGS / "arm2.yaml")
    # (position mode: arm2's torque-mode gains are tuned for its 500 Hz, and a busy host may hold only the lowest rate)
    control = dataclasses.replace(config.control, rate_hz=MIN_RATE_HZ, mode=ControlMode.POSITION)
    config = dataclasses.replace(config, control=control)
    with running_emulator(tmp_path, CONFIGS / "arm2.yaml", "--slcan-link") as emulated:
        bus = CanTransport("slcan", emulated.bus_args[-1], sleep_after_open=0)
        with pytest.raises(ValueError, match="takes the place of emulate= and bus_overrides="):
            Arm(config, bus=bus, emulate=True)
        with pytest.raises(TypeError, match="expected a motion.transport.Transport, got str"):
            Arm(config, bus="can0")  # type: ignore[arg-type]
        arm = Arm(config, bus=bus)
        try:
            arm.connect()
        except RateError as refused:
            pytest.skip(f"the rate check refused {MIN_RATE_HZ:g} Hz on this host just now: {refused}")
        try:
            assert arm.bus is bus
            arm.move_to({"shoulder": 10.0, "elbow": -10.0}, speed_scale=0.5)
            reached = arm.positions()
        finally:
            arm.close()
        assert reached == pytest.approx({"shoulder": 10.0, "elbow": -10.0}, abs=0.5)
        assert bus.closed


def test_a_second_session_on_a_port_a_session_holds_is_refused_and_the_first_moves_and_halts(tmp_path: Path) -> None:
    # a second rmd-motion session on the emulated adapter the arm holds, from another process (the command line) and
    # from this one (another Arm): each refused before it sends anything, and the first session moves and halts on
    base = load_config(CONFIGS / "arm2.yaml")
    with running_emulator(tmp_path, CONFIGS / "arm2.yaml", "--slcan-link") as emulated:
        overrides = {"interface": "slcan", "channel": emulated.bus_args[-1], "sleep_after_open": 0}
        # (the lock, not the rate, is the point: a rate a busy host holds, down to a tenth of a second's cycle)
        rate_hz = MIN_RATE_HZ
        while True:
            control = dataclasses.replace(base.control, rate_hz=rate_hz, mode=ControlMode.POSITION)
            config = dataclasses.replace(base, control=control)
            arm = Arm(config, bus_overrides=overrides)
            try:
                arm.connect()
                break
            except RateError as refused:
                rate_hz = 5.0 * round(0.6 * refused.check.highest_rate_hz / 5.0)
                if rate_hz < 10.0:
                    pytest.skip(f"no rate of at least 10 Hz holds on this host just now: {refused}")
        try:
            status = cli("status", "--config", CONFIGS / "arm2.yaml", *emulated.bus_args)
            assert status.returncode == 3, status.stderr
            assert "held by another rmd-motion session" in status.stderr and f"process {os.getpid()}" in status.stderr
            assert "Traceback" not in status.stderr
            with pytest.raises(PortHeld, match=re.escape(emulated.bus_args[-1])):
                Arm(config, bus_overrides=overrides).connect()
            assert arm.supervisor is not None and arm.supervisor.state is ArmState.READY
            since = emulated.log_size()
            arm.move_to({"shoulder": 10.0, "elbow": -10.0}, speed_scale=0.5)
            reached = arm.positions()
        finally:
            arm.close()
        assert reached == pytest.approx({"shoulder": 10.0, "elbow": -10.0}, abs=0.5)
    received = [_RECEIVED.match(line) for line in emulated.log_since(since).splitlines()]
    stops = {int(m[2], 16) - 0x140 for m in received if m is not None and int(m[3], 16) == 0x81}
    assert stops == {1, 2}, "every axis received the close's 0x81"
