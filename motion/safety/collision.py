"""The collision check: the momentum observer stepped in every complete cycle, its signal held against a threshold.

The collision observer is injected (:class:`CollisionObserver`; :func:`motion.compose.collision_observer_for` builds
it on the arm's Pinocchio model): this package never imports the model. It is updated in every evaluated cycle in
which every joint's state reply arrived, from the measured angles, speeds and torque currents of the cycle.

What is held against a joint's threshold is the *collision signal*: the residual's change over the last
``collision_window_s`` (with 0, the residual itself). A collision is a torque step, which the residual takes up
within a few cycles; what the model gets wrong changes slowly along the motion and mostly cancels in the difference.
What does not cancel is bounded (:mod:`motion.safety.collision_bound`: the model error a drive may have, the steps of
the reply fields, the current between two samples, the drift of position mode's sample), and the threshold in force
is that bound, or the joint's configured ``collision_threshold_nm`` where that is higher (0, ``bound`` in YAML: the
bound alone; ``rmd-motion collision-calibrate`` proposes it): no configuration takes the check below what a drive
within the stated bounds can show. A contact that builds up more
slowly than the window is left to the following error. The check is armed
:data:`COLLISION_SETTLE_TIME_CONSTANTS` of the observer plus the window after it (re)starts (loop start, ``clear()``):
there the drives take up their whole load at once, and any model error of that load is a step of the residual.

:class:`CollisionCheck` is one of the watchdog's monitors (:class:`motion.safety.watchdog.Watchdog` runs it and
raises what it finds): its own module because the observer's bookkeeping is the watchdog's largest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from motion.control.controller import Controller
from motion.errors import FaultKind, MotionFault
from motion.safety.collision_bound import CollisionBound, Window
from motion.transmission import FloatArray

#: Observer time constants (1 / K_O) after a (re)start before collisions are checked, on top of the window: the
#: residual of the drives taking up their load settles (1 - exp(-3.5) = 97 %).
COLLISION_SETTLE_TIME_CONSTANTS = 3.5


class CollisionObserver(Protocol):
    """An estimate of the external joint torques (``kinematics.observer.MomentumObserver``)."""

    #: The observer gain K_O, 1/s.
    gain_per_s: float

    @property
    def error_terms(self) -> FloatArray:
        """The filtered motor, rotor-inertial and friction torques and the sampling bound (4 × joints, N·m) of the
        latest step."""
        ...

    @property
    def momentum_rate_nm(self) -> FloatArray:
        """The rate of change of the momentum the model explains at the latest step, N·m per joint."""
        ...

    @property
    def mass_kgm2(self) -> FloatArray:
        """M(q) at the latest step, kg·m² (joints × joints)."""
        ...

    @property
    def coulomb_nm(self) -> FloatArray:
        """The modelled Coulomb friction per joint, N·m."""
        ...

    @property
    def coulomb_smoothing_dps(self) -> float:
        """The half-width of the Coulomb model's smoothing, deg/s."""
        ...

    def reset(self, q_deg: ArrayLike, qd_dps: ArrayLike) -> None:
        """Start (again) from this state: the residual is zero."""
        ...

    def update(self, q_deg: ArrayLike, qd_dps: ArrayLike, tau_motor_nm: ArrayLike, dt_s: float) -> FloatArray:
        """One step with the measured state and the joint torques of the measured currents; returns the residual
        per joint, N·m (the observer's array, overwritten by the next step)."""
        ...


class CollisionCheck:
    """The observer's steps, the collision signal, the threshold in force and the check (control thread only).

    Args:
        controller: the controller whose measured state the observer takes.
        observer: the collision observer (None: none runs, no residual is recorded, nothing is checked).
        thresholds_nm: per joint, the configured threshold (inf: not watched); empty: no joint is watched.
        window_s: the collision signal is the residual's change over this long, s (0: the residual).

    Raises:
        ValueError: ``thresholds_nm`` does not give one value per joint.
    """

    def __init__(
        self,
        controller: Controller,
        observer: CollisionObserver | None,
        thresholds_nm: Sequence[float],
        window_s: float,
    ) -> None:
        self.controller = controller
        self.observer = observer
        self._window_s = window_s
        n = len(controller.specs)
        self.names = tuple(s.name for s in controller.specs)
        self.threshold = np.array(thresholds_nm, dtype=np.float64) if thresholds_nm else np.full(n, np.inf)
        if self.threshold.shape != (n,):
            raise ValueError(f"collision_threshold_nm: expected {n} values (one per joint), got {len(thresholds_nm)}")
        self._tau_motor = np.zeros(n)
        self._over = np.zeros(n, dtype=bool)
        self._share = np.zeros(n)
        self._observed_s = math.nan  # when the observer last stepped; NaN: reset it at the next step
        #: The latest residual per joint, N·m (NaN before the first observer step).
        self.residual_nm = np.full(n, np.nan)
        #: The latest collision signal per joint (the residual's change over the window), N·m.
        self.signal_nm = np.full(n, np.nan)
        #: The latest threshold in force per joint: the configured one, or the bound where that is higher, N·m.
        self.limit_nm = self.threshold.copy()
        self.bound = CollisionBound(controller, observer) if observer is not None else None
        self._zero_bound = np.zeros(n)
        self._window = Window(window_s, controller.period_s, n)
        self._steps = 0  # observer steps since its (re)start
        self._reset_s = math.nan  # when it (re)started
        settle = COLLISION_SETTLE_TIME_CONSTANTS / observer.gain_per_s if observer is not None else 0.0
        #: How long after the observer (re)starts the collision check is armed, s.
        self.arming_s = settle + window_s
        #: The loop cycle count of the cycle that computed :attr:`residual_nm` (-1: none yet).
        self.residual_cycle = -1

    def restart(self) -> None:
        """The observer starts again from the measured state at its next step (loop start, ``clear()``)."""
        self._observed_s = math.nan

    def run(self, *, check: bool) -> None:
        """The cycle's step of the observer, then, if ``check`` (not while the arm yields to a collision) and the
        check is armed, the check.

        Raises:
            MotionFault: kind ``collision``, naming every joint over its threshold (the worst in ``joint``).
        """
        if self.observer is not None and self._observe() and check and self.armed:
            self._check()

    def _observe(self) -> bool:
        """Step the observer with the cycle's measurements (sampled when the cycle's exchange went out); False when a
        joint's state reply is missing (the next complete cycle integrates over the gap)."""
        observer, axes = self.observer, self.controller.axes
        assert observer is not None and self.bound is not None
        if not axes.fresh.all():
            return False
        sampled_s = self.controller.exchanged_s
        residual, signal, window = self.residual_nm, self.signal_nm, self._window
        if math.isnan(self._observed_s):
            observer.reset(axes.q_deg, axes.qd_dps)
            self.bound.restart()
            dt_s = 0.0
            residual[:] = 0.0
            window.clear()
            self._steps = 0
            self._reset_s = sampled_s
        else:
            tau = self.controller.transmission.joint_torque_nm(axes.iq_a, out=self._tau_motor)
            dt_s = sampled_s - self._observed_s
            residual[:] = observer.update(axes.q_deg, axes.qd_dps, tau, dt_s)
        terms = self.bound.step(dt_s)
        base = window.push(sampled_s, residual, terms)
        if self._window_s:
            np.subtract(residual, window.residual[base], out=signal)
        else:
            signal[:] = residual
        self.bound.limit(window, base, self.threshold, out=self.limit_nm)
        self._observed_s = sampled_s
        self._steps += 1
        self.residual_cycle = self.controller.loop.cycles
        return True

    @property
    def bound_nm(self) -> FloatArray:
        """The latest bound of the collision signal per joint, N·m (:mod:`motion.safety.collision_bound`; zeros
        without an observer): the check's array."""
        return self.bound.bound_nm if self.bound is not None else self._zero_bound

    @property
    def guarding(self) -> bool:
        """Whether a collision check runs: an observer, and a threshold on at least one joint."""
        return self.observer is not None and bool(np.isfinite(self.threshold).any())

    @property
    def armed(self) -> bool:
        """Whether the latest collision signal was (or would have been) held against the thresholds: the observer
        has settled since its (re)start (calibration looks only at these cycles)."""
        return self._steps > 1 and self._observed_s - self._reset_s >= self.arming_s

    def _check(self) -> None:
        residual, threshold, over = self.signal_nm, self.limit_nm, self._over
        np.abs(residual, out=self._share)
        np.greater(self._share, threshold, out=over)
        if not over.any():
            return
        self._share /= threshold
        worst = int(np.argmax(self._share))
        hit = [self.names[i] for i in np.flatnonzero(over)]
        detail = "collision signal (residual change): " + ", ".join(
            f"{self.names[i]} {residual[i]:+.2f} N·m (threshold {threshold[i]:.3g})" for i in np.flatnonzero(over)
        )
        raise MotionFault(
            FaultKind.COLLISION,
            joint=self.names[worst],
            value=float(residual[worst]),
            threshold=float(threshold[worst]),
            time_s=self.controller.clock.now(),
            detail=detail,
            joints=tuple(hit),
        )
