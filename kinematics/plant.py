"""The arm as the emulator's plant: Pinocchio forward dynamics with gravity couples the emulated drives.

Implements :class:`motion.emulator.Plant`. The emulator's plant coordinate of a drive is its joint-side angle ``p =
motor angle / gear_ratio`` in radians, drives in ascending motor-id order; the configuration's joint angle is ``q =
direction · p + zero_offset`` (the transmission of docs/architecture.md), and the drive's torque on ``p`` acts on ``q``
with the sign of ``direction``. Rotor inertias enter as armature (``gear_ratio² × rotor inertia``); viscous and Coulomb
friction act on each joint (Coulomb smoothed over ±``COULOMB_SMOOTHING_DPS`` so that the explicit integration does not
chatter at rest).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from kinematics.dynamics import crba_full
from kinematics.model import ArmModel
from motion.config import ArmConfig

FloatArray = NDArray[np.float64]

#: Joint speed over which Coulomb friction ramps up to its full value, deg/s.
COULOMB_SMOOTHING_DPS = 0.5


class ArmPlant:
    """Rigid-body arm dynamics for the emulator (joint side, radians, drives in ascending motor-id order).

    Args:
        arm: the Pinocchio model of ``config`` (this plant sets its armature and uses its ``data``: build one model
            for the plant and another for the controller's feed-forward).
        config: the arm configuration (transmission, friction and rotor inertia per joint).
        initial_deg: configuration joint angles at start, degrees (default: all zero, clamped into the limits).
    """

    def __init__(self, arm: ArmModel, config: ArmConfig, initial_deg: FloatArray | None = None) -> None:
        joints = config.joints
        n = len(joints)
        order = sorted(range(n), key=lambda i: joints[i].address)  # emulator index -> configuration index
        self._order = np.array(order, dtype=np.intp)
        self._model, self._data = arm.model, arm.data
        self._to_model = arm.to_model  # model coordinate -> configuration index
        # everything below is in model coordinate order
        cfg = [joints[i] for i in self._to_model]
        emu_of_cfg = np.argsort(self._order)  # configuration index -> emulator index
        self._emu_index = emu_of_cfg[self._to_model]
        self._model_of_emu = [int(m) for m in np.argsort(self._emu_index)]  # emulator index -> model coordinate
        self._free_of: dict[tuple[int, ...], tuple[Any, Any]] = {}  # held joints -> the free ones' indexes
        self._sign = np.array([float(j.direction) for j in cfg])
        self._offset_rad = np.radians([j.zero_offset_deg for j in cfg])
        per_rad_s = 180.0 / math.pi
        self._viscous = np.array([j.emulation.viscous_friction_nm_per_dps * per_rad_s for j in cfg])
        self._coulomb = np.array([j.emulation.coulomb_friction_nm for j in cfg])
        self._smoothing = math.radians(COULOMB_SMOOTHING_DPS)
        self._model.armature = np.array([j.gear_ratio**2 * j.emulation.rotor_inertia_kgm2 for j in cfg])
        start_cfg = np.zeros(n) if initial_deg is None else np.asarray(initial_deg, dtype=np.float64)
        self._q = np.radians(start_cfg[self._to_model])
        self._v = np.zeros(n)
        self._tau = np.zeros(n)
        self._work = np.zeros(n)  # (step's scratch: it runs at the emulator's rate, several times per cycle)
        self._p = np.zeros(n)
        self._pd = np.zeros(n)
        #: Joints held through the next step (model index -> the side it may leave toward, 0: none).
        self._held: dict[int, int] = {}
        self._export()

    @property
    def size(self) -> int:
        """Number of joints."""
        return len(self._q)

    def _export(self) -> None:
        # p (emulator order) = direction * (q - offset)
        work = self._work
        np.subtract(self._q, self._offset_rad, out=work)
        work *= self._sign
        self._p[self._emu_index] = work
        np.multiply(self._sign, self._v, out=work)
        self._pd[self._emu_index] = work

    def state(self) -> tuple[FloatArray, FloatArray]:
        """Current ``(positions_rad, velocities_rad_s)`` in the emulator's coordinates."""
        return self._p, self._pd

    def joint_positions_deg(self) -> FloatArray:
        """Configuration joint angles, degrees, in configuration order (for tests and reports)."""
        out = np.empty(self.size)
        out[self._to_model] = np.degrees(self._q)
        return out

    def step(self, dt_s: float, torques_nm: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Apply the drives' torques (emulator order, N·m on ``p``) for ``dt_s``; semi-implicit Euler."""
        tau, work, v = self._tau, self._work, self._v
        np.take(torques_nm, self._emu_index, out=tau)
        tau *= self._sign
        np.multiply(self._viscous, v, out=work)
        tau -= work
        np.divide(v, self._smoothing, out=work)
        np.tanh(work, out=work)
        work *= self._coulomb
        tau -= work
        acceleration = pin.aba(self._model, self._data, self._q, v, tau)
        if self._held:
            acceleration = self._constrained(acceleration, tau)
        np.multiply(acceleration, dt_s, out=work)
        v += work
        np.multiply(v, dt_s, out=work)
        self._q += work
        self._export()
        return self._p, self._pd

    def _constrained(self, free_acceleration: FloatArray, tau: FloatArray) -> FloatArray:
        """The accelerations with the held joints fixed (their stop or obstruction takes whatever torque it takes):
        ``M_FF qdd_F = tau_F - h_F`` over the free joints F, ``qdd_H = 0``. A joint at a one-sided stop whose free
        acceleration points away from it leaves the stop."""
        held = [m for m, side in self._held.items() if side * free_acceleration[m] <= 0.0]
        self._held.clear()
        if not held:
            return free_acceleration
        key = tuple(sorted(held))
        if key not in self._free_of:  # (the same few sets step after step: a brake, a stop)
            free = np.setdiff1d(np.arange(self.size), held)
            self._free_of[key] = (free, np.ix_(free, free))
        free, block = self._free_of[key]
        acceleration = np.zeros(self.size)
        if free.size:
            mass = crba_full(self._model, self._data, self._q)
            bias = pin.nonLinearEffects(self._model, self._data, self._q, self._v)
            acceleration[free] = np.linalg.solve(mass[block], tau[free] - bias[free])
        self._v[held] = 0.0
        return acceleration

    def hold(self, index: int, position_rad: float, side: int = 0) -> None:
        """Put the joint of emulator index ``index`` at ``position_rad`` (emulator coordinate) at rest, held there
        through the next step (the rest of the arm moves with it fixed); ``side``: see
        :meth:`motion.emulator.Plant.hold` (emulator coordinate)."""
        m = self._model_of_emu[index]
        self._q[m] = self._sign[m] * position_rad + self._offset_rad[m]
        self._v[m] = 0.0
        self._held[m] = int(self._sign[m]) * side
        self._export()
