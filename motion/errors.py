"""The one error tree of rmd-motion.

Every error the package raises derives from :class:`MotionError`, so a robot program can catch the whole family
in one place and still tell apart "we asked for something illegal" (:class:`EncodeError`), "the wire sent something
illegal" (:class:`DecodeError`), a bus problem (:class:`TransportError`), a bad configuration (:class:`ConfigError`),
a trajectory that cannot be planned (:class:`PlanningError`) and a fault that halted the arm (:class:`MotionFault`).
"""

from __future__ import annotations

from collections.abc import Sequence


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


class MotionFault(MotionError):
    """A fault halted every axis.

    Attributes:
        joint: the joint the fault was seen on, or ``None`` for arm-wide faults.
        kind: short machine-readable fault kind (``"over_temperature"``, ``"no_reply"``, ...).
        value: the measured value, if any.
        threshold: the configured threshold the value crossed, if any.
        time_s: controller time of the detection, in seconds.
    """

    def __init__(
        self,
        kind: str,
        *,
        joint: str | None = None,
        value: float | None = None,
        threshold: float | None = None,
        time_s: float = 0.0,
        detail: str = "",
    ) -> None:
        self.kind = kind
        self.joint = joint
        self.value = value
        self.threshold = threshold
        self.time_s = time_s
        parts: Sequence[str] = [
            f"{kind}",
            f"joint={joint}" if joint is not None else "",
            f"value={value:g}" if value is not None else "",
            f"threshold={threshold:g}" if threshold is not None else "",
            f"t={time_s:.4f}s",
            detail,
        ]
        super().__init__(" ".join(p for p in parts if p))
