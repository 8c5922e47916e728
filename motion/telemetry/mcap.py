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
                                                                  taken in; ``arbitration_id`` -1 on RS485;
                                                                  ``bus`` its bus's name (an arm of several buses)
``/robot_description``         ``std_msgs/msg/String``            the URDF a viewer draws the arm from, once
                                                                  (:class:`kinematics.frames.LinkFrames`)
``/tf``                        ``tf2_msgs/msg/TFMessage``         each link's pose in its parent's frame, per cycle
=============================  =================================  ===================================================

The metadata record ``rmd_motion`` holds ``meta``: the log's metadata as JSON (see :mod:`motion.telemetry`).
:func:`read_mcap` rebuilds the :class:`~motion.telemetry.TelemetryLog` from ``/rmd_motion/cycle``, the faults of
``/diagnostics`` and that record.

Writing happens after the run (the control loop only fills preallocated rows): ``mcap`` writes the file, the
messages are encoded by :mod:`motion.telemetry.cdr`; ``mcap-ros2-support`` decodes them in :func:`read_mcap`.
"""

from __future__ import annotations

import heapq
import json
import math
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import IO, TYPE_CHECKING, Any, Final, Protocol

import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory

from motion import __version__
from motion.telemetry import CYCLE_COLUMNS
from motion.telemetry.cdr import HEADER, CdrWriter

if TYPE_CHECKING:
    from motion.telemetry import TelemetryLog, TracedFrame

#: The metadata record's name.
METADATA: Final = "rmd_motion"
CYCLE_TOPIC: Final = "/rmd_motion/cycle"
DIAGNOSTICS_TOPIC: Final = "/diagnostics"
#: The diagnostic status names of faults and of state changes.
FAULT_NAME: Final = "rmd_motion/fault"
STATE_NAME: Final = "rmd_motion/state"
#: ``diagnostic_msgs/DiagnosticStatus`` levels: a fault is an ERROR, but for the arm's close at the end of a run (OK)
#: and a stop asked for (WARN).
OK, WARN, ERROR = 0, 1, 2
_FAULT_LEVELS: Final = {"close": OK, "stop": WARN, "estop": WARN}
_UINT32: Final = struct.Struct("<I")
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


#: The cycle message: every column of the per-cycle log (:data:`motion.telemetry.CYCLE_COLUMNS`; the scalars, then
#: per joint in configuration order: the float columns, the boolean ones), ``t_s``, ``cycle`` and ``state`` apart.
_APART = ("t_s", "cycle", "state")
CYCLE_SCALARS: Final = tuple(n for n, (joint, kind, _) in CYCLE_COLUMNS.items() if not joint and n not in _APART)
CYCLE_ARRAYS: Final = tuple(n for n, (joint, kind, _) in CYCLE_COLUMNS.items() if joint and kind is np.float64)
CYCLE_FLAGS: Final = tuple(n for n, (joint, kind, _) in CYCLE_COLUMNS.items() if joint and kind is np.bool_)
_CYCLE = "\n".join(
    [
        "builtin_interfaces/Time stamp",
        "float64 t_s",
        "int64 cycle",
        *(f"float64 {name}" for name in CYCLE_SCALARS),
        *(f"float64[] {name}" for name in CYCLE_ARRAYS),
        "float64[] following_error_deg",
        *(f"bool[] {name}" for name in CYCLE_FLAGS),
        "string state",  # (last: what precedes it has one layout for a given number of joints)
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
        "builtin_interfaces/Time stamp\nbool received\nint32 arbitration_id\nuint8[] data\nstring bus",
        "builtin_interfaces/Time",
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

    @property
    def urdf(self) -> str | None: ...

    def transforms(self, q_deg: Any) -> Sequence[LinkPose]: ...


def _ns(base_s: float, t_s: float) -> int:
    """``base_s + t_s`` in whole nanoseconds (each rounded on its own: a Unix time's float sum would lose the last
    few hundred).

    Raises:
        ValueError: a time before 1970 (MCAP's log times are unsigned).
    """
    ns = round(base_s * 1e9) + round(t_s * 1e9)
    if ns < 0:
        raise ValueError(f"a message at {base_s + t_s:.9f} s: before the epoch of MCAP's log time (0)")
    return ns


def _time(writer: CdrWriter, ns: int) -> CdrWriter:
    return writer.time(ns // 1_000_000_000, ns % 1_000_000_000)


def _header(ns: int, frame_id: str = "") -> CdrWriter:
    """A new message that begins with a ``std_msgs/Header``."""
    return _time(CdrWriter(), ns).string(frame_id)


def joint_state(ns: int, names: Sequence[str], position: Any, velocity: Any = (), effort: Any = ()) -> bytes:
    """A ``sensor_msgs/msg/JointState``."""
    return _header(ns).strings(names).float64s(position).float64s(velocity).float64s(effort).data()


def diagnostic_array(
    ns: int, level: int, name: str, message: str, *, hardware_id: str, values: dict[str, str]
) -> bytes:
    """A ``diagnostic_msgs/msg/DiagnosticArray`` of one status."""
    out = _header(ns).uint32(1).octet(level).string(name).string(message).string(hardware_id).uint32(len(values))
    for key, value in values.items():
        out.string(key).string(value)
    return out.data()


def bus_frame(ns: int, received: bool, arbitration_id: int, data: bytes, bus: str = "") -> bytes:
    """An ``rmd_motion/msg/BusFrame`` (``bus``: its bus's name on an arm of several, else empty)."""
    return _time(CdrWriter(), ns).octet(received).int32(arbitration_id).octets(data).string(bus).data()


def tf_message(ns: int, links: Sequence[LinkPose]) -> bytes:
    """A ``tf2_msgs/msg/TFMessage``."""
    out = CdrWriter().uint32(len(links))
    for link in links:
        _time(out, ns).string(link.parent).string(link.child)
        for value in (*link.translation_m, *link.rotation_xyzw):
            out.float64(value)
    return out.data()


class _Channels:
    """The MCAP writer (ROS 2 profile) and one channel per topic, its schema registered once per type."""

    def __init__(self, stream: IO[bytes]) -> None:
        self.writer = McapWriter(stream)
        self.writer.start(profile="ros2", library=f"rmd-motion {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}

    def write(self, topic: str, kind: str, message: bytes, log_ns: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema = self._schemas.get(kind)
            if schema is None:
                schema = self._schemas[kind] = self.writer.register_schema(kind, "ros2msg", SCHEMAS[kind].encode())
            channel = self._channels[topic] = self.writer.register_channel(topic, "cdr", schema)
        self.writer.add_message(channel, log_ns, message, log_ns)


def time_base_s(meta: dict[str, Any] | Any) -> float:
    """The stamp of a log's ``t_s = 0``: the controller's clock in a simulated run, else Unix time."""
    return float(meta["t0_s"]) if meta.get("simulated") else float(meta["t0_wall_unix_s"])


def cycle_message(ns: int, columns: Any, k: int, state: str, following: Any) -> bytes:
    """An ``rmd_motion/msg/Cycle``: row ``k`` of the log."""
    out = _time(CdrWriter(), ns).float64(float(columns["t_s"][k])).int64(int(columns["cycle"][k]))
    for name in CYCLE_SCALARS:
        out.float64(float(columns[name][k]))
    for name in CYCLE_ARRAYS:
        out.float64s(columns[name][k])
    out.float64s(following[k])
    for name in CYCLE_FLAGS:
        out.bools(columns[name][k])
    return out.string(state).data()


#: A message to write among the cycles: (time in ns, topic, type, bytes).
_Event = tuple[int, str, str, bytes]


def _faults(columns: Any, base_s: float) -> list[_Event]:
    """Each fault as a ``DiagnosticArray`` at its detection time, in time order."""
    faults = []
    for f in range(len(columns["fault_t_s"])):
        detected = float(columns["fault_t_s"][f])
        ns = _ns(base_s, detected)
        values = {
            "index": str(f),
            "t_s": repr(detected),
            "halt_s": repr(float(columns["fault_halt_s"][f])),
            "kind": str(columns["fault_kind"][f]),
            "joint": str(columns["fault_joint"][f]),
            "action": str(columns["fault_action"][f]),
        }
        level = _FAULT_LEVELS.get(values["kind"], ERROR)
        text = str(columns["fault_text"][f])
        fault = diagnostic_array(ns, level, FAULT_NAME, text, hardware_id=values["joint"], values=values)
        faults.append((ns, DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", fault))
    faults.sort(key=lambda fault: fault[0])
    return faults


def _frames(frames: Iterable[TracedFrame], base_s: float, buses: Sequence[str]) -> Iterator[_Event]:
    """Each traced frame as a ``BusFrame`` at its time, in the trace's (time) order (``buses``: the names of an arm's
    several buses by index; empty: one bus)."""
    for frame in frames:
        ns = _ns(base_s, frame.time_s)
        ident = -1 if frame.arbitration_id is None else frame.arbitration_id
        bus = buses[frame.bus] if buses else ""
        yield ns, "/bus/frames", "rmd_motion/msg/BusFrame", bus_frame(ns, frame.received, ident, frame.data, bus)


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
    q_ref, qd_ref, q_exp = np.radians(columns["q_ref_deg"]), np.radians(columns["qd_ref_dps"]), columns["q_exp_deg"]
    torques = columns["cmd_torque_nm"] if meta.get("mode") == "torque" else np.empty((len(t), 0))
    q_rad, qd_rad, q_exp_rad, effort = np.radians(q), np.radians(qd), np.radians(q_exp), iq * per_amp
    following = log.following_error_deg()
    previous_state = ""
    # the faults and the frames, merged in time order, go in among the cycles: the file in time order
    buses = [str(bus["name"]) for bus in meta.get("buses", ())]  # (an arm of several: each frame names its bus)
    events = heapq.merge(_faults(columns, base_s), _frames(frames, frames_base_s, buses), key=lambda event: event[0])
    event = next(events, None)
    if robot is not None and robot.urdf is not None:  # (at the first message's time)
        first = _ns(base_s, float(t[0]) if len(t) else 0.0)
        first = first if event is None else min(first, event[0])
        out.write("/robot_description", "std_msgs/msg/String", CdrWriter().string(robot.urdf).data(), first)
    for k in range(len(t)):
        ns = _ns(base_s, float(t[k]))
        while event is not None and event[0] <= ns:
            out.write(event[1], event[2], event[3], event[0])
            event = next(events, None)
        out.write(
            "/joint_states", "sensor_msgs/msg/JointState", joint_state(ns, names, q_rad[k], qd_rad[k], effort[k]), ns
        )
        ahead = _ns(base_s, float(t[k]) + period_s)
        reference = joint_state(ahead, names, q_ref[k], qd_ref[k], torques[k])
        out.write("/joint_states/reference", "sensor_msgs/msg/JointState", reference, ns)
        out.write("/joint_states/expected", "sensor_msgs/msg/JointState", joint_state(ns, names, q_exp_rad[k]), ns)
        code = int(columns["state"][k])
        state = states[code] if 0 <= code < len(states) else ""
        out.write(CYCLE_TOPIC, "rmd_motion/msg/Cycle", cycle_message(ns, columns, k, state, following), ns)
        if state != previous_state and state:
            said = {"t_s": repr(float(t[k])), "from": previous_state}
            change = diagnostic_array(ns, 0, STATE_NAME, state, hardware_id="", values=said)
            out.write(DIAGNOSTICS_TOPIC, "diagnostic_msgs/msg/DiagnosticArray", change, ns)
            previous_state = state
        if robot is not None:
            out.write("/tf", "tf2_msgs/msg/TFMessage", tf_message(ns, robot.transforms(q[k])), ns)
    while event is not None:  # (after the last cycle)
        out.write(event[1], event[2], event[3], event[0])
        event = next(events, None)
    out.writer.add_metadata(METADATA, {"meta": json.dumps(meta, allow_nan=False)})
    out.writer.finish()  # type: ignore[no-untyped-call]


def is_mcap(path: Any) -> bool:
    """The file begins with MCAP's magic bytes."""
    with open(path, "rb") as stream:
        return stream.read(len(MAGIC)) == MAGIC


def cycle_layout(joints: int) -> np.dtype[Any]:
    """The layout of an ``rmd_motion/msg/Cycle`` of ``joints`` joints up to its ``state`` (after the encapsulation
    header): CDR's alignment, as :class:`~motion.telemetry.cdr.CdrWriter` writes it; ``n_NAME`` the sequences'
    lengths."""
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    end = 0

    def field(name: str, kind: Any, size: int, align: int) -> None:
        nonlocal end
        end += -end % align
        names.append(name)
        formats.append(kind)
        offsets.append(end)
        end += size

    field("sec", "<i4", 4, 4)
    field("nanosec", "<u4", 4, 4)
    field("t_s", "<f8", 8, 8)
    field("cycle", "<i8", 8, 8)
    for name in CYCLE_SCALARS:
        field(name, "<f8", 8, 8)
    for name in (*CYCLE_ARRAYS, "following_error_deg"):
        field(f"n_{name}", "<u4", 4, 4)
        field(name, ("<f8", (joints,)), 8 * joints, 8)
    for name in CYCLE_FLAGS:
        field(f"n_{name}", "<u4", 4, 4)
        field(name, ("u1", (joints,)), joints, 1)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": end})


def _cycles(raw: list[bytes], joints: int, states: list[str]) -> dict[str, Any]:
    """The log's cycle columns from the ``Cycle`` messages' bytes (one fixed layout, then the state string).

    Raises:
        ValueError: a message of another layout (another number of joints, or not written by this version).
    """
    layout = cycle_layout(joints)
    size, head = layout.itemsize, len(HEADER)
    rows = np.frombuffer(b"".join(data[head : head + size] for data in raw), dtype=layout, count=len(raw))
    columns: dict[str, Any] = {}
    counts = [rows[f"n_{name}"] for name in (*CYCLE_ARRAYS, "following_error_deg", *CYCLE_FLAGS)]
    if len(rows) and not all((count == joints).all() for count in counts):
        raise ValueError(f"cycle messages not of the layout of {joints} joints")
    code = {state: index for index, state in enumerate(states)}
    at = head + size + (-size % 4)  # the state: its length (with the NUL), aligned to 4, then its bytes
    columns["t_s"] = rows["t_s"].copy()
    columns["cycle"] = rows["cycle"].astype(np.int64)
    texts = (data[at + 4 : at + 3 + _UINT32.unpack_from(data, at)[0]].decode() for data in raw)
    columns["state"] = np.array([code.get(text, 0) for text in texts], dtype=np.int8)  # (unknown: 0)
    for name in CYCLE_SCALARS:
        columns[name] = rows[name].copy()
    for name in CYCLE_ARRAYS:
        columns[name] = rows[name].reshape(-1, joints).copy()
    for name in CYCLE_FLAGS:
        columns[name] = rows[name].reshape(-1, joints).astype(np.bool_)
    return columns


def read_mcap(stream: IO[bytes], check: Callable[[dict[str, Any]], None]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The columns and metadata of a recording written by :func:`write_mcap`; ``check`` is given the metadata first
    (it raises ValueError for one of another schema or a newer version).

    Raises:
        ValueError: not such a recording (no ``rmd_motion`` metadata, refused by ``check``, or unreadable).
    """
    try:
        reader = make_reader(stream)
        meta: dict[str, Any] | None = None
        for record in reader.iter_metadata():
            if record.name == METADATA:
                meta = json.loads(record.metadata["meta"])
        if meta is None:
            raise ValueError(f"an MCAP file without the {METADATA!r} metadata record (not written by rmd-motion)")
        check(meta)
        raw: list[bytes] = []
        faults: list[dict[str, str]] = []
        decoders: dict[int, Callable[[bytes], Any]] = {}
        for schema, channel, message in reader.iter_messages(topics=[CYCLE_TOPIC, DIAGNOSTICS_TOPIC]):
            if channel.topic == CYCLE_TOPIC:
                raw.append(message.data)
                continue
            decode = decoders.get(channel.id)
            if decode is None:  # (diagnostics are few: the library's decoder)
                found = DecoderFactory().decoder_for(channel.message_encoding, schema)
                if found is None:
                    raise ValueError(f"no decoder for {channel.topic}")
                decode = decoders[channel.id] = found
            faults += [
                {value.key: value.value for value in status.values} | {"text": status.message}
                for status in decode(message.data).status
                if status.name == FAULT_NAME
            ]
        columns = _cycles(raw, len(meta["joints"]), list(meta.get("states", ())))
    except ValueError:
        raise
    except Exception as exc:  # (the mcap reader raises its own errors, struct's and decoders' on a damaged file)
        raise ValueError(f"not a readable MCAP recording ({type(exc).__name__}: {exc})") from exc
    faults.sort(key=lambda f: int(f["index"]))
    columns["fault_t_s"] = np.array([float(f["t_s"]) for f in faults], dtype=np.float64)
    columns["fault_halt_s"] = np.array([float(f["halt_s"]) for f in faults], dtype=np.float64)
    for key in ("kind", "joint", "action", "text"):
        columns[f"fault_{key}"] = np.array([f[key] for f in faults], dtype=np.str_)
    return columns, meta
