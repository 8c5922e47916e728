"""YAML arm configuration: the example configs load, and every kind of mistake names file, key path and range."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from motion.config import (
    ArmConfig,
    CanBusConfig,
    ControlMode,
    EmulationConfig,
    HaltPolicy,
    Rs485BusConfig,
    load_config,
    parse_config,
)
from motion.errors import ConfigError

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
EXAMPLES = sorted(CONFIGS.glob("*.yaml"))


def _mapping(name: str) -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((CONFIGS / name).read_text())
    if "urdf" in data["model"]:
        data["model"]["urdf"] = str(CONFIGS / data["model"]["urdf"])
    return data


ARM2 = _mapping("arm2.yaml")
ARM6 = _mapping("arm6.yaml")
BIMANUAL = _mapping("bimanual.yaml")


def test_there_are_six_examples() -> None:
    assert [p.name for p in EXAMPLES] == [
        "arm2.yaml", "arm2_rs485.yaml", "arm6.yaml", "arm6_v3.yaml", "bench1.yaml", "bimanual.yaml"
    ]  # fmt: skip


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_every_example_loads_from_any_directory(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    config = load_config(path)
    assert config.name == path.stem
    assert config.source == str(path)
    for index in range(len(config.buses)):
        on_bus = config.joints_on(index)
        assert sorted(j.motor_id for j in on_bus) == list(range(1, len(on_bus) + 1))
    assert len(config.transmission()) == len(config.joints)


def test_an_arm_on_two_buses_places_each_joint_on_its_bus_with_ids_per_bus() -> None:
    # issue 35: `buses:` names the buses; each joint names its own; motor ids are unique per bus, not per arm
    config = load_config(CONFIGS / "bimanual.yaml")
    assert [(b.name, b.channel) for b in config.buses] == [("left", "can0"), ("right", "can1")]  # type: ignore[union-attr]
    assert [(j.name, j.bus, j.motor_id, j.address) for j in config.joints[5:7]] == [
        ("left_flange_roll", "left", 6, 6),
        ("right_base_yaw", "right", 1, 101),
    ]
    assert config.joints_on(1) == config.joints[6:]
    assert config.joints[7].drive_label == "motor 2 on bus right"
    with pytest.raises(ConfigError, match=r"buses: this takes an arm on one bus; the arm is on left, right"):
        _ = config.bus
    arm6 = load_config(CONFIGS / "arm6.yaml")
    assert arm6.bus is arm6.buses[0] and arm6.bus.name == "" and [j.address for j in arm6.joints] == [1, 2, 3, 4, 5, 6]
    assert arm6.joints[0].drive_label == "motor 1"


def test_one_entry_under_buses_needs_no_bus_per_joint(tmp_path: Path) -> None:
    data = copy.deepcopy(ARM2)
    data["buses"] = {"main": data.pop("bus")}
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    config = load_config(path)
    assert config.bus.name == "main" and {j.bus for j in config.joints} == {"main"}
    assert [j.address for j in config.joints] == [j.motor_id for j in config.joints]


def test_arm6_uses_the_shipped_urdf() -> None:
    config = load_config(CONFIGS / "arm6.yaml")
    assert config.model.urdf == CONFIGS / "arm6.urdf"
    assert config.model.chain == ()
    assert config.model.gravity_m_s2 == (0.0, 0.0, -9.81)
    assert config.control.mode is ControlMode.POSITION
    assert isinstance(config.bus, CanBusConfig)
    assert config.bus.bitrate == 1_000_000


def test_arm2_values_and_defaults() -> None:
    config = load_config(CONFIGS / "arm2.yaml")
    shoulder, elbow = config.joints
    assert (shoulder.gear_ratio, elbow.direction, shoulder.torque_constant_nm_per_a) == (9.0, -1, 0.1)
    assert shoulder.encoder_bits == 14  # default
    assert elbow.emulation == EmulationConfig()  # default
    assert config.model.chain[1].origin_xyz_m == (0.3, 0.0, 0.0)
    assert config.model.chain[0].link_name == "upper_arm"
    assert config.model.tip_xyz_m == (0.25, 0.0, 0.0)
    assert config.control.period_s == pytest.approx(0.002)
    assert config.control.halt_policy is HaltPolicy.HOLD
    rs485 = load_config(CONFIGS / "arm2_rs485.yaml")
    assert rs485.bus == Rs485BusConfig(port="/dev/ttyUSB0", baudrate=115200)
    # the same arm, but for the elbow's torque gains, lowered for the RS485 arm's 100 Hz (tests/test_stability.py)
    assert rs485.joints[0] == config.joints[0]
    assert dataclasses.replace(rs485.joints[1], kp_nm_per_deg=0.3, kd_nm_per_dps=0.01) == config.joints[1]


def test_configuration_is_frozen() -> None:
    config = parse_config(copy.deepcopy(ARM2))
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.joints[0].gear_ratio = 1.0  # type: ignore[misc]
    assert not hasattr(config.joints[0], "__dict__")  # slotted


def test_optional_keys_take_their_documented_defaults() -> None:
    data = copy.deepcopy(ARM2)
    data["control"] = {"halt_policy": "stop"}
    data["safety"] = {"following_error_deg": 3.0, "min_voltage_v": 20.0}
    del data["model"]["gravity_m_s2"], data["model"]["chain"][0]["link"], data["model"]["chain"][0]["origin_xyz_m"]
    for joint in data["joints"]:
        del joint["kp_nm_per_deg"], joint["kd_nm_per_dps"], joint["temperature_limit_c"]
    config = parse_config(data)
    assert config.control.mode is ControlMode.POSITION
    assert (config.control.rate_hz, config.control.gravity_feedforward) == (200.0, False)
    assert (config.safety.reply_timeout_ms, config.safety.max_missed_replies) == (20.0, 3)
    assert config.model.gravity_m_s2 == (0.0, 0.0, -9.81)
    assert config.model.chain[0].link_name == "shoulder_link"
    assert config.model.chain[0].origin_xyz_m == (0.0, 0.0, 0.0)
    assert (config.joints[0].kp_nm_per_deg, config.joints[0].temperature_limit_c) == (0.0, 70.0)


def test_chain_axis_is_normalised() -> None:
    data = copy.deepcopy(ARM2)
    data["model"]["chain"][0]["axis"] = [0, 0, 2]
    assert parse_config(data).model.chain[0].axis == (0.0, 0.0, 1.0)


# ---- halt_policy and YAML 1.1 booleans -------------------------------------------------------------------


def _yaml_with(tmp_path: Path, old: str, new: str, name: str = "arm2.yaml") -> Path:
    text = (CONFIGS / name).read_text()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize("spelling", ["off", "'off'", '"off"', "false"])
def test_halt_policy_off_in_every_spelling(tmp_path: Path, spelling: str) -> None:
    path = _yaml_with(tmp_path, "halt_policy: hold", f"halt_policy: {spelling}")
    assert load_config(path).control.halt_policy is HaltPolicy.OFF


@pytest.mark.parametrize("spelling", ["on", "yes", "true"])
def test_halt_policy_true_is_rejected(tmp_path: Path, spelling: str) -> None:
    path = _yaml_with(tmp_path, "halt_policy: hold", f"halt_policy: {spelling}")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    expected = f"{path}: control.halt_policy: expected one of stop, off, hold; found the boolean"
    assert str(info.value).startswith(expected)
    assert "YAML 1.1" in str(info.value)


# ---- file-level errors -----------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="file not found") as info:
        load_config(path)
    assert (info.value.file, info.value.key_path) == (str(path), "<file>")


def test_invalid_yaml_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nbus:\n  transport: [can\ncontrol: {}\n")
    with pytest.raises(ConfigError, match="invalid YAML") as info:
        load_config(path)
    assert info.value.file == str(path)
    assert info.value.key_path.startswith("line 4,")


def test_duplicate_yaml_key_is_rejected(tmp_path: Path) -> None:
    old = "    gear_ratio: 9\n    direction: -1"
    path = _yaml_with(tmp_path, old, old.replace("\n", "\n    gear_ratio: 1\n"))
    line = path.read_text().splitlines().index("    gear_ratio: 1") + 1
    with pytest.raises(ConfigError, match="duplicate key 'gear_ratio'") as info:
        load_config(path)
    assert info.value.key_path == f"line {line}, column 5"


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.yaml"
    path.write_text("")
    with pytest.raises(ConfigError, match=r"<root>: expected a mapping of keys; found nothing \(null\)"):
        load_config(path)


def test_relative_urdf_is_relative_to_the_file(tmp_path: Path) -> None:
    path = _yaml_with(tmp_path, "urdf: arm6.urdf", "urdf: arm6.urdf", name="arm6.yaml")
    with pytest.raises(ConfigError, match=f"file not found: {tmp_path / 'arm6.urdf'}") as info:
        load_config(path)
    assert info.value.key_path == "model.urdf"
    (tmp_path / "arm6.urdf").write_text((CONFIGS / "arm6.urdf").read_text())
    assert load_config(path).model.urdf == tmp_path / "arm6.urdf"


# ---- one test per validation error kind ------------------------------------------------------------------

Mutation = Callable[[dict[str, Any]], None]


def _parent(data: dict[str, Any], keys: tuple[str | int, ...]) -> Any:
    target: Any = data
    for key in keys[:-1]:
        target = target[key]
    return target


def _set(*keys: str | int, value: object) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        _parent(data, keys)[keys[-1]] = value

    return mutate


def _delete(*keys: str | int) -> Mutation:
    def mutate(data: dict[str, Any]) -> None:
        del _parent(data, keys)[keys[-1]]

    return mutate


def _write_urdf(data: dict[str, Any], tmp_path: Path, old: str, new: str) -> None:
    text = (CONFIGS / "arm6.urdf").read_text()
    assert old in text
    urdf = tmp_path / "edited.urdf"
    urdf.write_text(text.replace(old, new))
    data["model"]["urdf"] = str(urdf)


# (case id, base, mutation, key path, fragments the message must contain: allowed values and the value found)
CASES: list[tuple[str, dict[str, Any], Mutation, str, list[str]]] = [
    (
        "unknown key",
        ARM2,
        _set("joints", 1, "gear_ration", value=9),
        "joints[1].gear_ration",
        ["unknown key", "did you mean 'gear_ratio'?", "allowed keys: acceleration_limit_dps2,"],
    ),
    ("unknown top-level key", ARM2, _set("source", value="x"), "source", ["unknown key", "allowed keys: bus,"]),
    (
        "missing key",
        ARM2,
        _delete("joints", 0, "gear_ratio"),
        "joints[0].gear_ratio",
        ["required key is missing", "a number, 0 < x"],
    ),
    ("missing section", ARM2, _delete("safety"), "safety", ["required section is missing"]),
    ("missing list", ARM2, _delete("joints"), "joints", ["expected a non-empty list of mappings", "missing"]),
    ("empty list", ARM2, _set("joints", value=[]), "joints", ["expected a non-empty list of mappings", "a list"]),
    (
        "section not a mapping",
        ARM2,
        _set("control", value="fast"),
        "control",
        ["expected a mapping of keys", "the string 'fast'"],
    ),
    (
        "string is not a number",
        ARM2,
        _set("joints", 1, "gear_ratio", value="9"),
        "joints[1].gear_ratio",
        ["expected a number (0 < x)", "the string '9'", "unquoted"],
    ),
    (
        "YAML 1.1 exponent",
        ARM2,
        _set("joints", 0, "emulation", "rotor_inertia_kgm2", value="3e-5"),
        "joints[0].emulation.rotor_inertia_kgm2",
        ["expected a number (0 <= x)", "'3e-5'", "1.0e-4"],
    ),
    (
        "bool is not a number",
        ARM2,
        _set("joints", 0, "current_limit_a", value=True),
        "joints[0].current_limit_a",
        ["expected a number (0 < x <= 32)", "the boolean True"],
    ),
    (
        "number out of range",
        ARM2,
        _set("joints", 0, "current_limit_a", value=40),
        "joints[0].current_limit_a",
        ["out of range (allowed: 0 < x <= 32)", "found 40"],
    ),
    (
        "zero is not positive",
        ARM2,
        _set("joints", 1, "jerk_limit_dps3", value=0),
        "joints[1].jerk_limit_dps3",
        ["allowed: 0 < x", "found 0"],
    ),
    (
        "negative gain",
        ARM2,
        _set("joints", 1, "kd_nm_per_dps", value=-0.1),
        "joints[1].kd_nm_per_dps",
        ["allowed: 0 <= x", "found -0.1"],
    ),
    (
        "not finite",
        ARM2,
        _set("joints", 0, "gear_ratio", value=float("nan")),
        "joints[0].gear_ratio",
        ["allowed: 0 < x", "found nan"],
    ),
    (
        "infinite position",
        ARM2,
        _set("joints", 0, "position_max_deg", value=float("inf")),
        "joints[0].position_max_deg",
        ["allowed: any finite number", "found inf"],
    ),
    (
        "float is not an integer",
        ARM2,
        _set("joints", 0, "motor_id", value=1.0),
        "joints[0].motor_id",
        ["expected an integer (1 <= x <= 32)", "found 1.0"],
    ),
    (
        "integer out of range",
        ARM2,
        _set("joints", 1, "motor_id", value=33),
        "joints[1].motor_id",
        ["allowed: 1 <= x <= 32", "found 33"],
    ),
    (
        "encoder bits",
        ARM2,
        _set("joints", 1, "encoder_bits", value=20),
        "joints[1].encoder_bits",
        ["allowed: 12 <= x <= 18", "found 20"],
    ),
    (
        "direction",
        ARM2,
        _set("joints", 1, "direction", value=0),
        "joints[1].direction",
        ["allowed: one of 1, -1", "found 0"],
    ),
    (
        "temperature",
        ARM2,
        _set("joints", 1, "temperature_limit_c", value=150),
        "joints[1].temperature_limit_c",
        ["allowed: 0 < x <= 100", "found 150"],
    ),
    ("rate", ARM2, _set("control", "rate_hz", value=0.5), "control.rate_hz", ["allowed: 1 <= x <= 1000", "found 0.5"]),
    (
        "mode",
        ARM2,
        _set("control", "mode", value="velocity"),
        "control.mode",
        ["expected one of position, torque", "the string 'velocity'"],
    ),
    (
        "halt policy",
        ARM2,
        _set("control", "halt_policy", value="brake"),
        "control.halt_policy",
        ["expected one of stop, off, hold", "the string 'brake'"],
    ),
    (
        "flag",
        ARM2,
        _set("control", "gravity_feedforward", value="yes please"),
        "control.gravity_feedforward",
        ["expected true or false", "the string 'yes please'"],
    ),
    (
        "missed replies",
        ARM2,
        _set("safety", "max_missed_replies", value=-1),
        "safety.max_missed_replies",
        ["allowed: 0 <= x <= 100", "found -1"],
    ),
    (
        "voltage",
        ARM2,
        _set("safety", "min_voltage_v", value=0),
        "safety.min_voltage_v",
        ["allowed: 0 < x <= 60", "found 0"],
    ),
    ("empty name", ARM2, _set("name", value=" "), "name", ["expected a non-empty string", "the string ' '"]),
    (
        "transport",
        ARM2,
        _set("bus", "transport", value="usb"),
        "bus.transport",
        ["expected one of can, rs485", "the string 'usb'"],
    ),
    (
        "bitrate",
        ARM2,
        _set("bus", "bitrate", value=250_000),
        "bus.bitrate",
        ["allowed: one of 500000, 1000000", "found 250000"],
    ),
    (
        "baudrate",
        ARM2,
        _set("bus", value={"transport": "rs485", "port": "COM3", "baudrate": 38400}),
        "bus.baudrate",
        ["allowed: one of 9600, 19200, 57600, 115200", "found 38400"],
    ),
    (
        "key of the other bus kind",
        ARM2,
        _set("bus", "port", value="COM3"),
        "bus.port",
        ["unknown key", "allowed keys: bitrate, channel, interface, protocol, transport"],
    ),
    (
        "bus and buses",
        BIMANUAL,
        _set("bus", value={"transport": "can"}),
        "bus",
        ["give bus (one bus) or buses", "both"],
    ),
    ("no bus", ARM2, _delete("bus"), "bus", ["give bus (one bus) or buses", "found neither"]),
    ("buses empty", BIMANUAL, _set("buses", value={}), "buses", ["a non-empty mapping of names", "an empty mapping"]),
    ("bus name", BIMANUAL, _set("buses", "left right", value={}), "buses", ["'left right' is not a name"]),
    (
        "key of a named bus",
        BIMANUAL,
        _set("buses", "right", "port", value="COM3"),
        "buses.right.port",
        ["unknown key", "allowed keys: bitrate, channel, interface, protocol, transport"],
    ),
    (
        "bitrate of a named bus",
        BIMANUAL,
        _set("buses", "left", "bitrate", value=250_000),
        "buses.left.bitrate",
        ["allowed: one of 500000, 1000000", "found 250000"],
    ),
    (
        "joint without its bus",
        BIMANUAL,
        _delete("joints", 7, "bus"),
        "joints[7].bus",
        ["required key is missing", "one of left, right"],
    ),
    ("unknown bus", BIMANUAL, _set("joints", 2, "bus", value="middle"), "joints[2].bus", ["unknown bus 'middle'"]),
    (
        "a bus named on an arm of one bus",
        ARM2,
        _set("joints", 0, "bus", value="left"),
        "joints[0].bus",
        ["this arm has the one `bus:` section", "found 'left'"],
    ),
    (
        "duplicate motor id on one of two buses",
        BIMANUAL,
        _set("joints", 7, "motor_id", value=1),
        "joints[7].motor_id",
        ["1 is already used by joints[6] on bus right (ids are per bus)"],
    ),
    (
        "duplicate motor id",
        ARM2,
        _set("joints", 1, "motor_id", value=1),
        "joints[1].motor_id",
        ["1 is already used by joints[0]"],
    ),
    (
        "duplicate joint name",
        ARM2,
        _set("joints", 1, "name", value="shoulder"),
        "joints[1].name",
        ["'shoulder' is already used by joints[0]"],
    ),
    (
        "position min >= max",
        ARM2,
        _set("joints", 0, "position_min_deg", value=90),
        "joints[0].position_max_deg",
        ["must be greater than position_min_deg (90)", "found 90"],
    ),
    (
        "gains required in torque mode",
        ARM2,
        _delete("joints", 1, "kp_nm_per_deg"),
        "joints[1].kp_nm_per_deg",
        ["required key is missing", "a number, 0 <= x"],
    ),
    ("urdf and chain", ARM2, _set("model", "urdf", value="arm6.urdf"), "model", ["exactly one of urdf", "chain"]),
    ("neither urdf nor chain", ARM2, _delete("model", "chain"), "model", ["exactly one of urdf", "chain"]),
    (
        "tip with urdf",
        ARM6,
        _set("model", "tip_xyz_m", value=[0, 0, 0.1]),
        "model.tip_xyz_m",
        ["allowed only with chain"],
    ),
    (
        "vector length",
        ARM2,
        _set("model", "gravity_m_s2", value=[0, -9.81]),
        "model.gravity_m_s2",
        ["expected a list of 3 numbers [x, y, z]", "a list"],
    ),
    (
        "vector element",
        ARM2,
        _set("model", "gravity_m_s2", value=[0, "down", 0]),
        "model.gravity_m_s2[1]",
        ["expected a number", "the string 'down'"],
    ),
    (
        "zero axis",
        ARM2,
        _set("model", "chain", 0, "axis", value=[0, 0, 0]),
        "model.chain[0].axis",
        ["expected a non-zero vector"],
    ),
    (
        "negative mass",
        ARM2,
        _set("model", "chain", 1, "mass_kg", value=-1),
        "model.chain[1].mass_kg",
        ["allowed: 0 <= x", "found -1"],
    ),
    (
        "unphysical inertia",
        ARM2,
        _set("model", "chain", 0, "inertia_kgm2", "izz", value=0.1),
        "model.chain[0].inertia_kgm2",
        ["not a physical inertia", "none larger than the sum of the other two"],
    ),
    (
        "inertia not positive semi-definite",
        ARM2,
        _set("model", "chain", 0, "inertia_kgm2", "ixy", value=0.05),
        "model.chain[0].inertia_kgm2",
        ["not a physical inertia", "non-negative"],
    ),
    (
        "chain joint not configured",
        ARM2,
        _set("model", "chain", 1, "joint", value="wrist"),
        "model.chain[1].joint",
        ["model.chain joint 'wrist' is not configured", "joints: shoulder, elbow"],
    ),
    (
        "chain joint twice",
        ARM2,
        _set("model", "chain", 1, "joint", value="shoulder"),
        "model.chain[1].joint",
        ["'shoulder' appears twice in model.chain"],
    ),
    (
        "configured joint not in chain",
        ARM2,
        lambda d: d["model"]["chain"].pop(),
        "joints[1].name",
        ["'elbow' is not a revolute joint of model.chain", "found: shoulder"],
    ),
    (
        "frame name clash",
        ARM2,
        _set("model", "chain", 1, "link", value="shoulder"),
        "model.chain[1].link",
        ["frame name 'shoulder' is already used"],
    ),
    (
        "urdf missing",
        ARM6,
        _set("model", "urdf", value="/no/such/arm.urdf"),
        "model.urdf",
        ["file not found: /no/such/arm.urdf"],
    ),
    (
        "renamed joint",
        ARM6,
        _set("joints", 2, "name", value="elbow"),
        "model.urdf",
        ["arm6.urdf joint 'elbow_pitch' is not configured"],
    ),
    (
        "power-on window as wide as a motor turn",
        ARM2,
        _set("joints", 0, "power_on_window_deg", value=[-20.0, 20.0]),
        "joints[0].power_on_window_deg",
        ["a window 40 deg wide", "360 / gear_ratio = 40 deg", "found [-20, 20]"],
    ),
    (
        "power-on window upside down",
        ARM2,
        _set("joints", 0, "power_on_window_deg", value=[5.0, -5.0]),
        "joints[0].power_on_window_deg",
        ["min < max", "found [5, -5]"],
    ),
    (
        "power-on window of one number",
        ARM2,
        _set("joints", 0, "power_on_window_deg", value=[5.0]),
        "joints[0].power_on_window_deg",
        ["a list of 2 numbers [min, max]"],
    ),
    (
        "hard stop inside the limits",
        ARM6,
        _set("joints", 1, "homing", "stop_deg", value=-100.0),
        "joints[1].homing.stop_deg",
        ["outside the joint's limits", "found -100"],
    ),
    (
        "homing faster than the joint",
        ARM6,
        _set("joints", 1, "homing", "speed_dps", value=1000.0),
        "joints[1].homing.speed_dps",
        ["out of range"],
    ),
    (
        "a negative goal tolerance",
        ARM2,
        _set("control", "goal_tolerance_deg", value=-0.1),
        "control.goal_tolerance_deg",
        ["out of range", "found -0.1"],
    ),
    (
        "a goal time of a minute and more",
        ARM2,
        _set("control", "goal_time_s", value=61.0),
        "control.goal_time_s",
        ["out of range", "found 61"],
    ),
    (
        "urdf joint not configured",
        ARM6,
        lambda d: d["joints"].pop(),
        "model.urdf",
        ["joint 'flange_roll' is not configured", "joints: base_yaw, shoulder_pitch"],
    ),
]


@pytest.mark.parametrize(("base", "mutate", "key_path", "fragments"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_validation_error_names_file_key_path_and_range(
    tmp_path: Path, base: dict[str, Any], mutate: Mutation, key_path: str, fragments: list[str]
) -> None:
    data = copy.deepcopy(base)
    mutate(data)
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    error = info.value
    assert (error.file, error.key_path) == (str(path), key_path)
    message = str(error)
    assert message.startswith(f"{path}: {key_path}: ")
    for fragment in fragments:
        assert fragment in message


def test_configured_joint_missing_from_urdf(tmp_path: Path) -> None:
    data = copy.deepcopy(ARM6)
    data["joints"].append(dict(data["joints"][0], name="gripper", motor_id=7))
    match = r"'gripper' is not a revolute joint of .*arm6.urdf \(found: base_yaw,"
    with pytest.raises(ConfigError, match=match) as info:
        parse_config(data, source="mem")
    assert (info.value.file, info.value.key_path) == ("mem", "joints[6].name")


@pytest.mark.parametrize(
    ("old", "new", "fragment"),
    [
        ('name="wrist_roll" type="revolute"', 'name="wrist_roll" type="continuous"', "type 'continuous'; supported"),
        ('name="wrist_roll" type="revolute"', 'name="wrist_roll" type="prismatic"', "type 'prismatic'; supported"),
        ("</robot>", "", "is not valid XML: no element found: line"),
        ("robot", "sdf", "the root element is <sdf>"),
    ],
)
def test_urdf_errors(tmp_path: Path, old: str, new: str, fragment: str) -> None:
    data = copy.deepcopy(ARM6)
    _write_urdf(data, tmp_path, old, new)
    with pytest.raises(ConfigError) as info:
        parse_config(data, source="mem")
    assert info.value.key_path == "model.urdf"
    assert fragment in str(info.value)


def test_fixed_joints_and_joint_order_are_free(tmp_path: Path) -> None:
    data = copy.deepcopy(ARM6)
    data["joints"].reverse()
    config = parse_config(data)
    assert config.joint_names[0] == "flange_roll"
    assert isinstance(config, ArmConfig)


def test_parse_config_resolves_relative_urdf_against_base_dir() -> None:
    data = copy.deepcopy(ARM6)
    data["model"]["urdf"] = "arm6.urdf"
    assert parse_config(data, base_dir=CONFIGS).model.urdf == CONFIGS / "arm6.urdf"


def test_a_joints_actuator_model_fills_its_published_figures(tmp_path: Path) -> None:
    # issue 33 §9: `actuator:` fills gear_ratio, torque_constant_nm_per_a (motor side: rated torque / rated current /
    # reduction) and current_limit_a (the published peak, where the torque command carries it); each stays
    # overridable; where the peak is not published or is beyond 32 A the current limit must be given
    def joint0(**keys: Any) -> dict[str, Any]:
        data = copy.deepcopy(ARM2)
        for key in ("gear_ratio", "torque_constant_nm_per_a", "current_limit_a"):
            data["joints"][0].pop(key)
        data["joints"][0].update(keys)
        return data

    joint = parse_config(joint0(actuator="X4-10"), source="mem", base_dir=CONFIGS).joints[0]
    assert (joint.actuator, joint.gear_ratio, joint.current_limit_a) == ("X4-10", 12.6, 19.5)
    assert joint.torque_constant_nm_per_a == pytest.approx(4.0 / 7.8 / 12.6)
    # the L series' direct drive (1:1, the driver's 15 A instant current) and an MG model (stall current as peak)
    joint = parse_config(joint0(actuator="L-7015"), source="mem", base_dir=CONFIGS).joints[0]
    assert (joint.gear_ratio, joint.current_limit_a) == (1.0, 15.0)
    assert joint.torque_constant_nm_per_a == pytest.approx(1.0 / 3.62)
    joint = parse_config(joint0(actuator="MG4010-10"), source="mem", base_dir=CONFIGS).joints[0]
    assert (joint.gear_ratio, joint.current_limit_a) == (10.0, 6.97)
    assert joint.torque_constant_nm_per_a == pytest.approx(2.5 / 3.5 / 10.0)
    joint = parse_config(
        joint0(actuator="X8-90", current_limit_a=12.0, gear_ratio=9.0), source="mem", base_dir=CONFIGS
    ).joints[0]
    assert (joint.gear_ratio, joint.current_limit_a) == (9.0, 12.0)  # the file's keys win
    assert joint.torque_constant_nm_per_a == pytest.approx(25.0 / 10.0 / 18.0)
    for model, why in (
        ("X8-90", "its peak current is not in the table"),
        ("X12-320", "its peak 100 A exceeds the 32 A"),
    ):
        with pytest.raises(ConfigError, match=rf"joints\[0\]\.current_limit_a: .*{model} \(required: {why}") as info:
            parse_config(joint0(actuator=model), source="mem", base_dir=CONFIGS)
        assert info.value.key_path == "joints[0].current_limit_a"
    with pytest.raises(
        ConfigError, match=r"joints\[0\]\.actuator: one of the models of the table \(X4-V2, .*found 'X9'"
    ):
        parse_config(joint0(actuator="X9"), source="mem", base_dir=CONFIGS)
