"""The generalized momentum observer (De Luca et al.; Haddadin, De Luca and Albu-Schäffer, "Robot Collisions",
IEEE T-RO 2017): an estimate of the external joint torques from the drives' measured currents and speeds.

With the generalized momentum ``p = M(q) q̇`` and ``ṗ = τ_m + τ_ext − τ_f + C(q, q̇)ᵀ q̇ − g(q)``, the residual

    r = K_O (p − p0 − ∫ (τ_m + C(q, q̇)ᵀ q̇ − g(q) − τ_f + r) dt)

obeys ``ṙ = K_O (τ_ext − r)``: a first-order filter of the external torque, per joint, decoupled by the model, with
no acceleration measured. ``τ_m`` is the joint torque of the measured torque current (direction × gear ratio ×
torque constant × iq), ``τ_f`` the joint's friction model (viscous + Coulomb), ``M`` includes the rotors
(``gear_ratio² × rotor inertia`` as Pinocchio's armature).

Discretised once per control cycle with the cycle's measured values (rectangle rule, the previous residual inside
the integral). Differencing the integral form between two cycles gives the form computed here,

    r_k = r_{k−1} + K_O·dt · ((p_k − p_{k−1}) / dt − (τ_m + Cᵀq̇ − g − τ_f)_k − r_{k−1}),

the same numbers for a constant ``K_O·dt``, which is the share of a torque step the residual takes up per cycle
(stable and without overshoot up to 1). A late cycle (real time) has a longer dt: ``K_O·dt`` is capped at 1 there,
which the integral form cannot do.

Pinocchio's shape: the model and its data are built once; an update runs ``crba``, ``computeCoriolisMatrix`` and
``computeGeneralizedGravity`` and numpy operations into preallocated arrays.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from kinematics.dynamics import crba_full
from kinematics.model import ArmModel, build_arm
from kinematics.plant import COULOMB_SMOOTHING_DPS
from motion.config import ArmConfig

FloatArray = NDArray[np.float64]

_RAD_PER_DEG = math.pi / 180.0
_DEG_PER_RAD = 180.0 / math.pi


class MomentumObserver:
    """One residual per joint, in N·m, configuration joint order.

    Args:
        arm: a Pinocchio model of the arm for the observer alone (this sets its armature and uses its ``data``).
        config: the arm (friction model, rotor inertia, gear ratios per joint; the gain per cycle from ``safety``).
        gain_per_cycle: ``K_O × dt`` at the nominal period (default ``safety.collision_gain_per_cycle``); the gain
            K_O in 1/s is this times the control rate.
    """

    def __init__(self, arm: ArmModel, config: ArmConfig, gain_per_cycle: float | None = None) -> None:
        joints = config.joints
        n = len(joints)
        self._model, self._data = arm.model, arm.data
        self._to_model = arm.to_model  # model coordinate -> configuration index
        self._to_config = arm.to_config  # configuration index -> model coordinate
        share = config.safety.collision_gain_per_cycle if gain_per_cycle is None else gain_per_cycle
        #: The observer gain K_O, 1/s.
        self.gain_per_s = share * config.control.rate_hz
        cfg = [joints[i] for i in self._to_model]  # model order below
        self._model.armature = np.array([j.gear_ratio**2 * j.rotor_inertia_kgm2 for j in cfg])
        self._viscous = np.array([j.viscous_friction_nm_per_dps * _DEG_PER_RAD for j in cfg])  # N·m per rad/s
        self._coulomb = np.array([j.coulomb_friction_nm for j in cfg])
        self._smoothing = math.radians(COULOMB_SMOOTHING_DPS)
        self._q = np.zeros(n)
        self._v = np.zeros(n)
        self._tau = np.zeros(n)
        self._p = np.zeros(n)
        self._p_previous = np.zeros(n)
        self._r = np.zeros(n)
        self._work = np.zeros(n)
        self._friction = np.zeros(n)
        self._out = np.zeros(n)
        self._started = False

    @property
    def size(self) -> int:
        """Number of joints."""
        return len(self._q)

    @property
    def residual_nm(self) -> FloatArray:
        """The latest residual, N·m, configuration order (the observer's array: copy what you keep)."""
        return self._out

    def _load(self, q_deg: ArrayLike, qd_dps: ArrayLike) -> None:
        np.take(np.asarray(q_deg, dtype=np.float64), self._to_model, out=self._q)
        np.take(np.asarray(qd_dps, dtype=np.float64), self._to_model, out=self._v)
        self._q *= _RAD_PER_DEG
        self._v *= _RAD_PER_DEG

    def _momentum(self) -> None:
        np.dot(crba_full(self._model, self._data, self._q), self._v, out=self._p)

    def reset(self, q_deg: ArrayLike, qd_dps: ArrayLike) -> None:
        """Start (again) at this state: p0 = M(q) q̇, the residual zero."""
        self._load(q_deg, qd_dps)
        self._momentum()
        self._p_previous[:] = self._p
        self._r[:] = 0.0
        self._out[:] = 0.0
        self._started = True

    def update(self, q_deg: ArrayLike, qd_dps: ArrayLike, tau_motor_nm: ArrayLike, dt_s: float) -> FloatArray:
        """One step with the cycle's measured state and motor torques; ``dt_s`` since the previous step.

        Args:
            q_deg: joint angles, deg, configuration order.
            qd_dps: joint speeds, deg/s.
            tau_motor_nm: joint torques of the measured torque currents, N·m.
            dt_s: time since the previous update (or the reset), s.

        Returns:
            The residual (estimated external torque) per joint, N·m, configuration order: the observer's own array.
        """
        if not self._started:
            self.reset(q_deg, qd_dps)
            return self._out
        model, data = self._model, self._data
        self._load(q_deg, qd_dps)
        q, v, work = self._q, self._v, self._work
        np.take(np.asarray(tau_motor_nm, dtype=np.float64), self._to_model, out=self._tau)
        coriolis = pin.computeCoriolisMatrix(model, data, q, v)
        np.dot(coriolis.T, v, out=work)  # C(q, q̇)ᵀ q̇
        work += self._tau
        work -= pin.computeGeneralizedGravity(model, data, q)
        friction = self._friction
        np.divide(v, self._smoothing, out=friction)
        np.tanh(friction, out=friction)
        friction *= self._coulomb
        work -= friction
        np.multiply(self._viscous, v, out=friction)
        work -= friction  # the rate of change of p that the model explains, without the external torque
        self._momentum()
        previous = self._p_previous
        np.subtract(self._p, previous, out=previous)
        previous /= dt_s
        previous -= work  # the external torque of this step
        r = self._r
        previous -= r
        previous *= min(self.gain_per_s * dt_s, 1.0)
        r += previous
        self._p_previous[:] = self._p
        np.take(r, self._to_config, out=self._out)
        return self._out


def momentum_observer(config: ArmConfig) -> MomentumObserver:
    """A momentum observer of ``config``'s arm on a Pinocchio model of its own."""
    return MomentumObserver(build_arm(config), config)
