"""A run's recording as MCAP with ROS 2 message types (CDR): Foxglove, PlotJuggler, Rerun and ``ros2 bag`` open it,
and so does ``rosbags`` (pure Python), without a ROS installation.

Topics (every message's header stamp, and its log time, is the cycle's time: the controller's clock since its epoch in
a simulated run, so two simulated runs give the same messages; Unix time in real time):

=============================  =================================  ===================================================
topic                          type                               content
=============================  =================================  ===================================================
``/joint_states``              ``sensor_msgs/msg/JointState``     measured, one per cycle: position (rad), velocity
                                                                  (rad/s), effort (N·m: the torque current through
                                                                  the joint's torque constant, gear and direction)
``/joint_states/reference``    ``sensor_msgs/msg/JointState``     the reference (position, velocity; effort: the
                                                                  torque asked for, torque mode), stamped at its
                                                                  set-point instant, one period after the cycle
``/joint_states/expected``     ``sensor_msgs/msg/JointState``     where each joint should be under its control loop
``/rmd_motion/cycle``          ``rmd_motion/msg/Cycle``           the whole row of the per-cycle log (the columns of
                                                                  :mod:`motion.telemetry`, their units) with the
                                                                  following error and the arm's state
``/diagnostics``               ``diagnostic_msgs/msg/             each fault at its detection (level ERROR; values:
                               DiagnosticArray``                  ``t_s``, ``halt_s``, ``kind``, ``joint``,
                                                                  ``action``) and each change of the arm's state (OK)
``/bus/frames``                ``rmd_motion/msg/BusFrame``        every frame on the bus (``--trace``), as sent or
                                                                  taken in; ``arbitration_id`` -1 on RS485
``/robot_description``         ``std_msgs/msg/String``            the URDF, once (a URDF model only)
``/tf``                        ``tf2_msgs/msg/TFMessage``         each link's pose in its parent's frame, per cycle
=============================  =================================  ===================================================

The metadata record ``rmd_motion`` holds ``meta``: the log's metadata as JSON (see :mod:`motion.telemetry`).
:func:`read_mcap` rebuilds the :class:`~motion.telemetry.TelemetryLog` from ``/rmd_motion/cycle``, the faults of
``/diagnostics`` and that record.

Writing happens after the run (the control loop only fills preallocated rows); ``mcap`` and ``mcap-ros2-support``
serialise the messages.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from typing import IO, TYPE_CHECKING, Any, Final, Protocol

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

if TYPE_CHECKING:
    from motion.telemetry import TelemetryLog, TracedFrame

#: The metadata record's name.
METADATA: Final = "rmd_motion"
CYCLE_TOPIC: Final = "/rmd_motion/cycle"
DIAGNOSTICS_TOPIC: Final = "/diagnostics"
#: The diagnostic status names of faults and of state changes.
FAULT_NAME: Final = "rmd_motion/fault"
STATE_NAME: Final = "rmd_motion/state"
#: MCAP's magic bytes (the first eight of every file).
MAGIC: Final = b"\x89MCAP0\r\n"

_SEPARATOR = "=" * 80
_TIME = "int32 sec\nuint32 nanosec"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id"
_DEPENDENCIES = {
    "builtin_interfaces/Time": _TIME,
    "std_msgs/Header": _HEADER,
    "diagnostic_msgs/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\n"
        "string hardware_id\nKeyValue[] values"
    ),
    "diagnostic_msgs/KeyValue": "string key\nstring value",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
}


def _definition(text: str, *dependencies: str) -> str:
    """A ``ros2msg`` schema: the message's text, then each type it uses (MCAP's concatenated form)."""
    parts = [text]
    for name in dependencies:
        parts += [_SEPARATOR, f"MSG: {name}", _DEPENDENCIES[name]]
    return "\n".join(parts) + "\n"


#: The cycle message: every column of the per-cycle log (scalars, then per joint in configuration order).
CYCLE_SCALARS: Final = ("jitter_s", "busy_s", "latency_s")
CYCLE_ARRAYS: Final = (
    "q_ref_deg",
    "qd_ref_dps",
    "qdd_ref_dps2",
    "q_deg",
    "q_exp_deg",
    "qd_dps",
    "iq_a",
    "temperature_c",
    "cmd_angle_deg",
    "cmd_speed_dps",
    "cmd_torque_nm",
    "residual_nm",
    "collision_signal_nm",
    "collision_limit_nm",
)
CYCLE_FLAGS: Final = ("fresh", "limited")
_CYCLE = "\n".join(
    [
        "builtin_interfaces/Time stamp",
        "float64 t_s",
        "int64 cycle",
        *(f"float64 {name}" for name in CYCLE_SCALARS),
        "string state",
        *(f"float64[] {name}" for name in CYCLE_ARRAYS),
        "float64[] following_error_deg",
        *(f"bool[] {name}" for name in CYCLE_FLAGS),
    ]
)
SCHEMAS: Final = {
    "sensor_msgs/msg/JointState": _definition(
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ),
    "rmd_motion/msg/Cycle": _definition(_CYCLE, "builtin_interfaces/Time"),
    "diagnostic_msgs/msg/DiagnosticArray": _definition(
        "std_msgs/Header header\nDiagnosticStatus[] status",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue",
    ),
    "rmd_motion/msg/BusFrame": _definition(
        "builtin_interfaces/Time stamp\nbool received\nint32 arbitration_id\nuint8[] data", "builtin_interfaces/Time"
    ),
    "std_msgs/msg/String": _definition("string data"),
    "tf2_msgs/msg/TFMessage": _definition(
        "geometry_msgs/TransformStamped[] transforms",
        "geometry_msgs/TransformStamped",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/Transform",
        "geometry_msgs/Vector3",
        "geometry_msgs/Quaternion",
    ),
}


class LinkPose(Protocol):
    """One link's pose in its parent's frame (:class:`kinematics.frames.LinkTransform`)."""

    @property
    def parent(self) -> str: ...
    @property
    def child(self) -> str: ...
    @property
    def translation_m(self) -> tuple[float, float, float]: ...
    @property
    def rotation_xyzw(self) -> tuple[float, float, float, float]: ...


class Robot(Protocol):
    """The arm's shape for ``/robot_description`` and ``/tf`` (:class:`kinematics.frames.LinkFrames`)."""

    urdf: str | None

    def transforms(self, q_deg: Any) -> Sequence[LinkPose]: ...


def _ns(t_s: float) -> int:
    return max(0, round(t_s * 1e9))


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _values(row: Any) -> list[float]:
    return [float(v) for v in row]


class _Channels:
    """The writer and one registered schema per message type."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.writer = Writer(stream)
        self._schemas: dict[str, Any] = {}

    def write(self, topic: str, kind: str, message: dict[str, Any], log_ns: int) -> None:
        schema = self._schemas.get(kind)
        if schema is None:
            schema = self._schemas[kind] = self.writer.register_msgdef(kind, SCHEMAS[kind])
        self.writer.write_message(topic, schema, message, log_time=log_ns, publish_time=log_ns)


def _joint_state(ns: int, names: list[str], position: Any, velocity: Any = (), effort: Any = ()) -> dict[str, Any]:
    return {
        "header": {"stamp": _stamp(ns), "frame_id": ""},
        "name": names,
        "position": _values(position),
        "velocity": _values(velocity),
        "effort": _values(effort),
    }


def _status(level: int, name: str, message: str, hardware_id: str, values: dict[str, str]) -> dict[str, Any]:
    return {
        "level": level,
        "name": name,
        "message": message,
        "hardware_id": hardware_id,
        "values": [{"key": k, "value": v} for k, v in values.items()],
    }


def time_base_s(meta: dict[str, Any] | Any) -> float:
    """The stamp of a log's ``t_s = 0``: the controller's clock in a simulated run, else Unix time."""
    return float(meta["t0_s"]) if meta.get("simulated") else float(meta["t0_wall_unix_s"])


def write_mcap(
    log: TelemetryLog,
    stream: IO[bytes],
    *,
    robot: Robot | None = None,
    frames: Iterable[TracedFrame] = (),
    frames_base_s: float = 0.0,
) -> None:
    """Write ``log`` as MCAP (the module docstring's topics); ``robot`` adds ``/robot_description`` and ``/tf``,
    ``frames`` (times on their own clock, ``frames_base_s`` added) ``/bus/frames``."""
    meta, columns = log.meta, log.columns
    names = log.joint_names
    base_s = time_base_s(meta)
    period_s = log.period_s
    out = _Channels(stream)
    per_amp = np.array([float(j.get("torque_nm_per_a", math.nan)) for j in meta["joints"]])
    states = list(meta.get("states", ()))
    t, q, qd, iq = columns["t_s"], columns["q_deg"], columns["qd_dps"], columns["iq_a"]
    torque_mode = meta.get("mode") == "torque"
    following = log.following_error_deg()
    previous_state = ""
    if robot is not None and robot.urdf is not None:
        first = _ns(base_s + (float(t[0]) if len(t) else 0.0))
        out.write("/robot_description", "std_msgs/msg/String", {"data": robot.urdf}, first)
    for k in range(len(t)):
        ns = _ns(base_s + float(t[k]))
        stamp = _stamp(ns)
        out.write(
            "/joint_states",
            "sensor_msgs/msg/JointState",
            _joint_state(ns, names, np.radians(q[k]), np.radians(qd[k]), iq[k] * per_amp),
            ns,
        )
        ahead = _ns(base_s + float(t[k]) + period_s)
        effort = columns["cmd_torque_nm"][k] if torque_mode else ()
        reference = _joint_state(
            ahead, names, np.radians(columns["q_ref_deg"][k]), np.radians(columns["qd_ref_dps"][k])
        )
        reference["effort"] = _values(effort)
        out.write("/joint_states/reference", "sensor_msgs/msg/JointState", reference, ns)
        out.write(
            "/joint_states/expected",
            "sensor_msgs/msg/JointState",
            _joint_state(ns, names, np.radians(columns["q_exp_deg"][k])),
            ns,
        )
        code = int(columns["state"][k])
        state = states[code] if 0 <= code < len(states) else ""
        cycle: dict[str, Any] = {"stamp": stamp, "t_s": float(t[k]), "cycle": int(columns["cycle"][k]), "state": state}
        for name in CYCLE_SCALARS:
            cycle[name] = float(columns[name][k])
        for name in CYCLE_ARRAYS:
            cycle[name] = _values(columns[name][k])
        cycle["following_error_deg"] = _values(following[k])
        for name in CYCLE_FLAGS:
            cycle[name] = [bool(v) for v in columns[name][k]]
        out.write(CYCLE_TOPIC, "rmd_motion/msg/Cycle", cycle, ns)
        if state != previous_state and state:
            status = _status(0, STATE_NAME, state, "", {"t_s": repr(float(t[k])), "from": previous_state})
            diagnostics = {"header": {"stamp": stamp, "frame_id": ""}, "status": [status]}
            out.write(DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", diagnostics, ns)
            previous_state = state
        if robot is not None:
            out.write("/tf", "tf2_msgs/msg/TFMessage", _tf(robot, stamp, q[k]), ns)
    for f in range(len(columns["fault_t_s"])):
        detected = float(columns["fault_t_s"][f])
        ns = _ns(base_s + detected)
        values = {
            "index": str(f),
            "t_s": repr(detected),
            "halt_s": repr(float(columns["fault_halt_s"][f])),
            "kind": str(columns["fault_kind"][f]),
            "joint": str(columns["fault_joint"][f]),
            "action": str(columns["fault_action"][f]),
        }
        status = _status(2, FAULT_NAME, str(columns["fault_text"][f]), values["joint"], values)
        diagnostics = {"header": {"stamp": _stamp(ns), "frame_id": ""}, "status": [status]}
        out.write(DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", diagnostics, ns)
    for frame in frames:
        ns = _ns(frames_base_s + frame.time_s)
        message = {
            "stamp": _stamp(ns),
            "received": frame.received,
            "arbitration_id": -1 if frame.arbitration_id is None else frame.arbitration_id,
            "data": frame.data,
        }
        out.write("/bus/frames", "rmd_motion/msg/BusFrame", message, ns)
    out.writer.add_metadata(METADATA, {"meta": json.dumps(meta, allow_nan=False)})
    out.writer.finish()  # type: ignore[no-untyped-call]


def _tf(robot: Robot, stamp: dict[str, int], q_deg: Any) -> dict[str, Any]:
    transforms = []
    for link in robot.transforms(q_deg):
        x, y, z = link.translation_m
        qx, qy, qz, qw = link.rotation_xyzw
        transforms.append(
            {
                "header": {"stamp": stamp, "frame_id": link.parent},
                "child_frame_id": link.child,
                "transform": {
                    "translation": {"x": x, "y": y, "z": z},
                    "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
                },
            }
        )
    return {"transforms": transforms}


def is_mcap(path: Any) -> bool:
    """The file begins with MCAP's magic bytes."""
    with open(path, "rb") as stream:
        return stream.read(len(MAGIC)) == MAGIC


def read_mcap(stream: IO[bytes]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The columns and metadata of a recording written by :func:`write_mcap` (the caller checks them).

    Raises:
        ValueError: not such a recording (no ``rmd_motion`` metadata, or unreadable).
    """
    try:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        meta: dict[str, Any] | None = None
        for record in reader.iter_metadata():
            if record.name == METADATA:
                meta = json.loads(record.metadata["meta"])
        if meta is None:
            raise ValueError(f"an MCAP file without the {METADATA!r} metadata record (not written by rmd-motion)")
        states = list(meta.get("states", ()))
        rows: dict[str, list[Any]] = {name: [] for name in ("t_s", "cycle", "state", *CYCLE_SCALARS)}
        rows |= {name: [] for name in (*CYCLE_ARRAYS, *CYCLE_FLAGS)}
        faults: list[dict[str, str]] = []
        for _, _, _, message in reader.iter_decoded_messages(topics=[CYCLE_TOPIC, DIAGNOSTICS_TOPIC]):
            if hasattr(message, "status"):
                faults += [
                    {value.key: value.value for value in status.values} | {"text": status.message}
                    for status in message.status
                    if status.name == FAULT_NAME
                ]
                continue
            rows["t_s"].append(message.t_s)
            rows["cycle"].append(message.cycle)
            rows["state"].append(states.index(message.state) if message.state in states else 0)
            for name in (*CYCLE_SCALARS, *CYCLE_ARRAYS, *CYCLE_FLAGS):
                rows[name].append(getattr(message, name))
    except ValueError:
        raise
    except Exception as exc:  # (the mcap reader raises its own errors, struct's and decoders' on a damaged file)
        raise ValueError(f"not a readable MCAP recording ({type(exc).__name__}: {exc})") from exc
    joints = len(meta["joints"])
    columns: dict[str, Any] = {
        "t_s": np.array(rows["t_s"], dtype=np.float64),
        "cycle": np.array(rows["cycle"], dtype=np.int64),
        "state": np.array(rows["state"], dtype=np.int8),
    }
    for name in CYCLE_SCALARS:
        columns[name] = np.array(rows[name], dtype=np.float64)
    for name in CYCLE_ARRAYS:
        columns[name] = np.array(rows[name], dtype=np.float64).reshape(-1, joints)
    for name in CYCLE_FLAGS:
        columns[name] = np.array(rows[name], dtype=np.bool_).reshape(-1, joints)
    faults.sort(key=lambda f: int(f["index"]))
    columns["fault_t_s"] = np.array([float(f["t_s"]) for f in faults], dtype=np.float64)
    columns["fault_halt_s"] = np.array([float(f["halt_s"]) for f in faults], dtype=np.float64)
    for key in ("kind", "joint", "action", "text"):
        columns[f"fault_{key}"] = np.array([f[key] for f in faults], dtype=np.str_)
    return columns, meta
