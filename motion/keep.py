"""What rmd-motion keeps between sessions, on the host: the turn offsets of each arm's joints
(:mod:`motion.control.turns`), the identified position loops (:mod:`motion.control.tracking`) and the record of the
drives' ROM-backed settings (:mod:`motion.control.drive_record`), in one folder (:func:`state_dir`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
import weakref
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

from motion.config.schema import ArmConfig
from motion.control.controller import Controller
from motion.control.drive_record import DriveRecord
from motion.control.tracking import PositionLoop, PositionLoopFit
from motion.control.turns import Source, TurnRecord, drive_reading
from motion.emulator.simulated import SimulatedBus, Simulation
from motion.safety import Supervisor
from motion.transport import Transport

logger = logging.getLogger("motion.config")


#: What a stored identification is (the file's ``schema`` and ``version``).
TRACKING_SCHEMA = "rmd-motion-tracking"
TRACKING_VERSION = 1
#: Environment variable naming the folder of stored identifications (default ``$XDG_STATE_HOME/rmd-motion``).
STATE_DIR_ENV = "RMD_MOTION_STATE_DIR"


def state_dir() -> Path:
    """The folder of what rmd-motion keeps between sessions: ``$RMD_MOTION_STATE_DIR``, else
    ``$XDG_STATE_HOME/rmd-motion`` (``~/.local/state/rmd-motion``)."""
    folder = os.environ.get(STATE_DIR_ENV)
    if folder is None:
        state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
        folder = str(Path(state) / "rmd-motion")
    return Path(folder)


def tracking_store(config: ArmConfig) -> Path:
    """Where the identified position loops of ``config``'s arm are stored (one file per arm name)."""
    return state_dir() / f"{config.name}-tracking.json"


#: The host's record of the drives' ROM-backed settings, in :func:`state_dir`.
DRIVE_RECORD_FILE = "drives.json"
# Emulated drives in simulated time are new with each simulation: their record is kept with it, in memory.
_SIMULATED_RECORDS: weakref.WeakKeyDictionary[Simulation, DriveRecord] = weakref.WeakKeyDictionary()


def drive_record_for(bus: Transport) -> tuple[DriveRecord, Callable[[], float]]:
    """The record of ``bus``'s drives and the clock its times are in: the file in :func:`state_dir` and the host's
    wall clock; for a simulated bus, one in memory per simulation and the simulation's clock."""
    if isinstance(bus, SimulatedBus):
        record = _SIMULATED_RECORDS.get(bus.simulation)
        if record is None:
            record = _SIMULATED_RECORDS[bus.simulation] = DriveRecord(None)
        return record, bus.simulation.now
    return DriveRecord(state_dir() / DRIVE_RECORD_FILE), time.time


#: What a turn record file is (the file's ``schema`` and ``version``).
TURNS_SCHEMA = "rmd-motion-turns"
TURNS_VERSION = 1


def turns_store(config: ArmConfig) -> Path:
    """Where the turn offsets of ``config``'s arm are kept between sessions (one file per arm name)."""
    return state_dir() / f"{config.name}-turns.json"


def load_turn_records(config: ArmConfig, where: str) -> dict[str, TurnRecord]:
    """The turn records the last session on ``where`` (the bus, as ``Transport.describe()`` says) left, by joint
    name; those of another bus or another motor id are left out. A missing file gives none; an unreadable one is
    logged and gives none (joints with a window are then resolved from it, or refused)."""
    path = turns_store(config)
    if not path.exists():
        return {}
    try:
        document = json.loads(path.read_text())
        if document.get("schema") != TURNS_SCHEMA or document.get("version") != TURNS_VERSION:
            raise ValueError(f"not a {TURNS_SCHEMA} version {TURNS_VERSION} file")
        if document.get("bus") != where:
            return {}
        # (a drive's address: its motor id on an arm of one bus; on several it names the bus too, so that a joint moved
        # to another bus at the same id is not taken for the drive it was)
        ids = {j.name: j.address for j in config.joints}
        records = {
            name: TurnRecord(
                int(e["motor_id"]),
                int(e["turns"]),
                float(e["reading_deg"]),
                Source(e["source"]),
                None if e.get("power_on") is None else (float(e["power_on"][0]), float(e["power_on"][1])),
            )
            for name, e in document["joints"].items()
        }
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        logger.warning("%s: recorded turn offsets ignored (%s)", path, exc)
        return {}
    return {name: r for name, r in records.items() if ids.get(name) == r.motor_id and math.isfinite(r.reading_deg)}


def save_turn_records(
    config: ArmConfig,
    where: str,
    controller: Controller,
    sources: Iterable[Source],
    power_ons: Sequence[tuple[float, float] | None] | None = None,
    *,
    angles_deg: Mapping[str, float] | None = None,
) -> Path:
    """Record each joint's turn offset and its drive's reading now (from the controller's latest snapshot), for
    the next session on ``where``; ``power_ons``: per joint, the drive's runtime at this session's connect and the
    host's time then (drives that tell it: :attr:`JointTurns.power_on`). ``angles_deg``: only these joints, at these
    angles (degrees; :func:`resting_angles` at a session's end); the others' records are dropped, so that the next
    session resolves them afresh."""
    q = controller.snapshot.position_deg
    angles = angles_deg if angles_deg is not None else {name: float(q[i]) for i, name in enumerate(config.joint_names)}
    joints = {
        j.name: {
            "motor_id": j.address,  # (see load_turn_records)
            "turns": k,
            "reading_deg": drive_reading(t, angles[j.name], k),
            "source": str(source),
            "power_on": None if power_on is None else list(power_on),
        }
        for j, t, k, source, power_on in zip(
            config.joints,
            controller.base_transmission.transmissions,
            controller.turns,
            sources,
            power_ons or [None] * len(config.joints),
            strict=True,
        )
        if j.name in angles
    }
    document = {"schema": TURNS_SCHEMA, "version": TURNS_VERSION, "arm": config.name, "bus": where, "joints": joints}
    path = turns_store(config)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2) + "\n")
    return path


def resting_angles(supervisor: Supervisor) -> dict[str, float]:
    """The joints whose turn records a closed session leaves, and their angles, degrees: those its end saw at rest
    after the final halt (:attr:`~motion.safety.ending.SessionEnd.rest_deg`: never one still coasting, nor one whose
    drive was not heard), less those whose drive restarted (their frame is unknown: the next session resolves each
    of them afresh, and the others from their records)."""
    lost = supervisor.lost_frames
    return {name: q for name, q in supervisor.ending.rest_deg.items() if name not in lost}


def store_tracking(config: ArmConfig, controller: Controller, fits: Mapping[str, PositionLoopFit]) -> Path:
    """Write the identified loops with the drive settings they were identified under; returns the file."""
    path = tracking_store(config)
    settings = controller.tracking.drive_settings
    joints = []
    for j, joint in enumerate(config.joints):
        fit = fits.get(joint.name)
        if fit is None or settings[j] is None:
            continue
        angle_kp, accel = settings[j] or (0, None)
        joints.append(
            {
                "name": joint.name,
                "motor_id": joint.address,  # (its address: see load_turn_records)
                "drive_angle_kp": angle_kp,
                "drive_acceleration_dps2": accel,
                "angle_gain_per_s": fit.loop.angle_gain_per_s,
                "acceleration_dps2": fit.loop.acceleration_dps2,
                "rms_prior_deg": fit.rms_prior_deg,
                "rms_deg": fit.rms_deg,
            }
        )
    document = {"schema": TRACKING_SCHEMA, "version": TRACKING_VERSION, "config": config.name, "joints": joints}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2) + "\n")
    return path


def offer_stored_tracking(config: ArmConfig, controller: Controller) -> list[str]:
    """Offer the stored identification of ``config``'s arm to the controller's tracking model: each joint's is used
    once its drive is read (in the loop's first cycles) with the gain and acceleration it was identified under, the
    prior otherwise (a retuned drive). Returns the joints that have one.

    A missing file offers nothing; an unreadable one is logged and offers nothing.
    """
    path = tracking_store(config)
    if not path.exists():
        return []
    try:
        document = json.loads(path.read_text())
        if document.get("schema") != TRACKING_SCHEMA or document.get("version") != TRACKING_VERSION:
            raise ValueError(f"not a {TRACKING_SCHEMA} version {TRACKING_VERSION} file")
        stored = {entry["name"]: entry for entry in document["joints"]}
        offered = []
        for j, joint in enumerate(config.joints):
            entry = stored.get(joint.name)
            if entry is None or entry.get("motor_id") != joint.address:
                continue
            accel = entry["drive_acceleration_dps2"]
            settings = (int(entry["drive_angle_kp"]), None if accel is None else int(accel))
            loop = PositionLoop(float(entry["angle_gain_per_s"]), float(entry["acceleration_dps2"]))
            controller.tracking.offer_identified(j, settings, loop)
            offered.append(joint.name)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        logger.warning("%s: stored position loops ignored (%s)", path, exc)
        return []
    if offered:
        logger.info("%s: identified position loops for %s", path, ", ".join(offered))
    return offered
