"""An arm whose buses have drives of different protocol generations (issue 35: each bus "its own protocol setting"):
bimanual.yaml with the left arm's drives of the older family (CAN v2.3) and the right arm's of driver V3 (V4.2). Each
bus is spoken in its drives' generation (told per bus at connect), the control loop treats each joint by its drive's
family (V3: the fine angle read in every cycle, output-shaft units, 0xA1 for torque, the link-loss protection and
planning accelerations set at connect), and the arm is still one trajectory and one safety domain."""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from motion.api import Arm
from motion.api.emulation import simulated_lines
from motion.compose import negotiate_family, open_bus, opening_families
from motion.config import ArmConfig, ControlMode, load_config
from motion.config.schema import HaltPolicy
from motion.control.family import FAMILIES as FAMILY_OF
from motion.control.ratecheck import RateError
from motion.emulator import Emulator, VirtualCanAttachment
from motion.emulator.arm import arm_emulator
from motion.emulator.drive_v3 import EmulatedDriveV3
from motion.emulator.faults import InjectedFault
from motion.emulator.model import DriveModel, LoadModel
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.errors import TransportError
from motion.protocol import Command
from motion.protocol.table import ProtocolFamily
from motion.protocol.v3.messages import CommandV3
from motion.safety import ArmState
from motion.telemetry import load_log
from tests.motion_rig import emulated_arm, logged_requests, received
from tests.test_buses import TARGETS, fault_halts_every_axis
from tests.test_cli import cli, host_stall_misses
from tests.test_mixed_buses import move_both_elbows

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
V2, V3 = ProtocolFamily.V2, ProtocolFamily.V3
#: The left bus's drives speak the older protocol, the right bus's driver V3's.
FAMILIES = (V2, V3)


def _mixed(tmp_path: Path, *, left: str = "v2", right: str = "v3", rs485: bool = False) -> Path:
    """bimanual.yaml (and its URDF) in ``tmp_path`` with each bus's ``protocol`` as named (``rs485``: each arm on an
    RS485 line at 115200 baud, at 25 Hz)."""
    shutil.copy(CONFIGS / "bimanual.urdf", tmp_path / "bimanual.urdf")
    data = yaml.safe_load((CONFIGS / "bimanual.yaml").read_text())
    if rs485:
        for name in ("left", "right"):
            data["buses"][name] = {"transport": "rs485", "port": f"/dev/ttyUSB-{name}", "baudrate": 115200}
        data["safety"]["reply_timeout_ms"] = 250
    data["buses"]["left"]["protocol"] = left
    data["buses"]["right"]["protocol"] = right
    # (V3 drives read their fine angle in every cycle: twice the older drives' frames, more than 250 Hz holds)
    data["control"]["rate_hz"] = 25 if rs485 else 125
    path = tmp_path / "generations.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _config(tmp_path: Path, **protocols: Any) -> ArmConfig:
    return load_config(_mixed(tmp_path, **protocols))


@pytest.mark.parametrize("rs485", [False, True], ids=["two can buses", "two rs485 lines"])
def test_each_bus_is_spoken_in_its_drives_generation_and_the_arm_moves_as_one(tmp_path: Path, rs485: bool) -> None:
    config = _config(tmp_path, rs485=rs485)
    with emulated_arm(config, "sim", tmp_path, supervised=True, family=FAMILIES) as rig:
        supervisor, controller = rig.supervisor, rig.controller
        assert supervisor is not None
        assert controller.bus.families == FAMILIES
        assert [f.family for f in controller.families] == [V2] * 6 + [V3] * 6
        references: list[np.ndarray] = []
        controller.cycle_hooks.append(lambda c, _start, _replies: references.append(c.reference.position.copy()))
        supervisor.move_to(TARGETS, 1.0)
        assert supervisor.wait(20.0)
        reference = np.array(references)
        arrived = [int(np.argmax(np.abs(reference[:, i] - TARGETS[i]) < 1e-9)) for i in range(len(TARGETS))]
        assert max(arrived) - min(arrived) <= 1 and min(arrived) > 10, arrived  # (a real move: 0.4 s and more)
        tolerance = config.control.goal_tolerance_deg
        np.testing.assert_allclose(controller.snapshot.position_deg, TARGETS, atol=tolerance)
        # the plant's own angles agree (each family's angle read the same joint angle: V3's output shaft times its
        # reduction, the older drives' encoder)
        np.testing.assert_allclose(rig.plant.joint_positions_deg(), TARGETS, atol=tolerance + 0.02)
        assert supervisor.state is ArmState.READY and not supervisor.faults
    # the V3 drives read their fine angle (0x92) in every cycle; the older ones as their restart read, in turn
    angles = received(rig, Command.READ_MULTI_TURN_ANGLE)
    cycles = len(received(rig, Command.MULTI_TURN_POSITION_SPEED)[101])
    assert all(len(angles[j.address]) >= cycles for j in config.joints_on(1))
    assert all(len(angles[j.address]) < cycles / 2 for j in config.joints_on(0))
    # the session set the V3 drives' link-loss protection and zeroed their planning accelerations; nothing on the
    # older drives (which have neither)
    for joint in config.joints:
        drive = rig.emulator.drives[joint.address]
        if joint.bus_index == 1:
            assert isinstance(drive, EmulatedDriveV3) and drive.communication_timeout_ms > 0
            assert {drive.accelerations[i] for i in FAMILY_OF[V3].planning_accelerations} == {0}
        else:
            assert not isinstance(drive, EmulatedDriveV3)
    assert not set(received(rig, CommandV3.WRITE_ACCELERATION)) & {j.address for j in config.joints_on(0)}


def test_torque_mode_sends_0x280_to_the_older_drives_and_0xa1_to_the_v3_drives(tmp_path: Path) -> None:
    config = _config(tmp_path)
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, mode=ControlMode.TORQUE))
    with emulated_arm(config, "sim", tmp_path, supervised=True, family=FAMILIES) as rig:
        # (holding the pose: the example's torque-mode gains are tuned for 250 Hz, not this arm's 125 Hz)
        assert rig.supervisor is not None
        rig.sleep(1.0)
        assert rig.supervisor.state is ArmState.READY and not rig.supervisor.faults
    multi = [t for t, address, _ in logged_requests(rig) if address is None]
    torque = received(rig, Command.TORQUE)
    # the left bus's motors 1..4: one 0x280 frame a cycle, as each V3 drive's 0xA1
    assert len(multi) > 100 and abs(len(multi) - len(torque[101])) <= 2
    assert set(torque) == {5, 6, 101, 102, 103, 104, 105, 106}  # (V3's 0x280 broadcasts one command: 0xA1 each)


@pytest.mark.parametrize(
    ("kind", "address", "value", "expected"),
    [
        (InjectedFault.OVER_TEMPERATURE, 103, 90.0, "drive_over_temperature"),  # a V3 drive's error word
        (InjectedFault.OVER_TEMPERATURE, 2, 90.0, "drive_over_temperature"),  # an older drive's flags
        (InjectedFault.SILENT, 105, None, "no_reply"),  # a V3 drive falls silent
        (InjectedFault.SILENT, 4, None, "no_reply"),  # an older drive falls silent
        (InjectedFault.POWER_CYCLE, 106, None, "drive_restarted"),  # a V3 drive's runtime starts again (0xB1)
        (InjectedFault.POWER_CYCLE, 3, None, "drive_restarted"),  # an older drive's angle jumps (0x92)
    ],
)
def test_a_fault_on_a_drive_of_either_generation_halts_all_twelve_axes_in_its_detection_cycle(
    tmp_path: Path, kind: InjectedFault, address: int, value: float | None, expected: str
) -> None:
    config = _config(tmp_path)
    joints = tuple(dataclasses.replace(j, temperature_limit_c=100.0) for j in config.joints)
    control = dataclasses.replace(config.control, halt_policy=HaltPolicy.STOP)
    safety = dataclasses.replace(config.safety, reply_timeout_ms=20)
    config = dataclasses.replace(config, joints=joints, control=control, safety=safety)
    fault_halts_every_axis(config, tmp_path, kind, address, value, expected, family=FAMILIES)


def test_auto_tells_each_bus_its_generation_and_a_setting_the_drives_contradict_is_refused(tmp_path: Path) -> None:
    def negotiated(config: ArmConfig) -> tuple[ProtocolFamily, ...]:
        emulator, _ = arm_emulator(config, family=FAMILIES)
        simulation = Simulation(emulator, lines=simulated_lines(config))
        names = [b.name for b in config.buses]
        with SimulatedBus(simulation, (V2, V2), names=names) as opened, negotiate_family(opened, config) as bus:
            assert {a: bus.family_of(a) for a in (1, 101)} == {1: V2, 101: V3}
            return bus.families

    assert negotiated(_config(tmp_path, left="auto", right="auto")) == FAMILIES
    # before asking: a bus set to auto opens in the generation the other buses name (else the older)
    assert opening_families(_config(tmp_path, left="v3", right="auto")) == (V3, V3)
    assert opening_families(_config(tmp_path, left="auto", right="auto")) == (V2, V2)
    # the API's emulated drives: each bus's generation given, or each bus's configured one
    assert Arm(_config(tmp_path, left="auto", right="auto"), emulated_protocol=FAMILIES).emulated_families == FAMILIES
    assert Arm(_config(tmp_path)).emulated_families == FAMILIES
    with pytest.raises(TransportError, match=r"buses\.left\.protocol is v3, but the drives answer in the v2"):
        negotiated(_config(tmp_path, left="v3", right="auto"))


def test_drives_of_both_generations_on_one_bus_are_refused_naming_the_bus(tmp_path: Path) -> None:
    # two virtual CAN buses: the left one's six older drives; on the right one five V3 drives and an older one (104)
    config = _config(tmp_path, left="auto", right="auto")
    left, right = uuid.uuid4().hex, uuid.uuid4().hex
    model, load = DriveModel(), LoadModel()
    with (
        VirtualCanAttachment(Emulator(range(1, 7), model=model, load=load), left),
        VirtualCanAttachment(Emulator([101, 102, 103, 105, 106], model=model, load=load, family=V3), right, line=1),
        VirtualCanAttachment(Emulator([104], model=model, load=load), right, line=1),
        open_bus(config, interface="virtual", channel={"left": left, "right": right}, bitrate=None) as opened,
        pytest.raises(TransportError, match=r"both protocol generations on bus right \(.*: v2.*: v3"),
    ):
        negotiate_family(opened, config)


def test_the_cli_moves_and_records_an_arm_of_both_generations(tmp_path: Path) -> None:
    recording = tmp_path / "run.mcap"
    move_both_elbows(_mixed(tmp_path), "--log", recording)
    meta = load_log(recording).meta
    assert meta["protocol"] == "v2+v3"
    assert [j["protocol"] for j in meta["joints"]] == ["v2"] * 6 + ["v3"] * 6


def test_the_api_runs_both_generations_against_the_emulator_process_in_real_time(tmp_path: Path) -> None:
    # `rmd-motion emulate --config` speaks each bus's configured generation on its own slcan pty
    path = _mixed(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["control"]["rate_hz"] = 50
    data["safety"]["reply_timeout_ms"] = 250
    data["safety"]["max_missed_replies"] = host_stall_misses(50)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    try:
        with Arm.from_config(path, emulate="realtime") as arm:
            assert arm.bus is not None and arm.bus.families == FAMILIES
            arm.move_to({"left_elbow_pitch": 20.0, "right_elbow_pitch": -20.0}, speed_scale=0.5)
            q = arm.positions()
    except RateError as exc:
        pytest.skip(f"this host does not hold the arm at 50 Hz just now: {exc}")
    tolerance = load_config(path).control.goal_tolerance_deg + 0.01
    assert abs(q["left_elbow_pitch"] - 20.0) < tolerance and abs(q["right_elbow_pitch"] + 20.0) < tolerance


def test_the_emulator_cli_takes_a_generation_per_bus(tmp_path: Path) -> None:
    refused = cli("emulate", "--config", _mixed(tmp_path), "--protocol", "middle=v3", "--slcan-link", "left=x")
    assert refused.returncode == 2 and "no bus 'middle'" in refused.stderr, refused.stderr
    both = cli("emulate", "--config", _mixed(tmp_path), "--protocol", "v3", "--protocol", "right=v2")
    assert both.returncode == 2 and "not both" in both.stderr, both.stderr


def test_the_drive_commands_speak_each_buss_generation_against_the_emulator_process(tmp_path: Path) -> None:
    # `rmd-motion emulate --config` on two slcan ptys (each bus's configured generation), then the one-off commands:
    # each joint asked in its drive's generation, and answered
    path = _mixed(tmp_path)
    links = {name: tmp_path / f"slcan-{name}" for name in ("left", "right")}
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", str(path)]
    for name, link in links.items():
        command += ["--slcan-link", f"{name}={link}"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None
        started = [process.stdout.readline() for _ in range(3)]
        assert "on bus left" in started[2] and "on bus right" in started[2], started
        bus = ["--interface", "slcan", *(a for n, p in links.items() for a in ("--channel", f"{n}={p}"))]
        scanned = cli("scan", "--config", path, *bus, "--ids", "1-6", "--json")
        assert scanned.returncode == 0, scanned.stderr
        assert [(d["bus"], d["protocol"]) for d in json.loads(scanned.stdout)["drives"]] == [
            (side, family.value) for side, family in zip(("left", "right"), FAMILIES, strict=True) for _ in range(6)
        ]
        assert "both protocol generations" not in scanned.stderr and "not the configuration's" not in scanned.stderr
        status = cli("status", "--config", path, *bus, "--json")
        assert status.returncode == 0, status.stderr
        assert len(json.loads(status.stdout)["joints"]) == 12
        for args in (("clear",), ("hold",), ("pid", "get"), ("stop",)):
            done = cli(*args, "--config", path, *bus)
            assert done.returncode == 0, (args, done.stderr)
        gains = cli("pid", "get", "--config", path, *bus, "--json")
        table = json.loads(gains.stdout)
        assert "angle_kp" in table["left_elbow_pitch"] and table["left_elbow_pitch"].keys() != (
            table["right_elbow_pitch"].keys()
        )  # (each generation's own parameters)
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)
