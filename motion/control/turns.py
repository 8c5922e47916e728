"""Which motor turn a geared joint is on: the drive's angle frame, resolved at connect.

A drive of the v2.3 / v1.62 generation counts motor turns from its own power-up: its multi-turn angle (0x92) starts
at the single-turn reading, 0..360 motor degrees (a drive without a multi-turn battery; the emulator models it). Behind
a 1:N gear one motor turn is ``360 / N`` joint degrees, so right after power-up the joint angle is known only modulo
that: 40 deg behind 1:9, 10 deg behind 1:36. The controller keeps a whole number of motor turns per joint, its *turn
offset*, between its frame and the drive's::

    joint_deg = direction * (drive_deg + 360 * turns) / gear_ratio + zero_offset_deg

(:meth:`motion.transmission.ArmTransmission.with_turns`); it applies to every target sent and every angle read, and
nothing is written to the drive.

How a joint's turns are found at connect (:func:`resolve_turns`), from the drive's reading and what the last session
left (:class:`TurnRecord`, kept per arm by :mod:`motion.compose`):

0. A drive that tells its runtime (V3, 0xB1) and has run since the record's session keeps the record's count,
   wherever the joint went meanwhile (its count is continuous while it is powered: an arm that went limp after a
   session and sagged is still in its frame) (``Source.KEPT``).
1. The drive reads in its first turn (0 <= reading < 360 motor degrees), as it does right after a power-up: a joint
   with a ``power_on_window_deg`` takes the unique turn count that puts it inside its window (``Source.WINDOW``).
   No such count, or a landing within :func:`edge_margin_deg` of an edge (a joint that was outside its window by
   about the gap between windows would land there), is refused. A record of an earlier session that continues into
   this reading with another count makes the reading ambiguous (a first-turn reading can also be a drive that never
   restarted): refused too.
2. The reading is past the first turn and continues the record of the last session (within
   :data:`CONTINUITY_MOTOR_DEG` of where it ended): the drive has not restarted since, its count is kept
   (``Source.KEPT``).
3. Past the first turn with no record that continues into it: the drive has turned since it powered up and no session
   saw its frame; a joint with a window is refused (power the drives up with it inside its window, or home it).
4. A joint without a window takes the record's count when it continues, else the drive's own count
   (``Source.ASSUMED``; connect warns once, naming the span of joint angles that assumption covers).

Homing (:mod:`motion.compose`) sets the turns from a hard stop instead (``Source.HOMED``).

Drives that report their **output shaft** (V3, V4.2 document section 2.12: 0x92 is the multi-turn angle of the
output) need no power-on window (:func:`resolve_output_joint`): their reading is the joint's angle, kept over power-off
where the drive is set to (function 0x20 index 4 = 1), else restarted within one output turn (0..360 output degrees).
After rule 0 and a record that continues into the reading (rule 2), a V3 joint takes the reading itself where it lies
within the joint's limits (``Source.ABSOLUTE``), else the whole output turns that bring it inside them, where one
count does (``Source.OUTPUT_TURN``: a drive in single-turn mode powered up at a negative angle); anything else is
refused. A joint whose limits span a whole output turn or more cannot tell single-turn readings apart: it takes the
reading (the drive must keep its multi-turn value, 0x20 index 4).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

from motion.errors import MotionError
from motion.transmission import Transmission

#: Motor degrees in one turn.
TURN_DEG: Final = 360.0
#: A reading continues a session's record when it lies this close to where the record ended, motor degrees: far less
#: than a turn, and more than an arm sags while its drives are off but powered.
CONTINUITY_MOTOR_DEG: Final = 90.0
#: A drive reads in its first turn at power-up; the joint may settle (sag under gravity, drives off) by this many
#: motor degrees before the controller connects, and the reading still counts as a power-up one.
POWER_UP_SAG_MOTOR_DEG: Final = 45.0
#: The largest refusal margin at a window's edge, joint degrees.
EDGE_MARGIN_MAX_DEG: Final = 1.0


class TurnError(MotionError):
    """A joint's turn count cannot be told: nothing may move until it is (the CLI exits 2)."""


class Source(StrEnum):
    """Where a joint's turn count came from."""

    WINDOW = "power-on window"
    KEPT = "kept from the last session"
    ASSUMED = "assumed (no window)"
    HOMED = "homed"
    EMULATED = "emulated drives powered up at the zero pose"
    ABSOLUTE = "the drive's output-shaft angle (V3)"
    OUTPUT_TURN = "the output turn inside the joint's limits (V3)"


@dataclass(frozen=True, slots=True)
class TurnRecord:
    """What a session leaves for the next one about one drive.

    Attributes:
        motor_id: the drive's id.
        turns: the turn offset the session used.
        reading_deg: the drive's multi-turn reading when the session last saw it, motor degrees (drive frame).
        source: how the session's turns were found.
        power_on: drives that tell their runtime (V3, 0xB1): the runtime at the session's connect and the host's
            wall-clock time then, s (None: not told).
    """

    motor_id: int
    turns: int
    reading_deg: float
    source: Source
    power_on: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class JointTurns:
    """One joint's resolved turn offset.

    Attributes:
        name: the joint.
        turns: whole motor turns added to the drive's reading.
        source: how they were found.
        reading_deg: the drive's multi-turn reading at connect, motor degrees.
        joint_deg: the joint angle at connect, with ``turns`` applied, degrees.
        window_deg: the joint's power-on window (None: none configured).
        power_on: the drive's runtime at connect and the host's wall-clock time then, s (None: not told; kept in the
            turn record).
    """

    name: str
    turns: int
    source: Source
    reading_deg: float
    joint_deg: float
    window_deg: tuple[float, float] | None
    power_on: tuple[float, float] | None = None

    def describe(self) -> str:
        """How the turns were found, in words (``rmd-motion status``)."""
        match self.source:
            case Source.WINDOW:
                assert self.window_deg is not None
                lo, hi = self.window_deg
                return f"{self.source.value} [{lo:g}, {hi:g}] deg, {self.turns:+d} turns"
            case _:
                return f"{self.source.value}, {self.turns:+d} turns"


def turn_joint_deg(transmission: Transmission) -> float:
    """One motor turn in joint degrees (positive)."""
    return TURN_DEG / transmission.gear_ratio


def edge_margin_deg(transmission: Transmission, window: tuple[float, float]) -> float:
    """How close to a window's edge a resolved angle may not land, joint degrees: a quarter of the gap between the
    window and its next copy one motor turn away, at most :data:`EDGE_MARGIN_MAX_DEG`."""
    gap = turn_joint_deg(transmission) - (window[1] - window[0])
    return min(EDGE_MARGIN_MAX_DEG, 0.25 * gap)


def joint_angle(transmission: Transmission, reading_deg: float, turns: int) -> float:
    """The joint angle of a drive reading (motor degrees) with ``turns`` whole motor turns added."""
    return transmission.joint_deg(reading_deg + TURN_DEG * turns)


def drive_reading(transmission: Transmission, joint_deg: float, turns: int) -> float:
    """The drive's reading (motor degrees) of a joint angle, in a frame ``turns`` away from the controller's."""
    return transmission.motor_deg(joint_deg) - TURN_DEG * turns


def in_first_turn(reading_deg: float) -> bool:
    """Whether a multi-turn reading is where a drive reads right after a power-up: in its first turn, give or take
    :data:`POWER_UP_SAG_MOTOR_DEG` of an arm that settled since."""
    return -POWER_UP_SAG_MOTOR_DEG <= reading_deg < TURN_DEG + POWER_UP_SAG_MOTOR_DEG


def ambiguous_after(
    transmission: Transmission, joint_deg: float, turns: int, window: tuple[float, float]
) -> int | None:
    """Whether a session that ends with the joint at ``joint_deg`` (its drive ``turns`` from the controller's frame)
    leaves the next session a reading it cannot tell from a power-up: one in the drive's first turn whose window
    count differs from ``turns``. Returns that count (the next session asks: ``--keep-turns`` or ``--forget-turns``),
    else None."""
    reading = drive_reading(transmission, joint_deg, turns)
    if not in_first_turn(reading):
        return None
    try:
        counted = window_turns("", transmission, reading, window)
    except TurnError:
        return None
    return counted if counted != turns else None


def ambiguous_joints(
    transmissions: Sequence[Transmission], turns: Sequence[JointTurns], q_deg: Iterable[float]
) -> list[tuple[str, float, tuple[float, float]]]:
    """The joints that a session ending at ``q_deg`` (joint degrees) leaves where the next one cannot tell their turns
    from their readings (:func:`ambiguous_after`): name, angle and power-on window of each."""
    found = []
    for transmission, spec, q in zip(transmissions, turns, q_deg, strict=True):
        window = spec.window_deg
        if window is not None and ambiguous_after(transmission, float(q), spec.turns, window) is not None:
            found.append((spec.name, float(q), window))
    return found


def window_turns(name: str, transmission: Transmission, reading_deg: float, window: tuple[float, float]) -> int:
    """The unique turn count that puts the joint inside its window, clear of the edges.

    Raises:
        TurnError: no count puts it inside, or the angle lands within the edge margin.
    """
    lo, hi = window
    q0 = joint_angle(transmission, reading_deg, 0)
    step = transmission.direction * turn_joint_deg(transmission)  # joint degrees per added motor turn
    margin = edge_margin_deg(transmission, window)
    ratio = (lo - q0) / step
    candidates = [k for k in (math.floor(ratio), math.ceil(ratio)) if lo <= q0 + k * step <= hi]
    fix = (
        f"move it into the window by hand with the drives off and power them up again, or home it "
        f"(`rmd-motion home`); one motor turn is {turn_joint_deg(transmission):g} deg of this joint"
    )
    if not candidates:
        below = max(q0 + k * step for k in (math.floor(ratio), math.ceil(ratio)) if q0 + k * step < lo)
        above = min(q0 + k * step for k in (math.floor(ratio), math.ceil(ratio)) if q0 + k * step > hi)
        raise TurnError(
            f"joint {name}: the drive reads {reading_deg:.2f} motor deg: the joint is at {below:.2f} or {above:.2f} "
            f"deg (or another whole motor turn away), neither inside its power_on_window_deg [{lo:g}, {hi:g}]: {fix}"
        )
    turns = candidates[0]
    q = q0 + turns * step
    if q - lo < margin or hi - q < margin:
        raise TurnError(
            f"joint {name}: the drive reads {reading_deg:.2f} motor deg, which puts the joint at {q:.2f} deg, within "
            f"{margin:g} deg of an edge of its power_on_window_deg [{lo:g}, {hi:g}]: too close to tell from a joint "
            f"outside the window; {fix}"
        )
    return turns


def resolve_joint(
    name: str,
    transmission: Transmission,
    reading_deg: float,
    window: tuple[float, float] | None,
    record: TurnRecord | None,
    *,
    powered_since: bool | None = None,
    stayed_powered: bool = False,
) -> JointTurns:
    """One joint's turn offset (the rules of the module docstring). ``powered_since``: whether the drive has run
    since the record's session, as its runtime tells (None: it does not tell); a drive that has keeps its count
    wherever the joint went meanwhile (``Source.KEPT``). ``stayed_powered``: the user says the drives stayed powered
    (``--keep-turns``): where the reading cannot tell (the record continues into it, and the window counts otherwise),
    the record's count holds; a reading that can tell is taken as it is.

    Raises:
        TurnError: a joint with a window whose turns cannot be told.
    """
    if record is not None and powered_since:
        return _joint_turns(name, transmission, reading_deg, window, record.turns, Source.KEPT, Source.KEPT)
    continues = record is not None and abs(reading_deg - record.reading_deg) <= CONTINUITY_MOTOR_DEG
    kept = record.turns if record is not None and continues else None
    if window is None:
        return _joint_turns(name, transmission, reading_deg, None, kept, Source.KEPT, Source.ASSUMED)
    if not in_first_turn(reading_deg):
        if kept is None:
            raise TurnError(
                f"joint {name}: the drive reads {reading_deg:.2f} motor deg: it has turned since it powered up and no "
                "session recorded its frame, so its power-on window no longer tells its turns; power the drives off "
                f"and on with the joint inside its power_on_window_deg [{window[0]:g}, {window[1]:g}], or home it "
                "(`rmd-motion home`)"
            )
        return _joint_turns(name, transmission, reading_deg, window, kept, Source.KEPT, Source.KEPT)
    try:
        turns = window_turns(name, transmission, reading_deg, window)
    except TurnError:
        if kept is None:
            raise
        return _joint_turns(name, transmission, reading_deg, window, kept, Source.KEPT, Source.KEPT)
    if kept is not None and kept != turns:
        if stayed_powered:
            return _joint_turns(name, transmission, reading_deg, window, kept, Source.KEPT, Source.KEPT)
        lo, hi = window
        raise TurnError(
            f"joint {name}: the drive reads {reading_deg:.2f} motor deg, which does not tell whether it was powered up "
            f"since the last session: if the drives stayed powered since, the joint is at "
            f"{joint_angle(transmission, reading_deg, kept):.2f} deg (run again with --keep-turns; API: "
            "keep_turns=True); if they were powered up with the joint inside its power_on_window_deg "
            f"[{lo:g}, {hi:g}], it is at {joint_angle(transmission, reading_deg, turns):.2f} deg (--forget-turns; "
            "API: forget_turns=True); if neither, home it (`rmd-motion home`)"
        )
    return JointTurns(name, turns, Source.WINDOW, reading_deg, joint_angle(transmission, reading_deg, turns), window)


def resolve_output_joint(
    name: str,
    transmission: Transmission,
    reading_deg: float,
    limits: tuple[float, float],
    record: TurnRecord | None,
    *,
    powered_since: bool | None = None,
    output_turn: int,
) -> JointTurns:
    """One joint's turn offset on a drive that reports its output shaft (the module docstring's last paragraph).
    ``output_turn``: motor turns per output turn of the drive (its reduction; 0 where that is no whole number: the
    reading alone counts); ``limits``: the joint's, degrees.

    Raises:
        TurnError: no whole output turn puts the joint inside its limits.
    """
    if record is not None and (powered_since or abs(reading_deg - record.reading_deg) <= CONTINUITY_MOTOR_DEG):
        return _joint_turns(name, transmission, reading_deg, None, record.turns, Source.KEPT, Source.KEPT)
    lo, hi = limits
    q0 = joint_angle(transmission, reading_deg, 0)
    if lo <= q0 <= hi:
        return JointTurns(name, 0, Source.ABSOLUTE, reading_deg, q0, None)
    step = transmission.direction * output_turn * turn_joint_deg(transmission)  # joint degrees per output turn
    inside = []
    if step:  # (0: a reduction that is no whole number of motor turns; the reading alone)
        ratio = (lo - q0) / step
        inside = [k for k in range(math.floor(ratio) - 1, math.ceil(ratio) + 2) if lo <= q0 + k * step <= hi]
    if len(inside) != 1:
        if len(inside) > 1:
            why = f"; {len(inside)} whole output turns would bring it inside: which one cannot be told"
        elif step:
            why = f", and no whole output turn ({abs(step):g} deg of this joint) brings it inside"
        else:
            why = ", and its drive's reduction is no whole number of motor turns: no turn can be added"
        output_deg = reading_deg / abs(transmission.gear_ratio)
        raise TurnError(
            f"joint {name}: the drive reads {output_deg:.2f} output deg, which puts the joint at {q0:.2f} deg, outside "
            f"its limits [{lo:g}, {hi:g}]{why}: move it inside its limits by hand with the drives off, or home it "
            "(`rmd-motion home`)"
        )
    turns = inside[0] * output_turn
    return JointTurns(name, turns, Source.OUTPUT_TURN, reading_deg, joint_angle(transmission, reading_deg, turns), None)


def _joint_turns(  # noqa: PLR0917 - the resolver's own helper
    name: str,
    transmission: Transmission,
    reading_deg: float,
    window: tuple[float, float] | None,
    kept: int | None,
    kept_source: Source,
    otherwise: Source,
) -> JointTurns:
    """The record's turns when one continues into the reading (``kept_source``), else the drive's own count."""
    turns, source = (kept, kept_source) if kept is not None else (0, otherwise)
    return JointTurns(name, turns, source, reading_deg, joint_angle(transmission, reading_deg, turns), window)


def resolve_turns(
    names: Sequence[str],
    transmissions: Sequence[Transmission],
    readings_deg: Sequence[float],
    windows: Sequence[tuple[float, float] | None],
    records: Sequence[TurnRecord | None],
    *,
    powered_since: Sequence[bool | None] | None = None,
    stayed_powered: bool = False,
    output_turns: Sequence[int | None] | None = None,
    limits: Sequence[tuple[float, float]] | None = None,
) -> tuple[JointTurns, ...]:
    """Every joint's turn offset (``powered_since``: see :func:`resolve_joint`, per joint; ``output_turns``: per joint,
    the motor turns of one output turn of a drive that reports its output shaft, None for the others, which then need
    ``limits``: :func:`resolve_output_joint`); all refusals are collected into one error.

    Raises:
        TurnError: one or more joints with a window whose turns cannot be told (one line each).
    """
    resolved: list[JointTurns] = []
    problems: list[str] = []
    n = len(names)
    since = [None] * n if powered_since is None else powered_since
    outputs = [None] * n if output_turns is None else output_turns
    for i, (*args, powered, output) in enumerate(
        zip(names, transmissions, readings_deg, windows, records, since, outputs, strict=True)
    ):
        try:
            if output is None:
                resolved.append(resolve_joint(*args, powered_since=powered, stayed_powered=stayed_powered))
            else:
                assert limits is not None
                name, transmission, reading, _window, record = args
                resolved.append(
                    resolve_output_joint(
                        name, transmission, reading, limits[i], record, powered_since=powered, output_turn=output
                    )
                )
        except TurnError as exc:
            problems.append(str(exc))
    if problems:
        raise TurnError("\n".join(problems))
    return tuple(resolved)


def assumed_span(transmission: Transmission, joint: JointTurns) -> tuple[float, float]:
    """The joint angles an assumed count is right for when the drive has just powered up (its first turn), degrees:
    a joint powered up outside them reads off by a multiple of ``360 / gear_ratio``."""
    ends = (joint_angle(transmission, 0.0, joint.turns), joint_angle(transmission, TURN_DEG, joint.turns))
    return (min(ends), max(ends))
