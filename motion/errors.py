"""The one error tree of rmd-motion.

Every error the package raises derives from :class:`MotionError`, so a robot program can catch the whole family
in one place and still tell apart "we asked for something illegal" (:class:`EncodeError`), "the wire sent something
illegal" (:class:`DecodeError`), a bus problem (:class:`TransportError`), a bad configuration (:class:`ConfigError`),
a trajectory that cannot be planned (:class:`PlanningError`) and a fault that halted the arm (:class:`MotionFault`).
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum
from typing import Final


class MotionError(Exception):
    """Base of every error raised by rmd-motion."""


class ProtocolError(MotionError):
    """A message could not be turned into bytes, or bytes into a message."""


class EncodeError(ProtocolError, ValueError):
    """We asked for something the protocol cannot carry (a value out of range, an unknown code, ...).

    Attributes:
        field: name of the offending field (``"motor_id"``, ``"iq_a"``, ...).
        valid: human-readable valid range or set (``"1..32"``).
        value: the value that was given.
    """

    def __init__(self, field: str, valid: str, value: object, detail: str = "") -> None:
        self.field = field
        self.valid = valid
        self.value = value
        text = f"{field}: {value!r} is outside the valid range {valid}"
        if detail:
            text += f" ({detail})"
        super().__init__(text)


class DecodeError(ProtocolError, ValueError):
    """The wire sent bytes that are not a valid message.

    Attributes:
        reason: what was wrong, without the bytes.
        raw: the offending bytes, as received.
    """

    def __init__(self, message: str, raw: bytes = b"") -> None:
        self.reason = message
        self.raw = bytes(raw)
        super().__init__(f"{message} (raw: {self.raw.hex(' ') or 'empty'})")


class TransportError(MotionError):
    """The bus or port failed: bus off, port gone, write refused."""


class TransportTimeout(TransportError, TimeoutError):
    """A transport operation did not complete before its deadline."""


class PortLost(TransportError):
    """The bus or port is gone for good (a device unplugged, a dead adapter, the far end of a pseudo-terminal closed):
    nothing more can be sent on it, and the transport that saw it counts as closed."""


class PortUnavailable(TransportError):
    """The bus or port could not be opened (no such device, an interface that is down or unknown, a port in use).

    Attributes:
        link: the kind of link (``"can"``, ``"rs485"``: a transport's registry name).
    """

    def __init__(self, message: str, link: str = "can") -> None:
        super().__init__(message)
        self.link = link


class PortHeld(PortUnavailable):
    """Another rmd-motion session (in this process or another) holds the bus or port: its advisory lock
    (:mod:`motion.transport.portlock`) is taken. Nothing was sent."""


class DrivesSilent(TransportError):
    """Drives did not answer a read every drive must answer (wrong motor id, no power, wiring, another protocol).

    Attributes:
        motor_ids: the drives that were asked and did not answer (their addresses: the motor ids on an arm of one
            bus).
        labels: how messages name them ("motor 3", "motor 3 on bus right"), in the same order.
    """

    def __init__(self, message: str, motor_ids: tuple[int, ...] = (), labels: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.motor_ids = motor_ids
        self.labels = labels or tuple(f"motor {i}" for i in motor_ids)


class ConfigError(MotionError, ValueError):
    """A configuration file is invalid.

    Attributes:
        file: path of the configuration file (or ``"<string>"``).
        key_path: dotted path of the offending key (``"joints[2].gear_ratio"``).
    """

    def __init__(self, file: str, key_path: str, message: str) -> None:
        self.file = file
        self.key_path = key_path
        super().__init__(f"{file}: {key_path}: {message}")


class PlanningError(MotionError):
    """A trajectory could not be planned (limits, invalid input, unreachable target)."""


class FaultKind(StrEnum):
    """What halted the arm (:attr:`MotionFault.kind`); compares equal to its value, e.g. ``"no_reply"``."""

    # seen by the watchdog in the cycle's replies
    FOLLOWING_ERROR = "following_error"  #: |expected - measured| beyond ``safety.following_error_deg``
    COLLISION = "collision"  #: a joint's momentum-observer residual beyond its ``collision_threshold_nm``
    POSITION_LIMIT = "position_limit"  #: a measured angle beyond its joint limit
    #: a measured joint speed beyond its velocity limit × the margin a healthy joint's loop may overshoot by (the
    #: torque constant's model error, and the steps of the speed fields: ``motion.safety.overspeed``)
    OVERSPEED = "overspeed"
    SETPOINT_LIMIT = "setpoint_limit"  #: a planned set-point beyond its joint limit (it was not sent)
    TEMPERATURE = "temperature"  #: motor temperature at or above the joint's ``temperature_limit_c``
    LOW_VOLTAGE = "low_voltage"  #: supply voltage below ``safety.min_voltage_v``
    DRIVE_OVER_TEMPERATURE = "drive_over_temperature"  #: the drive's own over-temperature flag (0x9A)
    DRIVE_LOW_VOLTAGE = "drive_low_voltage"  #: the drive's own low-voltage flag (0x9A)
    DRIVE_ERROR = "drive_error"  #: any other error flag of the drive (0x9A)
    DRIVE_RESTARTED = "drive_restarted"  #: a drive's multi-turn angle (0x92) jumped by whole turns: it restarted
    NO_REPLY = "no_reply"  #: too many consecutive missing replies, or too long without a good one
    CORRUPT_FRAMES = "corrupt_frames"  #: too many corrupt frames from a drive within a second
    OVERRUN = "overrun"  #: too many control cycles in a row over their period
    #: a fault the hold is for persisted through the hold (a blocked joint's following error, a current held at its
    #: limit): the drives' own halt instead
    HOLD_FAILED = "hold_failed"
    # failures of the host side
    TRANSPORT = "transport"  #: the bus or port failed
    EXCEPTION = "exception"  #: an exception in the control cycle (a bug: the arm halts rather than go on)
    STATE = "state"  #: an event the arm's state did not accept (the transition table's safe state)
    # requested
    ESTOP = "estop"  #: ``Supervisor.estop()`` (under policy ``hold``, a stop ramp)
    STOP = "stop"  #: ``Arm.stop()``: the drives' own halt, never a ramp
    CLOSE = "close"  #: the arm was closed while the loop ran (not an error)
    BUS_CLOSING = "bus_closing"  #: the bus was closed under the running loop
    # outcomes of commands
    CLEAR_FAILED = "clear_failed"  #: ``clear()`` found a cause still there
    WRITE_FAILED = "write_failed"  #: a drive did not echo what was written to it

    @property
    def holdable(self) -> bool:
        """True for the kinds after which streaming a stop ramp (policy ``hold``) is still trusted."""
        return self in HOLDABLE


#: The kinds after which the ``hold`` policy streams a stop ramp; every other kind halts with 0x81 / 0x80. Not the
#: limit faults (a ramp from at or beyond a limit would carry the arm further past it), nor communication, drive
#: flags or failures of our own code, nor a collision: the ramp follows the path on, into whatever the arm hit, for
#: its whole length (at arm6's speeds a quarter of a second and degrees of travel), where the drives' own 0x81 brakes
#: at their acceleration limit (``safety.collision_reaction: comply`` is the reaction that yields instead). Nor an
#: overspeed: a joint faster than any healthy loop drives it is one whose loop diverged (a torque-mode PD at a rate
#: its gains do not hold) or whose drive no longer keeps to its cap, and the stop ramp streams through that same loop,
#: from a speed beyond anything it planned; the drives' own 0x81 brakes each joint by its drive alone.
HOLDABLE: Final = frozenset(
    {FaultKind.FOLLOWING_ERROR, FaultKind.TEMPERATURE, FaultKind.LOW_VOLTAGE, FaultKind.OVERRUN, FaultKind.ESTOP}
)


class MotionFault(MotionError):
    """A fault halted every axis.

    Attributes:
        joint: the joint the fault was seen on, or ``None`` for arm-wide faults.
        kind: what halted the arm (a :class:`FaultKind`).
        value: the measured value, if any.
        threshold: the configured threshold the value crossed, if any.
        time_s: controller time of the detection, in seconds.
        joints: every joint the fault concerns (a collision may be isolated to more than one); ``(joint,)`` by
            default.
        detail: what was seen, in words.
        cause: the likely physical cause, where the run's evidence shows one (set by the arm that saw the fault:
            :mod:`motion.api.summary`), else None.
    """

    cause: str | None = None

    def __init__(
        self,
        kind: FaultKind | str,
        *,
        joint: str | None = None,
        value: float | None = None,
        threshold: float | None = None,
        time_s: float = 0.0,
        detail: str = "",
        joints: Sequence[str] = (),
    ) -> None:
        self.kind = FaultKind(kind)  # an unknown kind is a ValueError here, never a default
        self.joint = joint
        self.joints = tuple(joints) if joints else ((joint,) if joint is not None else ())
        self.value = value
        self.threshold = threshold
        self.time_s = time_s
        self.detail = detail
        parts: Sequence[str] = [
            str(self.kind),
            f"joint={joint}" if joint is not None else "",
            f"value={value:g}" if value is not None else "",
            f"threshold={threshold:g}" if threshold is not None else "",
            f"t={time_s:.4f}s",
            detail,
        ]
        super().__init__(" ".join(p for p in parts if p))
