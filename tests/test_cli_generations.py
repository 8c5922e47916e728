"""The command line against arm2's drives emulated in either protocol generation (issue 17): scan, status, move,
run, Ctrl-C, hold / stop / clear. Each generation's emulator runs in its own process in real time, one after the other
(the module's other CLI tests are in tests/test_cli.py, whose helpers these use)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.motion_rig import skip_if_rate_refused
from tests.test_cli import (
    ARM2,
    ROOT,
    RUN_TIMEOUT_S,
    SLOW_MOVE,
    Emulated,
    cli,
    positions,
    rate_that_holds,
    running_emulator,
    status_json,
)


@pytest.fixture(scope="module", params=["v2", "v3"])
def any_arm(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Emulated]:
    """arm2's drives over slcan in either protocol generation, one at a time (each emulator runs its drives in real
    time beside the tests)."""
    protocol = str(request.param)
    with running_emulator(tmp_path_factory.mktemp(protocol), ARM2, "--slcan-link", "--protocol", protocol) as emulated:
        emulated.protocol = protocol
        yield emulated


@pytest.fixture(scope="module")
def any_arm_200hz(any_arm: Emulated, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """arm2.yaml at a rate this host holds on :func:`any_arm`'s drives: at most 200 Hz, V3 at most 150 Hz (twice the
    frames: about 200 Hz is the edge of what holds here)."""
    ceiling = 200.0 if any_arm.protocol == "v2" else 150.0
    config = rate_that_holds(ARM2, any_arm, tmp_path_factory.mktemp("config"), ceiling)
    if any_arm.protocol == "v3":  # the drives keep holding after each command (see with_link_timeout)
        return with_link_timeout(config, 0)
    return config


def with_link_timeout(config: Path, timeout_ms: int) -> Path:
    """``config`` with ``safety.link_timeout_ms`` set, in a file beside it: with the protection on (the default) a V3
    drive stops by itself once its host goes quiet, so the joints of arm2 (no brakes) go limp after each command;
    with it off they hold where the command left them, as the older drives do."""
    text = re.sub(r"\n\s+link_timeout_ms: \S+", "", config.read_text())
    timeout = re.search(r"\n(\s+)reply_timeout_ms: \S+", text)
    assert timeout is not None, config
    text = text.replace(timeout.group(0), f"{timeout.group(0)}\n{timeout.group(1)}link_timeout_ms: {timeout_ms}")
    path = config.with_name(f"link{timeout_ms}-{config.name}")
    path.write_text(text)
    return path


def test_scan_finds_both_drives(any_arm: Emulated) -> None:
    can_arm = any_arm
    result = cli("scan", "--config", ARM2, *can_arm.bus_args, "--json")
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    assert [d["motor_id"] for d in data["drives"]] == [1, 2]
    assert [d["joint"] for d in data["drives"]] == ["shoulder", "elbow"]
    assert all(d["voltage_v"] >= 20.0 and d["errors"] == [] for d in data["drives"])
    assert all(d["protocol"] == can_arm.protocol for d in data["drives"])
    # (a V3 drive names its model and firmware date; the older ones answer no model read on CAN)
    assert all((d["model"] is None) is (can_arm.protocol == "v2") for d in data["drives"])
    assert data["missing"] == []
    text = cli("scan", "--config", ARM2, *can_arm.bus_args, "--ids", "1-3")
    assert text.returncode == 0, text.stderr
    assert "2 of 3 ids answered" in text.stdout and "shoulder" in text.stdout and "elbow" in text.stdout


def test_status_json(any_arm: Emulated) -> None:
    joints = status_json(ARM2, any_arm)
    assert list(joints) == ["shoulder", "elbow"]
    keys = {"motor_id", "position_deg", "velocity_dps", "iq_a", "temperature_c", "voltage_v", "errors"}
    for joint in joints.values():
        assert keys <= set(joint)
        assert joint["within_limits"] is True


def test_move_then_status_shows_the_joints_there(any_arm: Emulated, any_arm_200hz: Path, tmp_path: Path) -> None:
    can_arm, arm2_200hz = any_arm, any_arm_200hz
    log, trace, png = tmp_path / "move.mcap", tmp_path / "move.candump", tmp_path / "move.png"
    result = cli(
        "move", "--config", arm2_200hz, *can_arm.bus_args, "shoulder=20", "elbow=-30", "--json",
        "--log", log, "--trace", trace,
    )  # fmt: skip
    skip_if_rate_refused(result)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["command"] == "move" and summary["targets"] == {"shoulder": 20.0, "elbow": -30.0}
    assert [j["name"] for j in summary["status"]["joints"]] == ["shoulder", "elbow"]
    assert "move: done in" in result.stderr  # plain progress lines: stderr is no terminal here
    reached = positions(ARM2, can_arm)
    assert reached["shoulder"] == pytest.approx(20.0, abs=0.5)
    assert reached["elbow"] == pytest.approx(-30.0, abs=0.5)

    sent = " 141#A1" if "mode: torque" in arm2_200hz.read_text() else " 141#A4"
    assert sent in trace.read_text()  # the set-points to the shoulder (torque or position), as sent
    plotted = cli("plot", log, "-o", png)
    assert plotted.returncode == 0, plotted.stderr
    assert png.read_bytes().startswith(b"\x89PNG")
    not_a_log = cli("plot", trace, "-o", png)
    assert not_a_log.returncode == 2
    assert f"cannot plot {trace}" in not_a_log.stderr


def test_run_program(any_arm: Emulated, any_arm_200hz: Path, tmp_path: Path) -> None:
    can_arm, arm2_200hz = any_arm, any_arm_200hz
    program = tmp_path / "program.yaml"
    program.write_text(
        "steps:\n"
        "  - move: {shoulder: 10, elbow: 15}\n"
        "    speed_scale: 0.8\n"
        "  - wait: 0.2\n"
        "  - path: [{shoulder: 0}, {shoulder: -10, elbow: 5}]\n"
    )
    result = cli("run", "--config", arm2_200hz, *can_arm.bus_args, program, "--json")
    skip_if_rate_refused(result)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["command"] == "run" and summary["steps"] == 3
    for label in ("step 1/3 move: done", "step 2/3 wait: 0.2 s", "step 3/3 path (2 waypoints): done"):
        assert label in result.stderr
    reached = positions(ARM2, can_arm)
    assert reached["shoulder"] == pytest.approx(-10.0, abs=0.5)
    assert reached["elbow"] == pytest.approx(5.0, abs=0.5)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_during_a_move_halts_every_axis(any_arm: Emulated, any_arm_200hz: Path, signum: signal.Signals) -> None:
    can_arm, arm2_200hz = any_arm, any_arm_200hz
    process = subprocess.Popen(
        [sys.executable, "-m", "motion.cli", "move", "--config", str(arm2_200hz), *can_arm.bus_args, *SLOW_MOVE],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert process.stderr is not None
    try:
        planned = process.stderr.readline()  # "move: N s planned": the motion is under way
        if "cannot be held" in planned:
            process.communicate(timeout=RUN_TIMEOUT_S)
            skip_if_rate_refused(subprocess.CompletedProcess(process.args, process.returncode, "", planned))
        assert "planned" in planned, planned + process.stderr.read()
        assert float(planned.split()[1]) > 3.0
        time.sleep(0.3)
        with can_arm.log.open() as log:
            interrupted_at = len(log.readlines())
        process.send_signal(signum)
        _, stderr = process.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr and "E-stop" in stderr
    time.sleep(0.1)
    after = can_arm.log.read_text().splitlines()[interrupted_at:]
    halted = {line.split("| motor ")[1].split(":")[0] for line in after if " IN " in line and "MOTOR_STOP" in line}
    assert halted == {"1", "2"}, after[-20:]
    reached = positions(ARM2, can_arm)
    assert abs(reached["shoulder"] - 60.0) > 5.0, "the move went on after the interrupt"


def test_hold_stop_clear(any_arm: Emulated) -> None:
    can_arm = any_arm
    for command, expected in [
        ("stop", "motor stop (0x81) acknowledged by shoulder (motor 1), elbow (motor 2)"),
        ("clear", "shoulder (motor 1): clear"),
        ("hold", "holding (drive position loop, 0xA4): shoulder at"),
    ]:
        result = cli(command, "--config", ARM2, *can_arm.bus_args)
        assert result.returncode == 0, result.stderr
        assert expected in result.stdout


def _rom_writes_in(log: str) -> list[str]:
    """The 0x43 and 0xB3 requests (ROM writes of the V3 drives) in a frame log's lines."""
    return [w.upper() for w in re.findall(r" IN +\S+ +14[12]: (?:43|B3) [0-9A-F ]+", log, flags=re.IGNORECASE)]


def test_a_second_session_writes_no_rom_and_restore_puts_back_the_settings(tmp_path: Path) -> None:
    # Issue 31 §4: a session writes a ROM-backed setting only where the drive (or, for 0xB3, which has no read, the
    # host's record) shows it differs; the session's end writes nothing, so the protection stays on and each drive
    # stops by itself (output off, brake locked) once its host goes quiet; `restore` writes back what was there.
    braked = tmp_path / "arm2.yaml"
    braked.write_text(re.sub(r"(\n(\s+)motor_id: \d+)", r"\1\n\2brake: true", ARM2.read_text()))
    with running_emulator(tmp_path, braked, "--slcan-link", "--protocol", "v3") as emulated:
        (tmp_path / "config").mkdir()
        config = with_link_timeout(rate_that_holds(braked, emulated, tmp_path / "config", 150.0), 50)
        move: tuple[str | Path, ...] = ("move", "--config", config, *emulated.bus_args)
        offset = emulated.log_size()
        for target in ("shoulder=5", "shoulder=0"):
            result = cli(*move, target)
            skip_if_rate_refused(result)
            assert result.returncode == 0, result.stderr
            if target == "shoulder=5":
                assert len(_rom_writes_in(emulated.log_since(offset))) == 6  # 0x43 of both indexes, 0xB3: each drive
                offset = emulated.log_size()
        assert _rom_writes_in(emulated.log_since(offset)) == []
        joints = status_json(braked, emulated)
        assert {name: joint["rom_writes"] for name, joint in joints.items()} == {"shoulder": 3, "elbow": 3}
        assert joints["shoulder"]["position_deg"] == pytest.approx(0.0, abs=0.5)  # held by its brake since
        held = cli("hold", "--config", braked, *emulated.bus_args)  # the drives would stop 50 ms after it
        assert held.returncode == 2 and "hold refused" in held.stderr and "shoulder 50 ms" in held.stderr
        refused = cli("restore", "--config", braked, *emulated.bus_args)
        assert refused.returncode == 2 and "--yes" in refused.stderr
        offset = emulated.log_size()
        restored = cli("restore", "--config", braked, *emulated.bus_args, "--yes")
        assert restored.returncode == 0, restored.stderr
        written = _rom_writes_in(emulated.log_since(offset))
        assert sorted(w.split()[3] for w in written) == ["43"] * 4 + ["B3"] * 2
        assert all(w.strip().endswith("00 00 00 00") == (w.split()[3] == "B3") for w in written)  # (B3: 0, off)
        assert "motor 1: position_acceleration" in restored.stdout and "6 ROM write(s)" in restored.stdout
        assert cli("hold", "--config", braked, *emulated.bus_args).returncode == 0
        offset = emulated.log_size()
        again = cli(*move, "shoulder=5")
        skip_if_rate_refused(again)
        assert again.returncode == 0, again.stderr
        assert len(_rom_writes_in(emulated.log_since(offset))) == 6  # set for tracking again
