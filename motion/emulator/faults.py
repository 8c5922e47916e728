"""Fault injection: what can go wrong with a drive or its link, scheduled by simulation time.

Command-line syntax (``--fault``), also accepted by :func:`parse_fault`::

    KIND:MOTOR@START[-END][:PARAM]

``MOTOR`` is a drive id 1..32, ``START`` and ``END`` are simulation seconds (the fault is active for
``START <= t < END``; without ``END`` it never ends). Kinds and their parameter:

- ``over_temperature[:degC]``: the motor temperature is held at least PARAM (default: the drive's threshold + 10)
  while active; afterwards it cools with its thermal time constant. Error bit 3 is set while it is above the
  threshold and stays until it has cooled below it *and* 0x9B clears it.
- ``under_voltage[:V]``: the supply voltage is PARAM (default: the drive's threshold - 6 V) while active; error bit 0.
- ``silent``: the drive is off the bus: it neither hears requests nor answers them, and keeps its last command.
- ``delay[:ms]``: replies leave PARAM ms late (default 10).
- ``corrupt[:payload|id|length]``: replies are damaged so that a host must reject them. ``payload`` (default) - CAN:
  command byte 0x00, so the reply does not decode; RS485: a data byte changed, so the data checksum fails (the header
  checksum for frames without data). ``id`` - CAN: reply on 0x100 + id, outside the reply ids; RS485: motor id 0 with
  a valid header checksum. ``length`` - CAN: 7-byte payload; RS485: the last byte missing.
- ``drop[:probability]``: each request is lost with probability PARAM (default 1): not executed, not answered.
- ``blocked``: the joint is held where it is at START (a mechanical obstruction: zero speed whatever the torque)
  until END; the drive keeps driving against it.
- ``collision:NM``: an external torque of PARAM N·m (required; either sign) on the drive's joint, joint side,
  positive in the drive's positive sense (a configured ``direction: -1`` turns it the other way in joint angles), as a
  person or an obstacle pushing. It acts through the plant (with an arm's plant, through its rigid-body dynamics),
  so the drives' currents respond as their loops make them; torques of overlapping faults add up.

- ``power_cycle``: at START the drive switches off and on (a brown-out, a loose supply): RAM settings back to ROM,
  the drive OFF, and its multi-turn angle restarts from the single-turn reading; the shaft itself does not move.
  One instant: no END, no parameter.

Examples: ``over_temperature:2@5-20:95``, ``power_cycle:2@3.5``, ``delay:1@0:15``, ``silent:3@10``, ``drop:4@2-3:0.5``,
``corrupt:1@1:length``, ``collision:2@1.5-2.5:-4.2``, ``blocked:2@1.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from motion.protocol import CanFrame
from motion.protocol.rs485_frame import HEADER_BYTES, checksum
from motion.protocol.table import ADDRESS_STRIDE, MOTOR_ID_MAX, MOTOR_ID_MIN, split_address
from motion.protocol.v3.frames import crc16


class InjectedFault(Enum):
    """What goes wrong (see the module docstring for the parameter of each)."""

    OVER_TEMPERATURE = "over_temperature"  #: temperature held above a floor; error bit 3
    UNDER_VOLTAGE = "under_voltage"  #: supply voltage lowered; error bit 0
    SILENT = "silent"  #: drive off the bus, keeps its last command
    DELAY = "delay"  #: replies late by a number of milliseconds
    CORRUPT = "corrupt"  #: replies corrupted
    DROP = "drop"  #: requests lost with a probability
    BLOCKED = "blocked"  #: the joint held where it is (an obstruction)
    COLLISION = "collision"  #: an external torque on the joint, N·m
    POWER_CYCLE = "power_cycle"  #: the drive switches off and on at START (one-shot)


class Corruption(Enum):
    """How a ``corrupt`` fault damages a reply."""

    PAYLOAD = "payload"  #: CAN: invalid command byte; RS485: data checksum mismatch
    ID = "id"  #: CAN: arbitration id outside 0x141..0x160; RS485: motor id 0
    LENGTH = "length"  #: CAN: 7 data bytes; RS485: truncated frame


#: Kinds whose parameter is a number, with its unit and the check it must pass.
_NUMERIC: dict[InjectedFault, tuple[str, str]] = {
    InjectedFault.OVER_TEMPERATURE: ("degC", "a temperature in -40..127 degC"),
    InjectedFault.UNDER_VOLTAGE: ("V", "a voltage in 0..6553 V"),
    InjectedFault.DELAY: ("ms", "a delay >= 0 ms"),
    InjectedFault.DROP: ("", "a probability in 0..1"),
    InjectedFault.COLLISION: ("N*m", "a torque in N·m (finite, either sign)"),
}
_NUMERIC_RANGES: dict[InjectedFault, tuple[float, float]] = {
    InjectedFault.OVER_TEMPERATURE: (-40.0, 127.0),
    InjectedFault.UNDER_VOLTAGE: (0.0, 6553.0),
    InjectedFault.DELAY: (0.0, math.inf),
    InjectedFault.DROP: (0.0, 1.0),
    InjectedFault.COLLISION: (-math.inf, math.inf),
}


@dataclass(frozen=True, slots=True)
class Fault:
    """One scheduled fault on one drive.

    Attributes:
        kind: what goes wrong.
        motor_id: the drive, 1..32 (an arm on several buses: its address, bus index × 100 + motor id, so that 103 is
            motor 3 of the second bus).
        start_s: simulation time the fault begins, s.
        end_s: simulation time it ends, s (None: never).
        value: numeric parameter (degC, V, ms or a probability, per kind) or None for the kind's default.
        corruption: how ``corrupt`` damages replies.

    Raises:
        ValueError: a field is out of range or a parameter does not belong to the kind.
    """

    kind: InjectedFault
    motor_id: int
    start_s: float
    end_s: float | None = None
    value: float | None = None
    corruption: Corruption = Corruption.PAYLOAD

    def __post_init__(self) -> None:
        if self.motor_id < 0 or not MOTOR_ID_MIN <= split_address(self.motor_id)[1] <= MOTOR_ID_MAX:
            raise ValueError(
                f"fault motor id {self.motor_id} is outside {MOTOR_ID_MIN}..{MOTOR_ID_MAX} (an arm on several buses: "
                f"bus index × {ADDRESS_STRIDE} + motor id)"
            )
        if not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise ValueError(f"fault start {self.start_s!r} s must be a time >= 0")
        if self.end_s is not None and not (math.isfinite(self.end_s) and self.end_s > self.start_s):
            raise ValueError(f"fault end {self.end_s!r} s must be after its start {self.start_s:g} s")
        if self.kind is InjectedFault.POWER_CYCLE and self.end_s is not None:
            raise ValueError("fault power_cycle happens at one instant: give no END (power_cycle:MOTOR@T)")
        if self.kind is InjectedFault.COLLISION and self.value is None:
            raise ValueError("fault collision needs its torque in N·m, e.g. collision:2@1.5:4.2")
        if self.value is not None:
            if self.kind not in _NUMERIC:
                raise ValueError(f"fault {self.kind.value} takes no numeric parameter (got {self.value!r})")
            lo, hi = _NUMERIC_RANGES[self.kind]
            if not (math.isfinite(self.value) and lo <= self.value <= hi):
                expected = _NUMERIC[self.kind][1]
                raise ValueError(f"fault {self.kind.value} parameter must be {expected}, got {self.value}")

    def active(self, time_s: float) -> bool:
        """Whether the fault is in effect at simulation time ``time_s``."""
        return self.start_s <= time_s and (self.end_s is None or time_s < self.end_s)

    def describe(self) -> str:
        """The fault in command-line syntax."""
        window = f"{self.start_s:g}" + (f"-{self.end_s:g}" if self.end_s is not None else "")
        param = ""
        if self.kind is InjectedFault.CORRUPT:
            param = f":{self.corruption.value}"
        elif self.value is not None:
            param = f":{self.value:g}"
        return f"{self.kind.value}:{self.motor_id}@{window}{param}"


def parse_fault(spec: str) -> Fault:
    """Parse ``KIND:MOTOR@START[-END][:PARAM]`` (see the module docstring).

    Raises:
        ValueError: with a message naming the part that is wrong and the expected form.
    """
    form = "KIND:MOTOR@START[-END][:PARAM], e.g. over_temperature:2@5-20:95"
    kinds = ", ".join(k.value for k in InjectedFault)
    head, sep, rest = spec.strip().partition(":")
    if not sep:
        raise ValueError(f"fault {spec!r}: expected {form}")
    try:
        kind = InjectedFault(head.strip().lower())
    except ValueError:
        raise ValueError(f"fault {spec!r}: unknown kind {head!r}; kinds: {kinds}") from None
    target, at, when = rest.partition("@")
    if not at:
        raise ValueError(f"fault {spec!r}: missing '@START' ({form})")
    window, _, param = when.partition(":")
    start_text, dash, end_text = window.partition("-")
    try:
        motor_id = int(target)
    except ValueError:
        raise ValueError(f"fault {spec!r}: motor {target!r} is not an id 1..32") from None
    try:
        start_s = float(start_text)
        end_s = float(end_text) if dash else None
    except ValueError:
        raise ValueError(f"fault {spec!r}: times {window!r} are not START[-END] in seconds") from None
    value: float | None = None
    corruption = Corruption.PAYLOAD
    if param:
        if kind is InjectedFault.CORRUPT:
            try:
                corruption = Corruption(param.strip().lower())
            except ValueError:
                choices = ", ".join(c.value for c in Corruption)
                raise ValueError(f"fault {spec!r}: corruption {param!r} is not one of {choices}") from None
        elif kind in _NUMERIC:
            try:
                value = float(param)
            except ValueError:
                raise ValueError(f"fault {spec!r}: parameter {param!r} must be {_NUMERIC[kind][1]}") from None
        else:
            raise ValueError(f"fault {spec!r}: {kind.value} takes no parameter")
    try:
        return Fault(kind, motor_id, start_s, end_s, value, corruption)
    except ValueError as exc:
        raise ValueError(f"fault {spec!r}: {exc}") from None


#: Arbitration-id base of a corrupted CAN reply: 0x100 + id is outside every RMD id (0x141..0x160, 0x280).
_CORRUPT_CAN_ID_BASE = 0x100


def corrupt_can(frame: CanFrame, how: Corruption, motor_id: int) -> CanFrame:
    """A damaged copy of a CAN reply that a host decoder must reject."""
    if how is Corruption.ID:
        return CanFrame(_CORRUPT_CAN_ID_BASE + motor_id, frame.data)
    if how is Corruption.LENGTH:
        return CanFrame(frame.arbitration_id, frame.data[:-1])
    return CanFrame(frame.arbitration_id, b"\x00" + frame.data[1:])  # 0x00 is no command of either document


def corrupt_rs485(frame: bytes, how: Corruption) -> bytes:
    """A damaged copy of an RS485 reply frame that a host parser must reject."""
    out = bytearray(frame)
    if how is Corruption.ID:
        out[2] = 0
        out[4] = checksum(out[:4])
    elif how is Corruption.LENGTH:
        del out[-1]
    else:
        # The first data byte when there is one (data checksum fails), else the header checksum itself.
        index = HEADER_BYTES if len(out) > HEADER_BYTES else HEADER_BYTES - 1
        out[index] ^= 0xFF
    return bytes(out)


def corrupt_rs485_v3(frame: bytes, how: Corruption) -> bytes:
    """A damaged copy of a V3 RS485 reply frame (``3E id 08 data crc16``) that a host parser must reject."""
    out = bytearray(frame)
    if how is Corruption.ID:
        out[1] = 0  # no drive has id 0; the CRC is made to match, so only the id gives it away
        out[-2:] = crc16(out[:-2]).to_bytes(2, "little")
    elif how is Corruption.LENGTH:
        del out[-1]
    else:
        out[3] ^= 0xFF  # the command byte: the CRC fails
    return bytes(out)
