"""Joint <-> motor mapping (ros2_control's SimpleTransmission plus the drive's torque constant).

Conventions (docs/architecture.md, "Units and the transmission"):

* position: ``joint_deg = direction * motor_deg / gear_ratio + zero_offset_deg``, where ``motor_deg`` is the
  drive's multi-turn angle in degrees and ``gear_ratio`` is motor-shaft degrees per joint degree (9 for 1:9);
* rates (deg/s, deg/s², deg/s³) convert the same way without the offset;
* torque: ``joint_torque_nm = direction * gear_ratio * torque_constant_nm_per_a * iq_a``. Gear efficiency is not
  modelled (taken as 1), so the same factor holds whether the motor drives or is back-driven;
* torque current amperes <-> raw counts through :mod:`motion.protocol.scales` (±2000 raw <-> ±32 A).

:class:`Transmission` converts scalars for one joint; :class:`ArmTransmission` converts numpy arrays for all joints
with factors precomputed once (the control cycle calls it every cycle; pass ``out=`` to avoid allocations).
Nothing is clipped silently: ``iq_raw_limited`` returns whether it limited, ``iq_raw_checked`` raises.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray

from motion.errors import ConfigError, EncodeError
from motion.protocol.scales import IQ_RAW_LIMIT, IQ_SCALE, iq_amps, iq_raw

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Largest torque current the protocol can command, in amperes (IQ_RAW_LIMIT raw = 32 A).
IQ_LIMIT_A: Final = iq_amps(IQ_RAW_LIMIT)
#: Raw torque-current counts per ampere.
_RAW_PER_A: Final = IQ_SCALE[1] / IQ_SCALE[0]
#: Slack for float noise when a current limit in amperes falls exactly on a raw count (10 A -> 625 raw).
_RAW_EPSILON: Final = 1e-9


@dataclass(frozen=True, slots=True)
class Transmission:
    """Mapping between one joint and its motor.

    Attributes:
        gear_ratio: motor-shaft degrees per joint degree (dimensionless, > 0).
        direction: +1 or -1, the sign between motor and joint rotation.
        zero_offset_deg: joint angle when the motor reads 0, in degrees.
        torque_constant_nm_per_a: motor-side torque constant in N·m per ampere of torque current (> 0).
        current_limit_a: largest torque current commanded to this motor, in amperes (0 < x <= 32).
    """

    gear_ratio: float
    direction: int
    zero_offset_deg: float
    torque_constant_nm_per_a: float
    current_limit_a: float = IQ_LIMIT_A

    def __post_init__(self) -> None:
        checks = (
            ("gear_ratio", "> 0", math.isfinite(self.gear_ratio) and self.gear_ratio > 0),
            ("direction", "+1 or -1", self.direction in (1, -1)),
            ("zero_offset_deg", "a finite number", math.isfinite(self.zero_offset_deg)),
            (
                "torque_constant_nm_per_a",
                "> 0",
                math.isfinite(self.torque_constant_nm_per_a) and self.torque_constant_nm_per_a > 0,
            ),
            ("current_limit_a", f"0 < x <= {IQ_LIMIT_A:g}", 0 < self.current_limit_a <= IQ_LIMIT_A),
        )
        for name, allowed, ok in checks:
            if not ok:
                raise ConfigError("<Transmission>", name, f"allowed: {allowed}; found: {getattr(self, name)!r}")

    @property
    def iq_raw_limit(self) -> int:
        """Largest raw torque-current magnitude allowed by ``current_limit_a`` (at most IQ_RAW_LIMIT)."""
        return min(IQ_RAW_LIMIT, math.floor(self.current_limit_a * _RAW_PER_A + _RAW_EPSILON))

    @property
    def nm_per_a(self) -> float:
        """Signed joint torque per ampere of motor torque current, in N·m/A."""
        return self.direction * self.gear_ratio * self.torque_constant_nm_per_a

    def joint_deg(self, motor_deg: float) -> float:
        """Joint angle in degrees from the motor's multi-turn angle in degrees."""
        return self.direction * motor_deg / self.gear_ratio + self.zero_offset_deg

    def motor_deg(self, joint_deg: float) -> float:
        """Motor multi-turn angle in degrees for a joint angle in degrees."""
        return self.direction * (joint_deg - self.zero_offset_deg) * self.gear_ratio

    def joint_rate(self, motor_rate: float) -> float:
        """Joint rate from a motor rate, same unit (deg/s, deg/s² or deg/s³); no offset."""
        return self.direction * motor_rate / self.gear_ratio

    def motor_rate(self, joint_rate: float) -> float:
        """Motor rate from a joint rate, same unit (deg/s, deg/s² or deg/s³); no offset."""
        return self.direction * joint_rate * self.gear_ratio

    def joint_torque_nm(self, iq_a: float) -> float:
        """Joint torque in N·m produced by a motor torque current in amperes."""
        return self.nm_per_a * iq_a

    def iq_a(self, joint_torque_nm: float) -> float:
        """Motor torque current in amperes that produces a joint torque in N·m (no limit applied)."""
        return joint_torque_nm / self.nm_per_a

    def iq_raw_limited(self, joint_torque_nm: float) -> tuple[int, bool]:
        """Raw torque current for a joint torque, limited to ``±iq_raw_limit``.

        Returns:
            ``(raw, limited)``: the raw counts (nearest count, then limited) and whether limiting happened.

        Raises:
            EncodeError: the torque is not a finite number.
        """
        raw = self._raw(joint_torque_nm)
        limit = self.iq_raw_limit
        if abs(raw) <= limit:
            return raw, False
        return (limit if raw > 0 else -limit), True

    def iq_raw_checked(self, joint_torque_nm: float) -> int:
        """Raw torque current for a joint torque.

        Raises:
            EncodeError: the torque is not finite, or needs more than ``current_limit_a``.
        """
        raw, limited = self.iq_raw_limited(joint_torque_nm)
        if limited:
            raise _iq_error(self.iq_raw_limit, joint_torque_nm, self.iq_a(joint_torque_nm), "")
        return raw

    def _raw(self, joint_torque_nm: float) -> int:
        iq = self.iq_a(joint_torque_nm)
        if not math.isfinite(iq):
            raise _iq_error(self.iq_raw_limit, joint_torque_nm, iq, "")
        return iq_raw(iq)


def _iq_error(limit_raw: int, torque_nm: float, iq: float, joint: str) -> EncodeError:
    where = f"joint {joint}: " if joint else ""
    return EncodeError(
        "iq_a",
        f"±{iq_amps(limit_raw):g} A (±{limit_raw} raw)",
        iq,
        f"{where}joint torque {torque_nm:g} N·m",
    )


class ArmTransmission:
    """Vectorised :class:`Transmission` for N joints (arrays in configuration joint order).

    Every method takes and returns 1-D arrays of length N. The float conversions accept ``out=`` (an N-array of
    float64, may be the input itself) so that a control cycle can run them without allocating.
    """

    __slots__ = (
        "_joint_per_motor",
        "_motor_per_joint",
        "_nm_per_a",
        "_nm_per_a_list",
        "_offset_deg",
        "_raw_limit",
        "_raw_limit_list",
        "names",
        "transmissions",
    )

    def __init__(self, transmissions: Sequence[Transmission], names: Sequence[str] = ()) -> None:
        """Precompute the conversion factors.

        Args:
            transmissions: one per joint, in joint order.
            names: joint names for error messages (defaults to the joint indices).
        """
        self.transmissions = tuple(transmissions)
        self.names = tuple(names) or tuple(str(i) for i in range(len(self.transmissions)))
        if len(self.names) != len(self.transmissions):
            raise ValueError(f"{len(self.names)} names for {len(self.transmissions)} transmissions")

        def frozen(values: Sequence[float]) -> FloatArray:
            array = np.array(values, dtype=np.float64)
            array.flags.writeable = False
            return array

        t = self.transmissions
        self._joint_per_motor = frozen([x.direction / x.gear_ratio for x in t])
        self._motor_per_joint = frozen([x.direction * x.gear_ratio for x in t])
        self._offset_deg = frozen([x.zero_offset_deg for x in t])
        self._nm_per_a = frozen([x.nm_per_a for x in t])
        self._raw_limit = frozen([x.iq_raw_limit for x in t])
        self._nm_per_a_list = self._nm_per_a.tolist()
        self._raw_limit_list = [x.iq_raw_limit for x in t]

    def __len__(self) -> int:
        return len(self.transmissions)

    def with_turns(self, turns: Sequence[int]) -> ArmTransmission:
        """This mapping in a frame ``turns`` whole motor turns from the drives' (per joint): a drive reading ``m``
        is the joint angle of ``m + 360 * turns`` (see :mod:`motion.control.turns`). The turns fold into each
        zero offset, so every conversion stays one multiply and one add."""
        if len(turns) != len(self.transmissions):
            raise ValueError(f"{len(turns)} turn counts for {len(self.transmissions)} joints")
        shifted = [
            dataclasses.replace(t, zero_offset_deg=t.zero_offset_deg + t.direction * 360.0 * k / t.gear_ratio)
            for t, k in zip(self.transmissions, turns, strict=True)
        ]
        return ArmTransmission(shifted, self.names)

    def joint_deg(self, motor_deg: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Joint angles in degrees from motor multi-turn angles in degrees."""
        result = np.multiply(motor_deg, self._joint_per_motor, out=out)
        return np.add(result, self._offset_deg, out=result)

    def motor_deg(self, joint_deg: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Motor multi-turn angles in degrees for joint angles in degrees."""
        result = np.subtract(joint_deg, self._offset_deg, out=out)
        return np.multiply(result, self._motor_per_joint, out=result)

    def joint_rate(self, motor_rate: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Joint rates from motor rates, same unit (deg/s, deg/s² or deg/s³)."""
        return np.multiply(motor_rate, self._joint_per_motor, out=out)

    def motor_rate(self, joint_rate: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Motor rates from joint rates, same unit (deg/s, deg/s² or deg/s³)."""
        return np.multiply(joint_rate, self._motor_per_joint, out=out)

    def joint_torque_nm(self, iq_a: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Joint torques in N·m from motor torque currents in amperes."""
        return np.multiply(iq_a, self._nm_per_a, out=out)

    def iq_a(self, joint_torque_nm: ArrayLike, out: FloatArray | None = None) -> FloatArray:
        """Motor torque currents in amperes for joint torques in N·m (no limit applied)."""
        return np.divide(joint_torque_nm, self._nm_per_a, out=out)

    def iq_raw_limited(self, joint_torque_nm: ArrayLike) -> tuple[IntArray, BoolArray]:
        """Raw torque currents for joint torques, each limited to its joint's ``iq_raw_limit``.

        Returns:
            ``(raw, limited)``: int64 raw counts and a boolean mask of the joints that were limited.

        Raises:
            EncodeError: a torque is not a finite number.
        """
        raw, limited = self.iq_raw_limited_list(np.asarray(joint_torque_nm, dtype=np.float64).tolist())
        return np.array(raw, dtype=np.int64), np.array(limited, dtype=bool)

    def iq_raw_limited_list(self, joint_torque_nm: Sequence[float]) -> tuple[list[int], list[bool]]:
        """:meth:`iq_raw_limited` on Python floats, the form a control cycle builds its messages from.

        For a few joints a loop over Python floats costs a fraction of the numpy calls; the arithmetic is the same
        (torque / signed N·m per A × raw per A, rounded half to even, then limited).

        Raises:
            EncodeError: a torque is not a finite number.
        """
        raws: list[int] = []
        limited: list[bool] = []
        for torque_nm, nm_per_a, limit in zip(joint_torque_nm, self._nm_per_a_list, self._raw_limit_list, strict=True):
            scaled = torque_nm / nm_per_a * _RAW_PER_A
            if not math.isfinite(scaled):
                raise _iq_error(limit, float(torque_nm), float("nan"), self.names[len(raws)])
            raw = round(scaled)
            if raw > limit:
                raws.append(limit)
                limited.append(True)
            elif raw < -limit:
                raws.append(-limit)
                limited.append(True)
            else:
                raws.append(raw)
                limited.append(False)
        return raws, limited

    def iq_raw_checked(self, joint_torque_nm: ArrayLike) -> IntArray:
        """Raw torque currents for joint torques.

        Raises:
            EncodeError: naming the first joint whose torque is not finite or needs more than its current limit.
        """
        torque = np.asarray(joint_torque_nm, dtype=np.float64)
        raw, limited = self.iq_raw_limited(torque)
        if limited.any():
            i = int(np.argmax(limited))
            iq = float(torque[i] / self._nm_per_a[i])
            raise _iq_error(int(self._raw_limit[i]), float(torque[i]), iq, self.names[i])
        return raw
