"""The generalized momentum observer (De Luca et al.; Haddadin, De Luca and Albu-Schäffer, "Robot Collisions",
IEEE T-RO 2017): an estimate of the external joint torques from the drives' measured currents and speeds.

With the generalized momentum ``p = M(q) q̇`` and ``ṗ = τ_m + τ_ext − τ_f + C(q, q̇)ᵀ q̇ − g(q)``, the residual

    r = K_O (p − p0 − ∫ (τ_m + C(q, q̇)ᵀ q̇ − g(q) − τ_f + r) dt)

obeys ``ṙ = K_O (τ_ext − r)``: a first-order filter of the external torque, per joint, decoupled by the model, with
no acceleration measured. ``τ_m`` is the joint torque of the measured torque current (direction × gear ratio ×
torque constant × iq), ``τ_f`` the joint's friction model (viscous + Coulomb), ``M`` includes the rotors
(``gear_ratio² × rotor inertia`` as Pinocchio's armature).

Discretised once per control cycle with the cycle's measured values, over the measured interval between the
exchanges that sampled the drives. Differencing the integral form between two cycles gives the form computed here,

    r_k = r_{k−1} + K_O·dt · ((p_k − p_{k−1}) / dt − ½ (w_k + w_{k−1}) − r_{k−1}),   w = τ_m + Cᵀq̇ − g − τ_f,

with the trapezoid rule for the rate the model explains, as ``(p_k − p_{k−1}) / dt`` is the step's mean rate (the
rectangle rule's error is half a step of the torque's rate of change: 0.16 N·m on a 1:9 joint whose drive rings at
4 Hz). ``K_O·dt`` is the share of a torque step the residual takes up per step (stable and without overshoot up to
1); a late cycle (real time) has a longer dt, and the share is capped at 1 there.

**What the residual cannot know** (:meth:`MomentumObserver.error_terms`): the same filter applied to the terms the
drive's true figures scale — the motor torque (the torque constant), the rotor's inertial torque
(``gear_ratio² J q̈``), the friction torque — so that a drive whose figures are off by a fraction ε puts exactly
``ε ×`` that filtered term into the residual; and M(q), through which the speed field's steps enter.
:mod:`motion.safety.watchdog` bounds the collision signal's false part with them.

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
        gain_per_s: the gain K_O, 1/s (default ``safety.collision_observer_gain_per_s``).
    """

    def __init__(self, arm: ArmModel, config: ArmConfig, gain_per_s: float | None = None) -> None:
        joints = config.joints
        n = len(joints)
        self._model, self._data = arm.model, arm.data
        self._to_model = arm.to_model  # model coordinate -> configuration index
        self._to_config = arm.to_config  # configuration index -> model coordinate
        #: The observer gain K_O, 1/s.
        self.gain_per_s = config.safety.collision_observer_gain_per_s if gain_per_s is None else gain_per_s
        cfg = [joints[i] for i in self._to_model]  # model order below
        self._armature = np.array([j.gear_ratio**2 * j.rotor_inertia_kgm2 for j in cfg])
        self._model.armature = self._armature.copy()
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
        self._explained = np.zeros(n)  # the rate of change of p the model explained at the previous step
        self._rate_out = np.zeros(n)
        self._v_previous = np.zeros(n)
        # the filtered error terms (model order): motor torque, rotor inertial torque, friction torque, half the motor
        # torque's change over the step (what the trapezoid rule may miss of it); their
        # values at the previous step (for the trapezoid rule); and the terms and M in configuration order
        self._terms = np.zeros((4, n))
        self._terms_previous = np.zeros((4, n))
        self._inputs = np.zeros((4, n))
        self._terms_out = np.zeros((4, n))
        self._mass_rows = np.zeros((n, n))
        self._mass_out = np.zeros((n, n))
        self._started = False
        self._first = True

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
        mass = crba_full(self._model, self._data, self._q)
        np.dot(mass, self._v, out=self._p)
        np.take(mass, self._to_config, axis=0, out=self._mass_rows)
        np.take(self._mass_rows, self._to_config, axis=1, out=self._mass_out)

    @property
    def error_terms(self) -> FloatArray:
        """The latest filtered motor, rotor-inertial and friction torques, N·m, rows in that order, one column per
        joint in configuration order (the observer's array): a drive whose torque constant, rotor inertia or
        friction is off by the fraction ε puts ``ε ×`` its row's value into the residual; a fourth row, the filtered
        half change of the motor torque per step, bounds what the trapezoid rule misses of a torque that changes
        monotonically between two samples."""
        return self._terms_out

    @property
    def momentum_rate_nm(self) -> FloatArray:
        """The rate of change of the momentum ``M q̇`` the model explains at the latest step (motor, gravity,
        Coriolis and friction torques), N·m, configuration order (the observer's array)."""
        return self._rate_out

    @property
    def mass_kgm2(self) -> FloatArray:
        """M(q) at the latest step (rotors included), kg·m², configuration order (the observer's array)."""
        return self._mass_out

    @property
    def coulomb_nm(self) -> FloatArray:
        """The modelled Coulomb friction per joint, N·m, configuration order (smoothed over ±``COULOMB_SMOOTHING_DPS``:
        within a few times that of rest the friction the model takes is not the joint's)."""
        return self._coulomb[self._to_config]

    @property
    def coulomb_smoothing_dps(self) -> float:
        """The half-width of the Coulomb model's smoothing, deg/s."""
        return math.degrees(self._smoothing)

    def reset(self, q_deg: ArrayLike, qd_dps: ArrayLike) -> None:
        """Start (again) at this state: p0 = M(q) q̇, the residual zero."""
        self._load(q_deg, qd_dps)
        self._momentum()
        self._p_previous[:] = self._p
        self._v_previous[:] = self._v
        self._r[:] = 0.0
        self._out[:] = 0.0
        self._terms[:] = 0.0
        self._terms_out[:] = 0.0
        self._started = True
        self._first = True  # (no rate explained before the first step: the rectangle rule there)

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
        friction, inputs = self._friction, self._inputs
        np.divide(v, self._smoothing, out=friction)
        np.tanh(friction, out=friction)
        friction *= self._coulomb
        inputs[2] = friction
        np.multiply(self._viscous, v, out=friction)
        inputs[2] += friction  # the friction torque
        work -= inputs[2]  # the rate of change of p that the model explains, without the external torque
        inputs[0] = self._tau
        np.subtract(v, self._v_previous, out=inputs[1])
        inputs[1] *= self._armature
        inputs[1] /= dt_s  # the rotors' inertial torque over the step (its mean, as p's change)
        self._momentum()
        share = min(self.gain_per_s * dt_s, 1.0)
        explained, previous = self._explained, self._terms_previous
        if self._first:  # no rate explained before the first step: the rectangle rule there
            explained[:] = work
            previous[:] = inputs
            self._first = False
        explained += work
        explained *= 0.5
        rate = self._p_previous
        np.subtract(self._p, rate, out=rate)
        rate /= dt_s
        np.subtract(inputs[0], previous[0], out=inputs[3])
        np.abs(inputs[3], out=inputs[3])
        inputs[3] *= 0.5
        # the error terms through the residual's own filter (the inertial term is a step's mean already)
        previous += inputs
        previous *= 0.5
        previous[1] = inputs[1]
        previous[3] = inputs[3]
        previous -= self._terms
        previous *= share
        self._terms += previous
        previous[:] = inputs
        rate -= explained  # the external torque of this step
        explained[:] = work
        r = self._r
        rate -= r
        rate *= share
        r += rate
        self._p_previous[:] = self._p
        self._v_previous[:] = v
        np.take(r, self._to_config, out=self._out)
        np.take(self._terms, self._to_config, axis=1, out=self._terms_out)
        np.take(work, self._to_config, out=self._rate_out)
        return self._out


def momentum_observer(config: ArmConfig) -> MomentumObserver:
    """A momentum observer of ``config``'s arm on a Pinocchio model of its own."""
    return MomentumObserver(build_arm(config), config)
