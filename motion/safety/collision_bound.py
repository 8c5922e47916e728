"""The collision check's bound: how large the collision signal can grow on a drive that differs from its model while
nothing touches the arm, from the stated bounds of what the observer cannot know (see :mod:`motion.safety.watchdog`).

Per joint, over the window, in N·m:

- **model error**: ``Σ εⱼ |ΔFⱼ|`` over the observer's filtered motor, rotor-inertial and friction torques
  (:attr:`kinematics.observer.MomentumObserver.error_terms`), ε = :data:`MODEL_ERROR`: a drive
  whose figure is off by ε puts exactly ``ε × Fⱼ`` into the residual (the filter is linear), so its change over the
  window is ``ε × ΔFⱼ``;
- **sampling**: the trapezoid rule takes the motor torque between two samples as their mean; a torque that changes
  monotonically between them is off by at most half the change, through the filter, at each end of the window (in
  position mode a drive's loop can push right after each 0xA4 step and brake before the next sample, so that its
  current between two samples swings beyond both: that part is not bounded here, and a configured threshold above
  the bound covers it, see the configuration reference);
- **field steps**: the speed field comes in steps ``s`` (1 deg/s of what the drive reports: of the motor for the
  older family, of the output for V3), rounded; in the momentum ``M q̇`` a rounding error ``e`` puts
  ``K_O M (e − ē)`` into the residual (``ē`` the filtered past errors), at most ``K_O M s`` at each end: ``2 K_O M s``
  with M's diagonal at the step; the current field's step puts at most one step's torque into the change.

The timing: the observer steps over the measured interval between the exchanges that sampled the drives (a late
cycle is a longer step, not an error); the frames' positions in their batch are the same every cycle.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from motion.transmission import FloatArray

if TYPE_CHECKING:
    from motion.control.controller import Controller
    from motion.safety.watchdog import CollisionObserver

#: The model error the collision check bears without a false fault, as a fraction of the configured figure: the
#: drive's torque constant, its rotor inertia, the joint's friction (viscous and Coulomb).
MODEL_ERROR = (0.2, 0.3, 0.5)
#: Rows of the observer's error terms: motor, rotor-inertial, friction torque (scaled by the model error), the
#: sampling bound (taken at both ends of the window).
TERM_ROWS = 4
_SAMPLING_ROW = 3
#: Times closer than this count as the same instant (simulated time's sums of periods), s.
_SAME_S = 1e-6


class Window:
    """The observer's latest steps, enough to span the window: a ring of times, residuals and error terms.

    Args:
        window_s: the window, s (0: none).
        period_s: the nominal control period, s (the ring holds the window's steps at this rate, and its ends).
        n: joints.
    """

    def __init__(self, window_s: float, period_s: float, n: int) -> None:
        self.window_s = window_s
        self.size = math.ceil(window_s / period_s - _SAME_S) + 2
        self.times = np.full(self.size, math.nan)
        self.residual = np.zeros((self.size, n))
        self.terms = np.zeros((self.size, TERM_ROWS, n))
        self.head = 0
        self._newest = -1  # step number of the newest entry (slot: number % size)
        self._base = 0  # step number of the entry the window starts from

    def clear(self) -> None:
        """Forget every step (the observer restarts)."""
        self._newest = -1
        self._base = 0

    def push(self, time_s: float, residual: FloatArray, terms: FloatArray) -> int:
        """Keep a step; returns the slot of the latest step at or before ``time_s − window`` (else the oldest)."""
        size = self.size
        newest = self._newest = self._newest + 1
        head = self.head = newest % size
        self.times[head] = time_s
        self.residual[head] = residual
        self.terms[head] = terms
        base = max(self._base, newest - size + 1)
        start = time_s - self.window_s + _SAME_S
        while base < newest and self.times[(base + 1) % size] <= start:
            base += 1
        self._base = base
        return base % size


class CollisionBound:
    """The bound of the collision signal per joint (module doc), and the threshold in force: the configured one, or
    the bound where that is higher."""

    def __init__(self, controller: Controller, observer: CollisionObserver) -> None:
        family, specs = controller.family, controller.specs
        transmissions = controller.transmission.transmissions
        self._observer = observer
        self._error = np.array((*MODEL_ERROR, 0.0), dtype=np.float64)[:, None]
        # the speed field's step in joint rad/s, times 2 K_O (times M's diagonal at each step)
        step_rad_s = np.array(
            [
                math.radians(abs(t.joint_rate(family.speed_step_dps * s.drive_gear_ratio)))
                for s, t in zip(specs, transmissions, strict=True)
            ]
        )
        self._speed = 2.0 * observer.gain_per_s * step_rad_s
        self._current = np.abs(controller.transmission.joint_torque_nm(np.full(len(specs), family.current_step_a)))
        self._delta = np.zeros((TERM_ROWS, len(specs)))
        #: The latest bound per joint, N·m.
        self.bound_nm = np.zeros(len(specs))

    def limit(self, window: Window, base: int, configured: FloatArray, out: FloatArray) -> FloatArray:
        """The threshold in force at the window's newest step (from ``base``): the bound, or ``configured`` where
        that is higher (inf: a joint not watched)."""
        head = window.terms[window.head]
        start = window.terms[base]
        delta, bound = self._delta, self.bound_nm
        if window.window_s:
            np.subtract(head, start, out=delta)
        else:
            delta[:] = head
        np.abs(delta, out=delta)
        delta *= self._error
        np.sum(delta, axis=0, out=bound)
        bound += head[_SAMPLING_ROW]
        if window.window_s:
            bound += start[_SAMPLING_ROW]
        np.multiply(self._speed, self._observer.inertia_kgm2, out=self._delta[0])
        bound += self._delta[0]
        bound += self._current
        return np.maximum(configured, bound, out=out)
