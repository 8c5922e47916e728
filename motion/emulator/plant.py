"""The mechanics the emulated drives turn, behind a small interface.

A :class:`Plant` is joint side and in SI units: positions in rad, velocities in rad/s, torques in N·m, one entry per
drive of the emulator in ascending motor-id order. The drives convert through their gear ratio (motor-side angle =
``gear_ratio ×`` joint angle, joint torque = ``gear_ratio × torque_constant × iq``). Joint side because that is where a
rigid-body model (a later Pinocchio arm: forward dynamics with gravity) lives; the rotors enter it as armature
(``gear_ratio² × rotor inertia`` on the joint's diagonal).

:class:`IndependentLoads` gives each drive its own load: inertia, viscous and Coulomb friction and a constant external
torque, integrated with semi-implicit Euler. Coulomb friction acts as an impulse that can at most stop the joint
within one step, so a joint at rest sticks until the applied torque exceeds the breakaway torque, without chatter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from motion.emulator.model import LoadModel
from motion.errors import ConfigError

FloatArray = NDArray[np.float64]


class Plant(Protocol):
    """Joint-side mechanics: the emulator applies torques for one step and reads the new state.

    The arrays returned by :meth:`state` and :meth:`step` belong to the plant and are overwritten by the next step;
    callers copy what they keep.
    """

    @property
    def size(self) -> int:
        """Number of joints (one per emulated drive)."""
        ...

    def state(self) -> tuple[FloatArray, FloatArray]:
        """Current ``(positions_rad, velocities_rad_s)``."""
        ...

    def step(self, dt_s: float, torques_nm: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Apply ``torques_nm`` (joint side, N·m) for ``dt_s`` seconds; return ``(positions_rad, velocities_rad_s)``."""
        ...

    def hold(self, index: int, position_rad: float, side: int = 0) -> None:
        """Put joint ``index`` at ``position_rad`` at rest, held there through the next step (an obstruction: the
        emulator calls it after each step while the joint is held). ``side`` +1 / -1: a stop that lets the joint
        move only toward + / - (it leaves the stop when the torques pull it that way); 0: held both ways."""
        ...


class IndependentLoads:
    """Each drive turns its own load (no coupling, no gravity apart from a constant load torque).

    Args:
        loads: one load per drive, in the emulator's drive order.
        armature_kgm2: rotor inertia reflected to each joint (``gear_ratio² × rotor_inertia``), kg·m².

    Raises:
        ConfigError: a joint would have no inertia at all, or the sequences differ in length.
    """

    def __init__(self, loads: Sequence[LoadModel], armature_kgm2: Sequence[float] | None = None) -> None:
        armature = list(armature_kgm2) if armature_kgm2 is not None else [0.0] * len(loads)
        if len(armature) != len(loads):
            raise ConfigError("<IndependentLoads>", "armature_kgm2", f"needs {len(loads)} values, got {len(armature)}")
        self._inertia = np.array([load.inertia_kgm2 for load in loads], dtype=np.float64) + armature
        for i, inertia in enumerate(self._inertia):
            if not inertia > 0:
                raise ConfigError("<IndependentLoads>", f"loads[{i}].inertia_kgm2", "load + armature must be > 0")
        per_rad_s = 180.0 / math.pi  # N·m per deg/s -> N·m per rad/s
        self._viscous = np.array([load.viscous_friction_nm_per_dps * per_rad_s for load in loads], dtype=np.float64)
        self._coulomb = np.array([load.coulomb_friction_nm for load in loads], dtype=np.float64)
        self._load_torque = np.array([load.load_torque_nm for load in loads], dtype=np.float64)
        self._q = np.radians(np.array([load.initial_deg for load in loads], dtype=np.float64))
        self._v = np.zeros(len(loads))
        # Work buffers and per-dt constants, so that a step allocates nothing.
        self._p = np.zeros(len(loads))
        self._tmp = np.zeros(len(loads))
        self._dt_s = math.nan
        self._coulomb_dt = np.zeros(len(loads))
        self._denominator = np.zeros(len(loads))

    @property
    def size(self) -> int:
        """Number of joints."""
        return len(self._q)

    @property
    def inertia_kgm2(self) -> FloatArray:
        """Total joint-side inertia per joint (load + armature), kg·m²."""
        return self._inertia

    def state(self) -> tuple[FloatArray, FloatArray]:
        """Current ``(positions_rad, velocities_rad_s)``."""
        return self._q, self._v

    def step(self, dt_s: float, torques_nm: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Integrate one step: ``J v' = J v + dt (tau + tau_load - b v' - f_c sign)``, then ``q' = q + dt v'``.

        Viscous friction is implicit (stable for any step); the Coulomb impulse ``dt f_c`` opposes the momentum
        and cannot reverse it, so a joint whose momentum it exceeds stops and sticks.
        """
        if dt_s != self._dt_s:
            self._dt_s = dt_s
            np.multiply(self._coulomb, dt_s, out=self._coulomb_dt)
            np.multiply(self._viscous, dt_s, out=self._denominator)
            self._denominator += self._inertia
        p, tmp = self._p, self._tmp
        np.multiply(self._inertia, self._v, out=p)
        np.add(torques_nm, self._load_torque, out=tmp)
        tmp *= dt_s
        p += tmp
        np.abs(p, out=tmp)
        tmp -= self._coulomb_dt
        np.maximum(tmp, 0.0, out=tmp)
        np.copysign(tmp, p, out=tmp)
        np.divide(tmp, self._denominator, out=self._v)
        np.multiply(self._v, dt_s, out=tmp)
        self._q += tmp
        return self._q, self._v

    def hold(self, index: int, position_rad: float, side: int = 0) -> None:
        """Put joint ``index`` at ``position_rad`` at rest (independent joints: nothing else feels it, and a stop
        released the next step moves the joint away only if its torque pulls that way)."""
        del side
        self._q[index] = position_rad
        self._v[index] = 0.0
