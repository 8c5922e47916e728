"""``move`` and ``run`` with ``--emulate``: the configuration's emulated drives in simulated time, in the command's own
process (issue 11: what the command line prints is checked where the result does not depend on the host; the
real-time runs against ``rmd-motion emulate`` in another process are in ``tests/test_cli.py``)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

from motion.api import Arm
from motion.cli import main
from motion.cli.common import Interrupts, Session
from motion.cli.moves import _jog_verdict, hold_for, with_arm
from motion.compose import axis_specs
from motion.config import load_config, read_yaml
from motion.config.examples import example_names, resolve_program
from motion.emulator import Fault, InjectedFault
from motion.errors import MotionFault
from motion.telemetry import load_log
from tests.motion_rig import CONFIGS

PROGRAM = (
    "steps:\n"
    "  - move: {shoulder: 10, elbow: 15}\n"
    "    speed_scale: 0.8\n"
    "  - wait: 0.2\n"
    "  - path: [{shoulder: 0}, {shoulder: -10, elbow: 5}]\n"
)


def _run(capsys: pytest.CaptureFixture[str], *argv: str | Path) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_an_emulated_move_lands_where_commanded_and_prints_the_same_on_every_run(
    capsys: pytest.CaptureFixture[str],
) -> None:
    runs = [_run(capsys, "move", "--config", "arm2.yaml", "--emulate", "shoulder=30", "elbow=-20", "--json")]
    runs.append(_run(capsys, "move", "--config", "arm2.yaml", "--emulate", "shoulder=30", "elbow=-20", "--json"))
    (code, out, err), again = runs
    assert code == 0, err
    assert again == runs[0]  # simulated time: the same figures, the same progress lines, to the digit
    summary = json.loads(out)
    joints = {j["name"]: j for j in summary["status"]["joints"]}
    assert joints["shoulder"]["position_deg"] == pytest.approx(30.0, abs=0.1)
    assert joints["elbow"]["position_deg"] == pytest.approx(-20.0, abs=0.1)
    assert summary["status"]["state"] == "ready" and summary["status"]["fault"] is None
    # the duration is the arm's clock (simulated): the planned move, to the cycle, and then the joints' arrival within
    # control.goal_tolerance_deg (0.1 deg by default) for its settle time (issue 33 §6: torque mode's PD leaves arm2's
    # shoulder a few tenths short and still moving when the reference ends)
    planned = float(err.split("move: ")[1].split(" s planned")[0])
    arrival = summary["arrival"]
    assert arrival["arrived"] and 0.1 <= arrival["after_s"] < 1.0
    assert max(arrival["error_deg"].values()) <= 0.1
    assert summary["duration_s"] == pytest.approx(planned + arrival["after_s"], abs=0.01)
    assert f"move: done in {summary['duration_s']:.2f} s (arrived within 0.1 deg" in err


@pytest.mark.parametrize("arm", example_names())
def test_the_example_program_of_each_example_arm_runs_in_simulated_time(
    capsys: pytest.CaptureFixture[str], arm: str
) -> None:
    # issue 33: one program per example arm (`rmd-motion init` copies them), named as the README names it; its last
    # step brings every joint home, where the next session finds the same turns
    code, out, err = _run(capsys, "run", "--config", arm, "--emulate", f"configs/programs/{arm}", "--json")
    assert code == 0, err
    summary = json.loads(out)
    program = read_yaml(resolve_program(f"configs/programs/{arm}"))
    kinds = {next(iter(k for k in step if k != "speed_scale")) for step in program["steps"]}
    assert kinds == {"move", "path", "wait"} and any("speed_scale" in step for step in program["steps"]), kinds
    assert summary["steps"] == len(program["steps"]) and summary["status"]["fault"] is None
    assert {j["name"]: j["position_deg"] for j in summary["status"]["joints"]} == pytest.approx(
        {j["name"]: 0.0 for j in summary["status"]["joints"]}, abs=0.5
    )


def test_an_emulated_program_runs_every_step_and_records_its_cycles(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    program = tmp_path / "program.yaml"
    program.write_text(PROGRAM)
    log = tmp_path / "run.mcap"
    code, out, err = _run(capsys, "run", "--config", "arm2.yaml", "--emulate", program, "--json", "--log", log)
    assert code == 0, err
    for label in ("step 1/3 move: done", "step 2/3 wait: 0.2 s", "step 3/3 path (2 waypoints): done"):
        assert label in err
    summary = json.loads(out)
    assert summary["command"] == "run" and summary["steps"] == 3
    reached = {j["name"]: j["position_deg"] for j in summary["status"]["joints"]}
    assert reached == pytest.approx({"shoulder": -10.0, "elbow": 5.0}, abs=0.3)
    recorded = load_log(log)
    t = recorded["t_s"]
    # one row per cycle of the configured rate, no cycle late or skipped (simulated time)
    assert np.allclose(np.diff(t), 1.0 / recorded.meta["rate_hz"])
    assert recorded["q_deg"][-1] == pytest.approx([-10.0, 5.0], abs=0.3)


def test_emulate_refuses_bus_overrides(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, "move", "--config", "arm2.yaml", "--emulate", "--interface", "slcan", "shoulder=5")
    assert code == 2 and "--emulate opens no port: drop --interface" in err


@pytest.mark.parametrize("mode", ["torque", "position"])
def test_a_fault_of_a_joint_starved_of_current_names_its_physical_cause(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, mode: str
) -> None:
    # issue 33 §5: arm2's elbow with a current limit too low for its load and speed (0.2 A: a few steps of the
    # reply's current field): the following error that halts the arm is explained by what the run saw (the current
    # at its limit for the cycles before), and a run that completes prints its summary (cycles, timing, the largest
    # following error, the current-limited cycles)
    source = (CONFIGS / "arm2.yaml").read_text()
    config = tmp_path / "arm2.yaml"
    config.write_text(
        source.replace("current_limit_a: 10.0", "current_limit_a: 0.2").replace("mode: torque", f"mode: {mode}")
    )
    code, out, err = _run(capsys, "move", "--config", config, "--emulate", "elbow=-80", "shoulder=40")
    assert code == 1, err
    assert "motion fault, every axis halted: following_error joint=elbow" in err
    assert "likely cause: elbow at its 0.2 A current limit for " in err
    assert "torque_constant_nm_per_a and current_limit_a" in err
    assert "run until the fault: " in out and "current-limited cycles: elbow" in out  # the summary as far as it went
    code, out, err = _run(capsys, "move", "--config", config, "--emulate", "elbow=-80", "shoulder=40", "--json")
    assert code == 1, err
    printed = json.loads(out)  # --json: the summary with the fault and its cause, then the exit code
    assert printed["command"] == "move" and printed["fault"]["kind"] == "following_error"
    assert printed["fault"]["joint"] == "elbow" and "0.2 A current limit" in printed["fault"]["cause"]
    assert printed["run"]["joints"]["elbow"]["current_limited_cycles"] > 0
    assert printed["status"]["state"] not in ("ready", "moving")  # (halted: holding, braked or off by its policy)
    program = tmp_path / "program.yaml"
    program.write_text("- move: {elbow: -80, shoulder: 40}\n")
    code, out, err = _run(capsys, "run", "--config", config, "--emulate", program, "--json")
    assert code == 1, err
    assert json.loads(out)["fault"]["kind"] == "following_error"
    code, out, err = _run(capsys, "move", "--config", "arm2.yaml", "--emulate", "elbow=-20", "--json")
    assert code == 0, err
    run = json.loads(out)["run"]
    assert run["cycles"] > 100 and run["overruns"] == 0 and set(run["joints"]) == {"shoulder", "elbow"}
    assert 0.0 < run["max_following_error"]["deg"] < 1.0 and run["joints"]["elbow"]["current_limited_cycles"] == 0
    code, out, err = _run(capsys, "move", "--config", "arm2.yaml", "--emulate", "elbow=-20")
    assert "run: " in out and "current-limited cycles: none" in out


def test_a_configuration_is_checked_offline_against_what_its_drives_give(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # issue 33 §3: no bus: per joint the gravity torque at the worst pose in its limits and the torque to move at the
    # configured accelerations, against current limit x torque constant x gear; a program is validated as well
    code, out, err = _run(
        capsys, "check", "--config", "arm6.yaml", "--offline", "--program", "configs/programs/arm6.yaml", "--json"
    )
    assert code == 0, err
    report = json.loads(out)
    shoulder = report["joints"]["shoulder_pitch"]
    assert shoulder["available_nm"] == pytest.approx(36.0)  # its current limit x torque constant x 36 (1:36)
    assert 0.0 < shoulder["hold_nm"] < shoulder["move_nm"] < shoulder["available_nm"]
    assert report["joints"]["base_yaw"]["hold_nm"] == pytest.approx(0.0, abs=1e-6)  # a vertical axis carries no gravity
    assert report["program"]["steps"] == 6 and report["errors"] == [] and report["warnings"] == []
    # the trial's elbow: 0.74 N·m of the 0.8 it gives
    source = (CONFIGS / "arm2.yaml").read_text()
    weak = tmp_path / "arm2.yaml"
    weak.write_text(source.replace("current_limit_a: 10.0", "current_limit_a: 1.5"))
    code, out, err = _run(capsys, "check", "--config", weak, "--offline")
    assert code == 0, err
    assert "elbow holds the arm with 91% of what it gives (1.23 of 1.35 N·m" in err and "little is left" in err
    weak.write_text(source.replace("current_limit_a: 10.0", "current_limit_a: 1.0"))
    code, out, err = _run(capsys, "check", "--config", weak, "--offline")
    assert code == 2 and "error: elbow cannot hold the arm up: gravity takes 1.23 N·m" in err
    code, out, err = _run(capsys, "check", "--config", "arm2.yaml", "--program", "configs/programs/arm6.yaml")
    assert code == 2 and "--program checks a program offline: give --offline as well" in err
    code, out, err = _run(capsys, "check", "--config", "arm2.yaml", "--offline", "--holding")
    assert code == 2 and "--offline and --holding: one check at a time" in err
    code, out, err = _run(
        capsys, "check", "--config", "arm2.yaml", "--offline", "--program", "configs/programs/arm6.yaml"
    )
    assert code == 2 and "unknown joint" in err


def test_check_offline_prints_each_joints_unwrapping_headroom_and_refuses_one_beyond_it(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # per joint the motor degrees per sample at its velocity limit against half a turn, and the rates that unwrap it;
    # an X10-100 (1:35) at 60 deg/s at 10 Hz turns 210 motor deg per sample: an error naming its figures (exit 2)
    code, out, err = _run(capsys, "check", "--config", "arm2.yaml", "--offline")
    assert code == 0, err
    assert "encoder unwrapping at control.rate_hz 500 Hz" in out and "half a turn (180 motor deg)" in out
    assert re.search(r"shoulder\s+3\.2\s+2%\s+above 9 Hz", out) and re.search(r"elbow\s+4\.3\s+2%\s+above 12 Hz", out)
    text = (CONFIGS / "bench1.yaml").read_text().replace("rate_hz: 200", "rate_hz: 10")
    text = text.replace(
        "    gear_ratio: 9               # motor-shaft degrees per joint degree\n", "    actuator: X10-100\n"
    )
    text = text.replace("    torque_constant_nm_per_a: 0.1\n", "").replace(
        "velocity_limit_dps: 180.0", "velocity_limit_dps: 60.0"
    )
    x10 = tmp_path / "x10.yaml"
    x10.write_text(text)
    code, out, err = _run(capsys, "check", "--config", x10, "--offline", "--json")
    assert code == 2
    figures = json.loads(out)["unwrapping"]["lever"]
    assert figures["motor_deg_per_sample"] == pytest.approx(210.0) and figures["bound_motor_deg"] == 180.0
    assert figures["lowest_rate_hz"] == pytest.approx(11.667, abs=1e-3) and not figures["holds"]
    assert "error: joint lever: at its velocity_limit_dps 60 × gear_ratio 35 / control.rate_hz 10" in err
    assert "Raise control.rate_hz above 11.7 Hz, or lower its velocity_limit_dps below 51.4 deg/s" in err
    # V3 drives read their angle in every cycle: nothing is unwrapped
    code, out, err = _run(capsys, "check", "--config", "arm6_v3.yaml", "--offline")
    assert code == 0, err
    assert re.search(r"base_yaw\s+-\s+-\s+any \(0x92 every cycle\)", out)


def test_jog_moves_one_joint_and_back_and_says_which_drive_turned(capsys: pytest.CaptureFixture[str]) -> None:
    # issue 33 §2: a joint gravity does not load is commissioned by moving it: which drive turned, which way, how far
    code, out, err = _run(capsys, "jog", "--config", "arm2.yaml", "--emulate", "elbow", "--deg", "4", "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["expected_motor_deg"] == pytest.approx(-36.0)  # arm2's elbow: 1:9, mounted mirrored
    assert report["turned_motor_deg"]["elbow"] == pytest.approx(-36.0, abs=0.9)  # (arrived within 0.1 joint deg)
    assert abs(report["turned_motor_deg"]["shoulder"]) < 1.0
    assert (
        report["verdict"].startswith("elbow (motor 2) turned -35.") and "motor deg, as commanded" in report["verdict"]
    )
    code, _, err = _run(capsys, "jog", "--config", "arm2.yaml", "--emulate", "elbow", "--deg", "200")
    assert code == 2 and "takes it outside its limits [-135, 135]: jog the other way (--deg -200)" in err
    code, _, err = _run(capsys, "jog", "--config", "arm2.yaml", "--emulate", "elbow", "--deg", "0")
    assert code == 2 and "--deg: a non-zero number of joint degrees" in err


def test_the_jog_verdict_says_which_drives_turned_and_what_to_watch() -> None:
    # the drive is commanded and read through the joint's configured id, direction and gear, so its reading always
    # agrees with them: the verdict says so and what the user must watch; it names a drive that did not follow, none
    # that turned, and others that turned too
    config = load_config(CONFIGS / "arm2.yaml")
    shoulder, elbow = config.joints
    specs = {s.motor_id: s for s in axis_specs(config)}
    ok = _jog_verdict(elbow, -36.0, [(specs[2], -35.5)], 4.0)
    assert "elbow (motor 2) turned -35.5 motor deg, as commanded. Its reading follows the configuration" in ok
    assert "elbow should have moved +4 deg and back" in ok and "flip its direction" in ok and "9 times too far" in ok
    assert "no drive turned" in _jog_verdict(shoulder, 45.0, [], 5.0)
    assert "turned: motor 1 (shoulder) +45.0 motor deg, motor 2 (elbow) +20.0 motor deg" in _jog_verdict(
        shoulder, 45.0, [(specs[1], 45.0), (specs[2], 20.0)], 5.0
    )
    assert "the drive did not follow" in _jog_verdict(shoulder, 45.0, [(specs[1], 20.0)], 5.0)


@pytest.mark.parametrize("name", ["arm2_rs485.yaml", "arm6.yaml", "arm6_v3.yaml"])
def test_the_close_names_only_the_drives_that_never_answered_the_halt(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # one drive silent from 0.5 s: the halt goes to every drive, each healthy one answers it at once; on RS485 the
    # silent drive's reply windows ate its neighbour's later reads, and at the session's end a shortened exchange cut
    # a healthy drive's last read: neither is a halt left unanswered, so the warning at close names the silent drive
    # alone
    config = load_config(CONFIGS / name)
    silent = config.joints[0]

    def body(arm: Arm) -> int:
        with pytest.raises(MotionFault):
            hold_for(arm, 1.0)
        arm.sleep(0.5)  # halted, the silent drive's halt sent every cycle
        return 1

    faults = [Fault(InjectedFault.SILENT, silent.address, 0.5)]
    code = with_arm(argparse.Namespace(), Session(config, {}), Interrupts(), body, emulate=True, faults=faults)
    assert code == 1
    warned = [line for line in capsys.readouterr().err.splitlines() if "never acknowledged the halt" in line]
    assert len(warned) == 1 and warned[0].startswith(f"{silent.name} ({silent.drive_label}) never acknowledged")
