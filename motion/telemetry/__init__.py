"""Run telemetry: a per-cycle log from the controller's cycle hooks and a trace of every frame on the bus.

Recording costs a control cycle 6-40 µs and no I/O (``bench/recording_cost.py``): rows go into preallocated
numpy chunks (a full chunk is followed by a new one; nothing recorded is ever copied during the run), frames into
preallocated arrays and one byte buffer per chunk (a new chunk, every CHUNK_ROWS cycles, costs that cycle a few
hundred microseconds). Nothing is encoded, logged or written until :meth:`TelemetrySession.close` (about 0.5 ms per
recorded cycle, after the loop has ended). Memory grows by about ``(5 + 10 J) * 8`` bytes
per cycle for the log (arm6 at 250 Hz: 135 kB/s) and 30 bytes per CAN frame for the trace (arm6: 13 frames per
cycle, 100 kB/s), so record runs of minutes, not days.

The per-cycle log (schema ``rmd-motion-telemetry`` version 6)
--------------------------------------------------------------
A run is recorded as MCAP with ROS 2 message types (:mod:`motion.telemetry.mcap`: the columns below are its
``/rmd_motion/cycle`` messages, the faults its ``/diagnostics``, ``meta`` its metadata record);
:meth:`TelemetryLog.export_npz` writes the same as a :func:`numpy.savez_compressed` archive: one array per column,
plus ``meta``, a JSON document in a 0-d string array, which ``numpy.load(path)`` reads without pickles.
:func:`load_log` reads either and returns a :class:`TelemetryLog`. ``N`` is
the number of recorded cycles, ``J`` the number of joints (configuration order, named in ``meta["joints"]``), ``F``
the number of faults. Times are seconds since ``meta["t0_s"]`` (controller clock: simulated time in a simulated run,
where every array is reproducible to the bit; ``meta["t0_wall_unix_s"]`` is the host's wall-clock Unix time at that
instant, the time base of the bus trace). Version 2 renamed version 1's ``t0_unix_s``; version 3 added the collision
observer's columns, version 4 ``q_exp_deg``, version 5 ``collision_limit_nm`` (:func:`load_log` gives older logs NaN
ones), version 6 ``state`` (0 in older logs).

=================  =====  =======  ==============================================================================
column             shape  dtype    meaning (unit)
=================  =====  =======  ==============================================================================
``t_s``            N      float64  scheduled start of the cycle (s)
``cycle``          N      int64    the loop's cycle count (overrun-skipped grid points are gaps in ``t_s``)
``jitter_s``       N      float64  wake-up minus scheduled start (s)
``busy_s``         N      float64  wake-up to the end of the cycle (s); NaN where unknown (the last cycle)
``latency_s``      N      float64  scheduled start to the cycle's replies taken in (s)
``state``          N      int8     the arm's state at the cycle, an index into ``meta["states"]`` (0: unknown)
``q_ref_deg``      N×J    float64  reference position for the set-point instant ``t_s + period_s`` (deg)
``qd_ref_dps``     N×J    float64  reference velocity (deg/s)
``qdd_ref_dps2``   N×J    float64  reference acceleration (deg/s²)
``q_deg``          N×J    float64  measured joint position after the cycle's replies (deg)
``q_exp_deg``      N×J    float64  expected position at the measurement: where the joint should be under its control
                                   loop (:mod:`motion.control.tracking`); the following error is ``q_exp - q`` (deg)
``qd_dps``         N×J    float64  measured joint velocity (deg/s)
``iq_a``           N×J    float64  measured torque current (A)
``temperature_c``  N×J    float64  measured motor temperature (°C)
``fresh``          N×J    bool     a state reply of the joint arrived in the cycle
``cmd_angle_deg``  N×J    float64  position mode: the 0xA4 multi-turn angle sent, motor side (deg); NaN otherwise
``cmd_speed_dps``  N×J    float64  position mode: the 0xA4 max speed sent, motor side (deg/s); NaN otherwise
``cmd_torque_nm``  N×J    float64  torque mode: joint torque asked for, feed-forward + PD before the current limit
                                   (N·m); NaN otherwise
``limited``        N×J    bool     torque mode: the current limit clipped the joint's command
``residual_nm``    N×J    float64  the collision observer's residual: the estimated external torque (N·m); NaN in
                                   the cycles it did not run (no observer, a state reply missing, halted)
``collision_signal_nm`` N×J float64 what the collision thresholds apply to: the residual's change over
                                   ``safety.collision_window_s`` (N·m); NaN likewise
``collision_limit_nm`` N×J float64 the threshold in force: the joint's ``collision_threshold_nm`` or the bound of
                                   what a drive within its model error can show, whichever is higher (N·m; inf: not
                                   watched); NaN likewise
``fault_t_s``      F      float64  detection time of each fault (s)
``fault_halt_s``   F      float64  time its halt went out (s)
``fault_kind``     F      str      the fault kind (``following_error``, ``no_reply``, ..., ``close`` at the end)
``fault_joint``    F      str      the joint, ``""`` for arm-wide faults
``fault_action``   F      str      the reaction: ``hold``, ``comply``, ``MOTOR_STOP`` (0x81) or ``MOTOR_OFF`` (0x80)
``fault_text``     F      str      the fault's message
=================  =====  =======  ==============================================================================

Command columns are NaN in the cycles that sent no set-point (while halted). ``meta`` holds ``schema``,
``version``, ``config`` (name), ``config_source``, ``mode``, ``transport``, ``channel``, ``emulated``, ``simulated``
(the controller's clock is simulated time), ``rate_hz``, ``period_s``, ``joints`` (``name``, ``motor_id``,
``torque_nm_per_a``: joint N·m per ampere of torque current), ``units`` (column -> unit), ``states``, ``t0_s``,
``t0_wall_unix_s``,
``following_error_limit_deg``, ``collision_threshold_nm`` (per joint, null where not watched),
``loop`` (the :class:`~motion.control.scheduler.LoopStatistics` of the run),
``counters`` (per motor id: sent, replied, timeouts, bad and stale frames) and ``trace`` (file name or null).

The bus trace
-------------
CAN: a candump log (``candump -L`` format with python-can's direction flag), readable by ``can.LogReader``,
``canplayer`` and ``log2asc``::

    (1700000000.123456) can0 141#A400680128230000 T

``T`` is a frame the host sent, ``R`` one it took in. The channel is the configured one (also for emulated runs,
so that a trace replays onto the configured interface). RS485: one line per write or read of the port, the bytes in
hex (a read may hold part of a frame, or several)::

    (1700000000.123456) T 3E A4 01 0C EF 00 68 01 00 00 00 00 00 28 23 00 00 B4

An arm on several buses (``buses:``): one trace of all their frames, each on its bus. CAN: the interface field is
the bus's name (``(1700000000.123456) left 141#A400680128230000 T``; ``canplayer left=can0 right=can1 -I FILE``
replays it onto interfaces of your choice); RS485: the bus's name before the direction
(``(1700000000.123456) left T 3E A4 ...``). The recording's ``/bus/frames`` messages name the bus too.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Final, TextIO

import numpy as np
from numpy.typing import NDArray

from motion.closing import Closing
from motion.config.schema import ArmConfig, CanBusConfig
from motion.control.clock import MonotonicClock
from motion.control.controller import Controller
from motion.protocol.table import split_address
from motion.safety.states import ArmState
from motion.telemetry.trace import BusTrace as BusTrace
from motion.telemetry.trace import TracedFrame as TracedFrame
from motion.transmission import FloatArray
from motion.transport.base import Reply, Transport

if TYPE_CHECKING:
    from motion.safety import Supervisor
    from motion.safety.supervisor import HaltRecord
    from motion.telemetry.mcap import Robot

SCHEMA: Final = "rmd-motion-telemetry"
VERSION: Final = 6
#: Columns added by versions 3, 4 and 5 (NaN in older logs); version 6 added ``state`` (0, unknown, in older logs).
_V3_COLUMNS: Final = ("residual_nm", "collision_signal_nm")
_V4_COLUMNS: Final = ("q_exp_deg",)
_V5_COLUMNS: Final = ("collision_limit_nm",)
#: The arm states a log's ``state`` column indexes (``meta["states"]``; 0: unknown).
STATES: Final = ("", *(state.value for state in ArmState))
#: Rows per chunk of the per-cycle log (16 s at 250 Hz).
CHUNK_ROWS: Final = 4096

#: Per-cycle columns: name -> (per joint, dtype, unit).
CYCLE_COLUMNS: Final[Mapping[str, tuple[bool, type[np.generic], str]]] = {
    "t_s": (False, np.float64, "s"),
    "cycle": (False, np.int64, "1"),
    "jitter_s": (False, np.float64, "s"),
    "busy_s": (False, np.float64, "s"),
    "latency_s": (False, np.float64, "s"),
    "state": (False, np.int8, "1"),
    "q_ref_deg": (True, np.float64, "deg"),
    "qd_ref_dps": (True, np.float64, "deg/s"),
    "qdd_ref_dps2": (True, np.float64, "deg/s^2"),
    "q_deg": (True, np.float64, "deg"),
    "q_exp_deg": (True, np.float64, "deg"),
    "qd_dps": (True, np.float64, "deg/s"),
    "iq_a": (True, np.float64, "A"),
    "temperature_c": (True, np.float64, "degC"),
    "fresh": (True, np.bool_, "1"),
    "cmd_angle_deg": (True, np.float64, "deg (motor)"),
    "cmd_speed_dps": (True, np.float64, "deg/s (motor)"),
    "cmd_torque_nm": (True, np.float64, "N*m"),
    "limited": (True, np.bool_, "1"),
    "residual_nm": (True, np.float64, "N*m"),
    "collision_signal_nm": (True, np.float64, "N*m"),
    "collision_limit_nm": (True, np.float64, "N*m"),
}
#: Fault columns: name -> unit.
FAULT_COLUMNS: Final[Mapping[str, str]] = {
    "fault_t_s": "s",
    "fault_halt_s": "s",
    "fault_kind": "",
    "fault_joint": "",
    "fault_action": "",
    "fault_text": "",
}

Chunk = dict[str, NDArray[Any]]


def _schema_meta(mode: str, rate_hz: float, joints: list[dict[str, Any]]) -> dict[str, Any]:
    units = {name: unit for name, (_, _, unit) in CYCLE_COLUMNS.items()} | dict(FAULT_COLUMNS)
    return {
        "schema": SCHEMA,
        "version": VERSION,
        "mode": mode,
        "rate_hz": rate_hz,
        "period_s": 1.0 / rate_hz,
        "joints": joints,
        "units": units,
        "states": list(STATES),
    }


def _fault_columns(halts: Sequence[HaltRecord], t0_s: float) -> dict[str, NDArray[Any]]:
    return {
        "fault_t_s": np.array([h.detected_s - t0_s for h in halts], dtype=np.float64),
        "fault_halt_s": np.array([h.halt_sent_s - t0_s for h in halts], dtype=np.float64),
        "fault_kind": np.array([h.fault.kind for h in halts], dtype=np.str_),
        "fault_joint": np.array([h.fault.joint or "" for h in halts], dtype=np.str_),
        "fault_action": np.array([h.reaction for h in halts], dtype=np.str_),
        "fault_text": np.array([str(h.fault) for h in halts], dtype=np.str_),
    }


def _allocate(rows: int, joints: int) -> Chunk:
    """Empty columns: floats NaN (so that what a cycle does not write reads as unknown), the rest zero."""
    chunk: Chunk = {}
    for name, (per_joint, dtype, _) in CYCLE_COLUMNS.items():
        shape = (rows, joints) if per_joint else (rows,)
        chunk[name] = np.full(shape, np.nan) if dtype is np.float64 else np.zeros(shape, dtype=dtype)
    return chunk


@dataclasses.dataclass(frozen=True)
class TelemetryLog:
    """A recorded run: the columns and the metadata of the module's schema."""

    columns: Mapping[str, NDArray[Any]]
    meta: Mapping[str, Any]

    def __getitem__(self, name: str) -> NDArray[Any]:
        return self.columns[name]

    @property
    def joint_names(self) -> list[str]:
        """Joint names in column order."""
        return [str(joint["name"]) for joint in self.meta["joints"]]

    @property
    def period_s(self) -> float:
        """The control period, s."""
        return float(self.meta["period_s"])

    @property
    def cycles(self) -> int:
        """Number of recorded cycles."""
        return len(self.columns["t_s"])

    @property
    def duration_s(self) -> float:
        """Time from the first to the last recorded cycle, s."""
        t = self.columns["t_s"]
        return float(t[-1] - t[0]) if len(t) else 0.0

    def active_rows(self) -> NDArray[np.bool_]:
        """Rows recorded before the first halt (the ``close`` halt at the end of a run counts): all rows without."""
        t, halts = self.columns["t_s"], self.columns["fault_t_s"]
        return t < halts.min() if len(halts) else np.ones(len(t), dtype=np.bool_)

    def following_error_deg(self) -> FloatArray:
        """Expected minus measured position at each cycle's measurement, deg (N×J): what the watchdog compares with
        ``safety.following_error_deg`` (it adds the lag a joint slower than expected loses). A log before version 4
        has no expected positions: there it is :meth:`lag_deg`."""
        q_exp, q = self.columns["q_exp_deg"], self.columns["q_deg"]
        if len(q) and np.isnan(q_exp).all():
            return self.lag_deg()
        error: FloatArray = q_exp - q
        return error

    def lag_deg(self) -> FloatArray:
        """Reference minus measured position at each cycle's measurement instant, deg (N×J): how far the joints
        trail the reference (the drives' own lag and the PD loop's, which the expected position models).

        Row *k* of ``q_ref_deg`` is the set-point for ``t_s[k] + period_s`` and row *k* of ``q_deg`` was measured
        at about ``t_s[k]``, so the reference is interpolated to the measurement instants (which also handles
        skipped cycles).
        """
        t, q_ref, q = self.columns["t_s"], self.columns["q_ref_deg"], self.columns["q_deg"]
        error = np.empty_like(q)
        for j in range(q.shape[1] if len(t) else 0):
            error[:, j] = np.interp(t, t + self.period_s, q_ref[:, j]) - q[:, j]
        return error

    def save(
        self,
        file: str | os.PathLike[str] | IO[bytes],
        *,
        robot: Robot | None = None,
        frames: Iterable[TracedFrame] = (),
        frames_base_s: float = 0.0,
    ) -> None:
        """Write the recording as MCAP (:mod:`motion.telemetry.mcap`): ``robot`` adds the arm's URDF and link
        transforms, ``frames`` the bus trace (their times plus ``frames_base_s`` on the log's time base)."""
        from motion.telemetry.mcap import write_mcap  # noqa: PLC0415 - (mcap's writer only where one is written)

        if isinstance(file, (str, os.PathLike)):
            if Path(file).suffix != ".mcap":
                raise ValueError(f"{os.fspath(file)}: save writes MCAP: name it FILE.mcap (export_npz writes .npz)")
            with open(file, "wb") as stream:
                write_mcap(self, stream, robot=robot, frames=frames, frames_base_s=frames_base_s)
        else:
            write_mcap(self, file, robot=robot, frames=frames, frames_base_s=frames_base_s)

    def export_npz(self, file: str | os.PathLike[str] | IO[bytes]) -> None:
        """Write the columns and the metadata as a numpy ``.npz`` archive (the module docstring; a path gets no
        suffix added, unlike :func:`numpy.savez`): :func:`load_log` reads it back."""
        arrays: dict[str, Any] = dict(self.columns)
        arrays["meta"] = np.array(json.dumps(self.meta, allow_nan=False))
        if isinstance(file, (str, os.PathLike)):
            with open(file, "wb") as stream:
                np.savez_compressed(stream, **arrays)
        else:
            np.savez_compressed(file, **arrays)


def load_log(path: str | os.PathLike[str]) -> TelemetryLog:
    """Read a run's recording (``.mcap``, :mod:`motion.telemetry.mcap`) or a log exported as ``.npz`` (and the
    ``.npz`` logs of earlier versions).

    Raises:
        OSError: the file cannot be read.
        ValueError: the file is not an rmd-motion recording (or of a newer version).
    """
    from motion.telemetry.mcap import is_mcap, read_mcap  # noqa: PLC0415 - (mcap's reader only where one is read)

    name = os.fspath(path)
    if is_mcap(path):
        try:
            with open(path, "rb") as stream:
                arrays, meta = read_mcap(stream, _check_meta)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from exc
    else:
        arrays, meta = _read_npz(name)
        try:
            _check_meta(meta)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from exc
    version = int(meta.get("version", 0))
    if version < VERSION and "q_deg" in arrays:
        older = (*(_V3_COLUMNS if version < 3 else ()), *(_V4_COLUMNS if version < 4 else ()))
        for column in (*older, *(_V5_COLUMNS if version < 5 else ())):
            arrays.setdefault(column, np.full(arrays["q_deg"].shape, np.nan))
        arrays.setdefault("state", np.zeros(len(arrays["q_deg"]), dtype=np.int8))
        meta.setdefault("states", list(STATES))
    missing = [column for column in (*CYCLE_COLUMNS, *FAULT_COLUMNS) if column not in arrays]
    if missing:
        raise ValueError(f"{name}: telemetry log without column(s) {', '.join(missing)}")
    return TelemetryLog(arrays, meta)


def _check_meta(meta: Any) -> None:
    if not isinstance(meta, dict) or meta.get("schema") != SCHEMA:
        raise ValueError(f"not a telemetry log (schema {meta.get('schema') if isinstance(meta, dict) else None!r})")
    if int(meta.get("version", 0)) > VERSION:
        raise ValueError(f"telemetry log version {meta['version']} is newer than {VERSION}")


def _read_npz(name: str) -> tuple[dict[str, NDArray[Any]], Any]:
    try:
        archive = np.load(name, allow_pickle=False)
    except (ValueError, EOFError):  # numpy: neither .npz nor .npy (it then suggests unpickling), or truncated
        raise ValueError(
            f"{name}: not a telemetry log (neither an MCAP recording nor an .npz exported from one)"
        ) from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(f"{name}: not a telemetry log (a single array)")
    with archive:
        arrays = {column: archive[column] for column in archive.files}
    if "meta" not in arrays:
        raise ValueError(f"{name}: not a telemetry log (no meta)")
    return arrays, json.loads(str(arrays.pop("meta")))


class Recorder:
    """Records every control cycle of a controller (a cycle hook; see the module docstring for the columns).

    Args:
        controller: the controller (before or after its loop started).
        supervisor: its safety supervisor, whose faults and halts the log lists.
        chunk_rows: rows per preallocated chunk.
    """

    def __init__(
        self, controller: Controller, supervisor: Supervisor | None = None, *, chunk_rows: int = CHUNK_ROWS
    ) -> None:
        self.controller = controller
        self.supervisor = supervisor
        #: The names of an arm's several buses, by index (the joints' metadata names each one's); empty: one bus.
        self.bus_names: tuple[str, ...] = ()
        self._joints = len(controller.specs)
        self._position_mode = controller.options.mode.traits.drive_position_loop
        self._state_code = {state: STATES.index(state.value) for state in ArmState}
        self._chunk_rows = chunk_rows
        self._chunks: list[Chunk] = [_allocate(chunk_rows, self._joints)]
        self._chunk = self._chunks[0]
        self._row = 0
        self._prev_chunk: Chunk | None = None
        self._prev_row = 0
        #: Time zero of the log, controller clock, s.
        self.t0_s = controller.clock.now()
        #: The same instant as Unix time, s.
        self.t0_wall_unix_s = time.time() - (controller.clock.now() - self.t0_s)

    def attach(self) -> Recorder:
        """Append to the controller's cycle hooks."""
        self.controller.cycle_hooks.append(self)
        return self

    def detach(self) -> None:
        """Remove from the controller's cycle hooks (the recorded rows stay)."""
        if self in self.controller.cycle_hooks:
            self.controller.cycle_hooks.remove(self)

    @property
    def rows(self) -> int:
        """Recorded cycles."""
        return (len(self._chunks) - 1) * self._chunk_rows + self._row

    def __call__(self, controller: Controller, start_s: float, replies: list[Reply]) -> None:
        """Record one cycle (the controller calls this after the cycle's replies were taken in)."""
        chunk, row = self._chunk, self._row
        if row == self._chunk_rows:
            chunk, row = _allocate(self._chunk_rows, self._joints), 0
            self._chunks.append(chunk)
            self._chunk = chunk
        loop = controller.loop
        cycle = loop.cycles
        chunk["t_s"][row] = start_s - self.t0_s
        chunk["cycle"][row] = cycle
        chunk["jitter_s"][row] = loop.wake_jitter_s
        chunk["latency_s"][row] = controller.clock.now() - start_s
        if self.supervisor is not None:
            chunk["state"][row] = self._state_code[self.supervisor.state]
        previous = self._prev_chunk
        if previous is not None and previous["cycle"][self._prev_row] == cycle - 1:
            previous["busy_s"][self._prev_row] = loop.last_busy_s  # known once that cycle has ended
        if previous is not None:
            self._residual(previous, self._prev_row)
        reference, axes = controller.reference, controller.axes
        chunk["q_ref_deg"][row] = reference.position
        chunk["qd_ref_dps"][row] = reference.velocity
        chunk["qdd_ref_dps2"][row] = reference.acceleration
        chunk["q_deg"][row] = axes.q_deg
        chunk["q_exp_deg"][row] = controller.tracking.expected_deg
        chunk["qd_dps"][row] = axes.qd_dps
        chunk["iq_a"][row] = axes.iq_a
        chunk["temperature_c"][row] = axes.temperature_c
        chunk["fresh"][row] = axes.fresh
        setpoints = controller.setpoints
        if setpoints.commanded:  # a halted cycle sends only status reads
            if self._position_mode:
                chunk["cmd_angle_deg"][row] = setpoints.motor_angle_deg
                chunk["cmd_speed_dps"][row] = setpoints.max_speed_dps
            else:
                chunk["cmd_torque_nm"][row] = setpoints.torque_nm
                chunk["limited"][row] = setpoints.limited
        self._prev_chunk, self._prev_row = chunk, row
        self._row = row + 1

    def _residual(self, chunk: Chunk, row: int) -> None:
        """The collision observer's output of the cycle of ``row``: the watchdog computes it after the cycle's
        hooks ran, so a row gets it at the next cycle (or at :meth:`finish`)."""
        watchdog = self.supervisor.watchdog if self.supervisor is not None else None
        if watchdog is not None and watchdog.residual_cycle == chunk["cycle"][row]:
            chunk["residual_nm"][row] = watchdog.residual_nm
            chunk["collision_signal_nm"][row] = watchdog.collision_signal_nm
            chunk["collision_limit_nm"][row] = watchdog.collision_limit_nm

    def finish(self) -> None:
        """Complete the last row's busy time and residuals once the loop has ended (call after the loop stopped)."""
        previous, loop = self._prev_chunk, self.controller.loop
        if previous is not None and not loop.running and previous["cycle"][self._prev_row] == loop.cycles - 1:
            previous["busy_s"][self._prev_row] = loop.last_busy_s
        if previous is not None:
            self._residual(previous, self._prev_row)

    def columns(self) -> dict[str, NDArray[Any]]:
        """The recorded cycle and fault columns (copies)."""
        parts = [*self._chunks[:-1], {name: array[: self._row] for name, array in self._chunk.items()}]
        columns = {name: np.concatenate([part[name] for part in parts]) for name in CYCLE_COLUMNS}
        columns.update(_fault_columns(self.supervisor.halts if self.supervisor is not None else (), self.t0_s))
        return columns

    def meta(self) -> dict[str, Any]:
        """The metadata the recorder knows (joints, mode, rate, time base, units, loop statistics, counters)."""
        controller = self.controller
        per_amp = controller.transmission.joint_torque_nm(np.ones(len(controller.specs)))
        # (an arm on several buses: a drive's address splits into its bus, named as in the metadata's "buses", and
        # its motor id on that bus)
        names = self.bus_names
        protocols = sorted({f.family.value for f in controller.families})
        joints = [
            {"name": s.name, "motor_id": split_address(s.motor_id)[1], "torque_nm_per_a": float(k)}
            | ({"bus": names[split_address(s.motor_id)[0]]} if len(names) > 1 else {})
            | ({"protocol": f.family.value} if len(protocols) > 1 else {})
            for s, k, f in zip(controller.specs, per_amp, controller.families, strict=True)
        ]
        return _schema_meta(controller.options.mode.value, controller.options.rate_hz, joints) | {
            "simulated": not isinstance(controller.clock, MonotonicClock),
            "t0_s": self.t0_s,
            "t0_wall_unix_s": self.t0_wall_unix_s,
            "protocol": "+".join(protocols),  # ("v2+v3": each joint's is in its entry)
            "loop": dataclasses.asdict(controller.loop.statistics()),
            "counters": {str(mid): dataclasses.asdict(c) for mid, c in sorted(controller.bus.counters.items())},
        }

    def log(self, **meta: Any) -> TelemetryLog:
        """The run so far as a :class:`TelemetryLog`; ``meta`` entries are added to (or replace) the metadata."""
        return TelemetryLog(self.columns(), self.meta() | meta)


@dataclasses.dataclass(frozen=True, slots=True)
class TelemetryOptions:
    """What to record of a run (``Arm(..., telemetry=TelemetryOptions(log=..., trace=...))``).

    Attributes:
        log: the run's recording (``.mcap``: :mod:`motion.telemetry.mcap`), or None.
        trace: the bus trace file (CAN: candump ``.log``; RS485: hex lines), or None; with a ``log``, the recording
            holds the frames too.

    Raises:
        ValueError: a ``log`` whose name does not end in ``.mcap`` (``.npz`` is an export: ``rmd-motion export``).
    """

    log: str | os.PathLike[str] | None = None
    trace: str | os.PathLike[str] | None = None

    def __post_init__(self) -> None:
        if self.log is not None and Path(self.log).suffix != ".mcap":
            raise ValueError(
                f"{os.fspath(self.log)}: a run is recorded as MCAP: name it FILE.mcap (an .npz for numpy is exported "
                "from it: rmd-motion export FILE.mcap FILE.npz)"
            )


def _output(path: str | os.PathLike[str]) -> Path:
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    return target


class TelemetrySession(Closing):
    """The recording of one arm run: opens the output files at once (a bad path fails before anything moves),
    traces the bus and records every cycle, writes both files at :meth:`close`.

    Args:
        options: the files to write.
        config: the arm's configuration (name, transport, channel and following-error limit go into the metadata).
        emulated: the run is on emulated drives.
        robot: the arm's URDF and link transforms for the recording (:class:`kinematics.frames.LinkFrames`).

    Raises:
        OSError: an output file cannot be created.
    """

    def __init__(
        self, options: TelemetryOptions, config: ArmConfig, *, emulated: bool = False, robot: Robot | None = None
    ) -> None:
        self.options = options
        self.config = config
        self.emulated = emulated
        self.robot = robot
        self.recorder: Recorder | None = None
        self.trace: BusTrace | None = None
        #: The log written by :meth:`close`.
        self.result: TelemetryLog | None = None
        self._closed = False
        self._log_file: IO[bytes] | None = None
        self._trace_file: TextIO | None = None
        try:
            if options.log is not None:
                self._log_file = _output(options.log).open("wb")
            if options.trace is not None:
                self._trace_file = _output(options.trace).open("w", encoding="ascii")
                self.trace = BusTrace()
        except BaseException:
            self._close_files()
            raise

    def tap(self, bus: Transport) -> None:
        """Trace every frame of ``bus`` (if a trace file was asked for)."""
        if self.trace is not None:
            self.trace.install(bus)

    def attach(self, controller: Controller, supervisor: Supervisor | None = None) -> None:
        """Record every cycle of ``controller`` (if a log file was asked for)."""
        if self._log_file is not None:
            self.recorder = Recorder(controller, supervisor).attach()
            self.recorder.bus_names = tuple(bus.name for bus in self.config.buses)

    def close(self) -> TelemetryLog | None:
        """Stop recording and write the files (after the control loop ended); safe to call twice.

        Returns:
            The per-cycle log, or None when none was asked for.

        Raises:
            OSError: a file could not be written.
        """
        if self._closed:
            return self.result
        self._closed = True
        try:
            if self.trace is not None:
                self.trace.uninstall()
            if self.recorder is not None:
                self.recorder.detach()
                self.recorder.finish()
            if self._trace_file is not None and self.trace is not None:
                buses = self.config.buses
                several = len(buses) > 1  # (an arm on several buses: each frame on its bus, by name)
                if all(isinstance(bus, CanBusConfig) for bus in buses):
                    channels = [bus.name if several else bus.link for bus in buses]
                    self.trace.write_candump(self._trace_file, channels)
                else:
                    self.trace.write_hex(self._trace_file, [bus.name for bus in buses] if several else ())
            if self._log_file is not None:
                self.result = log = self._log()
                trace = self.trace
                frames_base_s = 0.0 if log.meta.get("simulated") or trace is None else trace.unix_offset_s
                log.save(self._log_file, robot=self.robot, frames=trace or (), frames_base_s=frames_base_s)
        finally:
            self._close_files()
        return self.result

    def _log(self) -> TelemetryLog:
        config = self.config
        meta: dict[str, Any] = {
            "config": config.name,
            "config_source": config.source,
            "transport": ", ".join(dict.fromkeys(bus.transport.value for bus in config.buses)),
            "channel": ", ".join(f"{b.name}={b.link}" if b.name else b.link for b in config.buses),
            "emulated": self.emulated,
            "following_error_limit_deg": config.safety.following_error_deg,
            "collision_threshold_nm": list(config.collision_thresholds_nm),
            "trace": Path(self.options.trace).name if self.options.trace is not None else None,
        }
        if len(config.buses) > 1:  # each joint's "bus" names one of these
            meta["buses"] = [{"name": b.name, "transport": b.transport.value, "channel": b.link} for b in config.buses]
        if self.recorder is not None:
            return self.recorder.log(**meta)
        # Nothing was recorded (the arm never connected): an empty log that still names the joints.
        columns: dict[str, NDArray[Any]] = dict(_allocate(0, len(config.joints)))
        columns.update(_fault_columns((), 0.0))
        several = len(config.buses) > 1  # (as the recorder's: each joint's bus named on an arm of several)
        joints = [{"name": j.name, "motor_id": j.motor_id} | ({"bus": j.bus} if several else {}) for j in config.joints]
        meta |= _schema_meta(config.control.mode.value, config.control.rate_hz, joints)
        meta |= {"t0_s": 0.0, "t0_wall_unix_s": time.time(), "loop": None, "counters": {}}
        return TelemetryLog(columns, meta)

    def _close_files(self) -> None:
        for file in (self._log_file, self._trace_file):
            if file is not None:
                file.close()
