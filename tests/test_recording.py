"""Recordings as MCAP with ROS 2 message types (issue 34), read back with a reader we did not write: ``rosbags``."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.writer import Writer
from rosbags.highlevel import AnyReader

from kinematics.frames import LinkTransform
from motion.api import Arm
from motion.cli import main
from motion.config import load_config
from motion.telemetry import TelemetryLog, TelemetryOptions, load_log
from motion.telemetry.mcap import (
    CYCLE_ARRAYS,
    SCHEMAS,
    bus_frame,
    cycle_message,
    diagnostic_array,
    joint_state,
    tf_message,
)
from tests.test_telemetry import CONFIGS

ARM6 = CONFIGS / "arm6.yaml"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, TelemetryLog, int]:
    """arm6 in simulated time: a move, then an E-stop; recorded with its bus trace."""
    out = tmp_path_factory.mktemp("recording")
    options = TelemetryOptions(log=out / "run.mcap", trace=out / "run.log")
    with Arm.from_config(ARM6, emulate=True, telemetry=options) as arm:
        arm.move_to({"shoulder_pitch": 20.0, "elbow_pitch": -30.0, "wrist_roll": 15.0})
        arm.stop()
        arm.sleep(0.05)
    assert arm.telemetry is not None and arm.telemetry.result is not None and arm.telemetry.trace is not None
    return out / "run.mcap", arm.telemetry.result, len(arm.telemetry.trace)


def _read(path: Path) -> dict[str, list[Any]]:
    """Every message of the file, decoded by rosbags, per topic (and each topic's type)."""
    topics: dict[str, list[Any]] = {}
    with AnyReader([path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/joint_states": "sensor_msgs/msg/JointState",
            "/joint_states/reference": "sensor_msgs/msg/JointState",
            "/joint_states/expected": "sensor_msgs/msg/JointState",
            "/rmd_motion/cycle": "rmd_motion/msg/Cycle",
            "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
            "/bus/frames": "rmd_motion/msg/BusFrame",
            "/robot_description": "std_msgs/msg/String",
            "/tf": "tf2_msgs/msg/TFMessage",
        }
        for connection, _, raw in reader.messages():
            topics.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    return topics


def _seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def test_rosbags_reads_every_topic_and_the_values_the_run_measured(recorded: tuple[Path, TelemetryLog, int]) -> None:
    path, log, frames = recorded
    topics = _read(path)
    n, names = log.cycles, log.joint_names
    measured = topics["/joint_states"]
    assert len(measured) == n > 100  # one message per cycle
    per_amp = np.array([j["torque_nm_per_a"] for j in log.meta["joints"]])
    assert all(np.isfinite(per_amp)) and per_amp[1] != 0
    for k in (0, n // 2, n - 1):
        state = measured[k]
        assert list(state.name) == names
        assert np.array_equal(state.position, np.radians(log["q_deg"][k]))
        assert np.array_equal(state.velocity, np.radians(log["qd_dps"][k]))
        assert np.array_equal(state.effort, log["iq_a"][k] * per_amp)
        # simulated time: the stamp is the cycle's time on the controller's clock
        assert _seconds(state.header.stamp) == pytest.approx(log.meta["t0_s"] + log["t_s"][k], abs=1e-9)
        reference = topics["/joint_states/reference"][k]
        assert np.array_equal(reference.position, np.radians(log["q_ref_deg"][k]))
        assert _seconds(reference.header.stamp) == pytest.approx(_seconds(state.header.stamp) + log.period_s, abs=2e-9)
        assert np.array_equal(topics["/joint_states/expected"][k].position, np.radians(log["q_exp_deg"][k]))
        cycle = topics["/rmd_motion/cycle"][k]
        assert cycle.cycle == log["cycle"][k] and cycle.t_s == log["t_s"][k]
        assert np.array_equal(cycle.iq_a, log["iq_a"][k])
        assert np.array_equal(cycle.following_error_deg, log.following_error_deg()[k], equal_nan=True)
        assert np.array_equal(cycle.collision_signal_nm, log["collision_signal_nm"][k], equal_nan=True)
    states = [c.state for c in topics["/rmd_motion/cycle"]]
    assert "moving" in states and states[-1] == "halted"
    statuses = [s for array in topics["/diagnostics"] for s in array.status]
    faults = [s for s in statuses if s.name == "rmd_motion/fault"]
    assert [dict((v.key, v.value) for v in s.values)["kind"] for s in faults] == list(log["fault_kind"]) == ["stop"]
    assert faults[0].level == 1 and faults[0].message == log["fault_text"][0]  # a stop asked for: WARN, not ERROR
    detected = log.meta["t0_s"] + log["fault_t_s"][0]
    (stamped,) = [a for a in topics["/diagnostics"] if a.status[0].name == "rmd_motion/fault"]
    assert _seconds(stamped.header.stamp) == pytest.approx(detected, abs=1e-9)
    changes = [s.message for s in statuses if s.name == "rmd_motion/state"]
    assert changes[:3] == ["ready", "moving", "ready"] and "halted" in changes
    bus = topics["/bus/frames"]
    assert len(bus) == frames and {f.received for f in bus} == {True, False}
    # the frames on the cycles' clock: the first cycle's set-points went out within its period
    first_cycle = _seconds(measured[0].header.stamp)
    sent = [_seconds(f.stamp) for f in bus if not f.received and bytes(f.data)[0] == 0xA4]
    assert 0.0 <= min(s for s in sent if s >= first_cycle) - first_cycle < log.period_s
    assert any(f.arbitration_id == 0x141 and bytes(f.data)[0] == 0xA4 and not f.received for f in bus)
    (description,) = topics["/robot_description"]
    _drawn_as_configured(description.data, ARM6)


def test_the_link_transforms_place_the_arm_as_its_model_does(recorded: tuple[Path, TelemetryLog, int]) -> None:
    import pinocchio as pin

    path, log, _ = recorded
    tf = _read(path)["/tf"]
    assert len(tf) == log.cycles
    last = {t.child_frame_id: t for t in tf[-1].transforms}
    assert set(last) == {
        "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "flange_link", "tool0"
    }  # fmt: skip
    # chain the transforms from the root to the tool and compare with Pinocchio's forward kinematics
    pose, frame = pin.SE3.Identity(), "tool0"
    while frame in last:
        t = last[frame].transform
        rotation = pin.Quaternion(t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z).matrix()
        pose = pin.SE3(rotation, np.array([t.translation.x, t.translation.y, t.translation.z])) * pose
        frame = last[frame].header.frame_id
    assert frame == "base_link"
    model = pin.buildModelFromUrdf(str(CONFIGS / "arm6.urdf"))
    data = model.createData()
    q = np.radians(log["q_deg"][-1])  # (arm6's model order is its configuration order)
    pin.framesForwardKinematics(model, data, q)
    expected = data.oMf[model.getFrameId("tool0")]
    assert np.allclose(pose.translation, expected.translation, atol=1e-9)
    assert np.allclose(pose.rotation, expected.rotation, atol=1e-9)


def test_load_log_rebuilds_the_run_from_the_recording(recorded: tuple[Path, TelemetryLog, int]) -> None:
    path, log, _ = recorded
    again = load_log(path)
    assert set(again.columns) == set(log.columns)
    for name, column in log.columns.items():
        assert again[name].dtype == column.dtype, name
        assert np.array_equal(again[name], column, equal_nan=column.dtype.kind == "f"), name
    assert again.meta == dict(log.meta)


def test_export_writes_the_columns_for_numpy(
    recorded: tuple[Path, TelemetryLog, int], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, log, _ = recorded
    out = tmp_path / "run.npz"
    before = path.read_bytes()
    assert main(["export", str(path), str(path)]) == 2  # (never over the recording)
    assert main(["export", str(path), str(tmp_path / "run.txt")]) == 2
    assert "name it OUT.npz, found" in capsys.readouterr().err and path.read_bytes() == before
    with pytest.raises(ValueError, match=r"run\.npz: save writes MCAP"):
        log.save(out)
    trace = path.with_suffix(".log")  # (the candump trace beside it: text)
    assert main(["export", str(trace), str(out)]) == 2
    assert "not a telemetry log (neither an MCAP recording nor an .npz exported from one)" in capsys.readouterr().err
    assert main(["plot", str(path), "-o", str(tmp_path / "run.txt")]) == 2
    assert "plot draws a PNG: name it OUT.png" in capsys.readouterr().err
    assert main(["export", str(path), str(out)]) == 0
    with np.load(out) as archive:
        assert np.array_equal(archive["q_deg"], log["q_deg"]) and str(archive["fault_kind"][0]) == "stop"
    assert np.array_equal(load_log(out)["iq_a"], log["iq_a"])
    assert main(["export", str(tmp_path / "missing.mcap"), str(out)]) == 2


def test_a_log_not_named_mcap_is_refused_before_anything_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ValueError, match=r"run\.npz: a run is recorded as MCAP: name it FILE\.mcap"):
        TelemetryOptions(log=tmp_path / "run.npz")
    code = main(["move", "--config", str(ARM6), "--emulate", "base_yaw=5", "--log", str(tmp_path / "run.npz")])
    assert code == 2
    assert "--log" in capsys.readouterr().err and not (tmp_path / "run.npz").exists()


def test_an_mcap_file_of_another_program_is_not_a_run(tmp_path: Path) -> None:
    stream = io.BytesIO()
    writer = Writer(stream)
    schema = writer.register_msgdef("std_msgs/msg/String", "string data\n")
    writer.write_message("/chatter", schema, {"data": "hello"}, log_time=1, publish_time=1)
    writer.finish()
    (tmp_path / "other.mcap").write_bytes(stream.getvalue())
    with pytest.raises(ValueError, match="other.mcap: an MCAP file without the 'rmd_motion' metadata record"):
        load_log(tmp_path / "other.mcap")
    (tmp_path / "cut.mcap").write_bytes(stream.getvalue()[:40])
    with pytest.raises(ValueError, match="cut.mcap: not a readable MCAP recording"):
        load_log(tmp_path / "cut.mcap")


def test_a_chain_model_hangs_its_links_from_the_world_and_is_drawn_from_a_urdf_written_from_it(tmp_path: Path) -> None:
    config = load_config(CONFIGS / "arm2.yaml")
    options = TelemetryOptions(log=tmp_path / "arm2.mcap")
    with Arm(config, emulate=True, telemetry=options) as arm:
        arm.move_to({"shoulder": 10.0})
    with AnyReader([tmp_path / "arm2.mcap"]) as reader:
        topics = {c.topic for c in reader.connections}
        assert {"/robot_description", "/tf"} <= topics
        (tf,) = [c for c in reader.connections if c.topic == "/tf"]
        for _, _, raw in reader.messages(connections=[tf]):
            message: Any = reader.deserialize(raw, tf.msgtype)
        (described,) = [c for c in reader.connections if c.topic == "/robot_description"]
        for _, _, raw in reader.messages(connections=[described]):
            urdf = reader.deserialize(raw, described.msgtype).data  # type: ignore[attr-defined]
    _drawn_as_configured(urdf, CONFIGS / "arm2.yaml")
    parents = {t.child_frame_id: t.header.frame_id for t in message.transforms}
    assert parents == {"upper_arm": "universe", "forearm": "upper_arm"}
    shoulder = load_log(tmp_path / "arm2.mcap")["q_deg"][-1][0]
    rotation = message.transforms[0].transform.rotation
    assert 2 * math.degrees(math.atan2(math.hypot(rotation.x, rotation.y, rotation.z), rotation.w)) == pytest.approx(
        abs(shoulder), abs=1e-6
    )


def _their_encoding(kind: str, message: dict[str, Any]) -> bytes:
    """``mcap-ros2-support``'s encoding of ``message`` (written with its writer, read back raw)."""
    stream = io.BytesIO()
    writer = Writer(stream)
    writer.write_message("/t", writer.register_msgdef(kind, SCHEMAS[kind]), message, log_time=0, publish_time=0)
    writer.finish()
    stream.seek(0)
    ((_, _, raw),) = make_reader(stream).iter_messages()
    return bytes(raw.data)


def test_the_cdr_shim_encodes_as_the_reference_encoder_does() -> None:
    stamp = {"sec": 1_700_000_000, "nanosec": 123_456_789}
    ns = 1_700_000_000_123_456_789
    names = ["base_yaw", "schulter_ä", ""]
    ours = joint_state(ns, names, [0.1, -2.5, 3.0], [1.0, 2.0, 3.0], [])
    theirs = {"header": {"stamp": stamp, "frame_id": ""}, "name": names, "position": [0.1, -2.5, 3.0]}
    assert ours == _their_encoding("sensor_msgs/msg/JointState", theirs | {"velocity": [1.0, 2.0, 3.0], "effort": []})
    values = {"kind": "stop", "joint": ""}
    ours = diagnostic_array(ns, 2, "rmd_motion/fault", "stop: E-stop 5 °C", hardware_id="elbow", values=values)
    status = {"level": 2, "name": "rmd_motion/fault", "message": "stop: E-stop 5 °C", "hardware_id": "elbow"}
    status["values"] = [{"key": k, "value": v} for k, v in values.items()]
    diagnostics = {"header": {"stamp": stamp, "frame_id": ""}, "status": [status]}
    assert ours == _their_encoding("diagnostic_msgs/msg/DiagnosticArray", diagnostics)
    for received, ident, data, bus in (
        (True, 0x141, b"\xa4\x00\x01\x02\x03\x04\x05\x06", ""),
        (False, -1, b"\x3e", "right"),
    ):
        frame = {"stamp": stamp, "received": received, "arbitration_id": ident, "data": data, "bus": bus}
        assert bus_frame(ns, received, ident, data, bus) == _their_encoding("rmd_motion/msg/BusFrame", frame)
    link = LinkTransform("base_link", "shoulder_link", (0.0, 0.1, 0.12), (0.0, 0.0, 0.38268343, 0.92387953))
    transform = {"translation": {"x": 0.0, "y": 0.1, "z": 0.12}}
    transform["rotation"] = {"x": 0.0, "y": 0.0, "z": 0.38268343, "w": 0.92387953}
    tf = {"header": {"stamp": stamp, "frame_id": "base_link"}, "child_frame_id": "shoulder_link"}
    assert tf_message(ns, [link, link]) == _their_encoding(
        "tf2_msgs/msg/TFMessage", {"transforms": [tf | {"transform": transform}] * 2}
    )
    cycle = {"stamp": stamp, "t_s": 0.25, "cycle": 2**40, "jitter_s": 1e-5, "busy_s": math.nan, "latency_s": 0.001}
    cycle |= {"state": "moving", "following_error_deg": [0.5, -0.5], "fresh": [True, False], "limited": [False, True]}
    cycle |= {name: [float(i), -1.5] for i, name in enumerate(CYCLE_ARRAYS)}
    columns = {name: np.array([value]) for name, value in cycle.items() if name not in ("stamp", "state")}
    ours = cycle_message(ns, columns, 0, "moving", columns["following_error_deg"])
    assert ours == _their_encoding("rmd_motion/msg/Cycle", cycle)


def _drawn_as_configured(urdf: str, config_path: Path) -> None:
    """The published URDF: every moving link drawn (a ``<visual>``), and the same arm as the configuration's model:
    its joints, their limits, and its forward kinematics at a pose within them."""
    import pinocchio as pin

    from kinematics.model import build_arm

    config = load_config(config_path)
    published = pin.buildModelFromXML(urdf)
    configured = build_arm(config)
    names = list(config.joint_names)
    assert [str(n) for n in published.names[1:]] == [str(n) for n in configured.model.names[1:]]
    for name in names:
        joint = config.joints[names.index(name)]
        j = published.getJointId(name)
        lower, upper = (
            published.lowerPositionLimit[published.idx_qs[j]],
            published.upperPositionLimit[published.idx_qs[j]],
        )
        expected = (math.radians(joint.position_min_deg), math.radians(joint.position_max_deg))
        assert (lower, upper) == pytest.approx(expected, abs=1e-4)  # (a URDF's limits as its text rounds them)
    root = ElementTree.fromstring(urdf)
    moved = {child.get("link") for j in root.iter("joint") if j.get("type") != "fixed" for child in j.iter("child")}
    assert moved and all(link.find("visual") is not None for link in root.iter("link") if link.get("name") in moved)
    pose = np.radians([0.5 * (j.position_min_deg + j.position_max_deg) + 3.0 for j in config.joints])
    q = np.zeros(published.nq)
    q[[published.idx_qs[published.getJointId(n)] for n in names]] = pose
    data = published.createData()
    pin.framesForwardKinematics(published, data, q)
    q_model = np.zeros(configured.model.nq)
    q_model[configured.to_config] = pose
    pin.framesForwardKinematics(configured.model, configured.data, q_model)
    for name in names:
        mine = data.oMi[published.getJointId(name)]
        theirs = configured.data.oMi[configured.model.getJointId(name)]
        assert np.allclose(mine.homogeneous, theirs.homogeneous, atol=1e-5), name


def test_the_file_is_in_time_order(recorded: tuple[Path, TelemetryLog, int]) -> None:
    # messages as written (not sorted by a reader's index): log times never go back, faults and frames among the cycles
    path, _, _ = recorded
    with path.open("rb") as stream:
        written = [
            (channel.topic, m.log_time) for _, channel, m in make_reader(stream).iter_messages(log_time_order=False)
        ]
    times = [t for _, t in written]
    assert times == sorted(times)
    topics = [topic for topic, _ in written]
    assert (
        topics.index("/bus/frames")
        < topics.index("/rmd_motion/cycle")
        < len(topics) - topics[::-1].index("/bus/frames")
    )
