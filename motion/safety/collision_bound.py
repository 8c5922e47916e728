"""The collision check's bound: how large the collision signal can grow on a drive that differs from its model while
nothing touches the arm, from the stated bounds of what the observer cannot know (see :mod:`motion.safety.collision`).

Per joint, over the window, in N·m:

- **model error**: ``Σ εⱼ |ΔFⱼ|`` over the observer's filtered motor, rotor-inertial and friction torques
  (:attr:`kinematics.observer.MomentumObserver.error_terms`), ε = :data:`MODEL_ERROR`: a drive
  whose figure is off by ε puts exactly ``ε × Fⱼ`` into the residual (the filter is linear), so its change over the
  window is ``ε × ΔFⱼ``;
- **sampling**: the trapezoid rule takes the motor torque between two samples as their mean; a torque that changes
  monotonically between them is off by at most half the change, through the filter, at each end of the window (in
  position mode a drive's loop can push right after each 0xA4 step and brake before the next sample, so that its
  current between two samples swings beyond both: the next row);
- **position-mode steps**: a 0xA4 target moves by ``v dt`` each cycle; a drive whose loops are faster than the
  period answers each step with a push and a brake inside the cycle (its speed ripples by up to the angle loop's
  ``k v dt``), and the current sampled at the cycle's exchange is the same phase of that response every cycle, not
  the cycle's mean. A drive whose speed loop is ideal samples the brake that ends each step's response,
  ``M k v``, where the mean is the acceleration's torque ``M a``; and every joint's drive does the same at the same
  instants, which reaches its neighbours through M's off-diagonal terms: the sample is off by up to
  ``X = |M| (k |v| + |a|)`` (``|M|``: M(q) with its terms' magnitudes; ``k``: the tracking model's angle-loop
  gain, twice its prior where the drives' settings are not read; ``v``: the reference's speed, or the speed the
  tracking model expects of the drive at this sample or the one before where larger, the speed of the step this
  sample ends (a drive still closing the lag of the stream's last step brakes as hard; at a low rate it does so for a
  whole period after the stream has stopped; the model's speed, which a collision does not change); ``a``: the
  reference's acceleration), times :data:`STEP_SHARE` for a speed loop that
  overshoots. The phase being the same every
  cycle, the signal moves by the change of that (filtered as the residual) over the window, not by ``X`` itself;
  a step longer or shorter than the one before by a share ``f``
  of the period moves the sample within the response, by up to ``f X`` (at most ``X``), at each end of the
  window. The phase is the same every cycle only as far as the drive's response is linear and its state the same
  from step to step: a drive whose loops saturate or whose speed and acceleration change along the path moves the
  sample by up to :data:`STEP_DRIFT` of ``X`` at each end of the window, plus :data:`STEP_FLOOR_STEPS` steps of the
  current field. These position-mode rows are a model of the drives' response; drives at the corners of the stated
  bounds (every joint's loop tuning doubled with the rotor inertia 30 % up and the torque constant 20 % down) exceed
  them by up to :data:`POSITION_MARGIN` (less 7 %), and the sum of every row is taken that many times in position
  mode;
- **saturated current**: in position mode a sample at the drive's current limit (within a step of the configured
  ``current_limit_a``) says only that the current between it and its neighbours stayed within the limit ``L``: a
  drive pinned there by each step's push and let off before the next sample (a stiff loop on a heavy joint at a low
  rate) has a mean anywhere in ``±L``, so the trapezoid is off by up to ``2 L`` (filtered, at each end of the window).
  While a joint's drive samples at its limit the check on that joint is as good as blind: a drive without headroom
  cannot push back at a contact either, and the following error takes it (the joint falls behind);
- **friction at rest**: within :data:`REST_BAND_SMOOTHINGS` smoothing widths of the observer's Coulomb model (plus
  a step of the speed field) of rest, the joint's friction is anything up to its breakaway, ``(1 + ε) F_c``, either
  way (a joint held by stiction takes whatever torque the drive pushes with), and its sampled speed does not say
  which way the smoothed model should take it: at each end of the window, the filtered ``(1 + ε) F_c`` of the steps
  at rest;
- **field steps**: the speed field comes in steps ``s`` (1 deg/s of what the drive reports: of the motor for the
  older family, of the output for V3), rounded; in the momentum ``M q̇`` a rounding error ``e`` puts
  ``K_O M (e − ē)`` into the residual (``ē`` the filtered past errors), at most ``K_O M s`` at each end: ``2 K_O M s``
  with M at the step, every joint's speed through M's row (``|M| s``: a shoulder's speed step reaches the wrist's
  momentum); the current field's step puts at most one step's torque into the change.

- **sampling instant**: a drive answers with its state as of its own latest loop step, so the instant its reply
  sampled is up to :data:`SAMPLE_INSTANT_S` before the request's arrival, and where the arrival moves (the reply
  jitter, the host) it moves between steps: the measured momentum's change is then off the interval's by up to
  ``ṗ × SAMPLE_INSTANT_S``, which puts ``K_O |ṗ| SAMPLE_INSTANT_S`` into the residual (``ṗ``: the momentum's rate of
  change the model explains), decaying as the residual does (the instants stay within their span: their errors
  telescope), at each end of the window.

The timing: the observer steps over the measured interval between the exchanges that sampled the drives (a late
cycle is a longer step, not an error); the frames' positions in their batch are the same every cycle, the drive's
sample within its loop step is the row above.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from motion.transmission import FloatArray

if TYPE_CHECKING:
    from motion.control.controller import Controller
    from motion.safety.collision import CollisionObserver

#: The model error the collision check bears without a false fault, as a fraction of the configured figure: the
#: drive's torque constant, its rotor inertia, the joint's friction (viscous and Coulomb).
MODEL_ERROR = (0.2, 0.3, 0.5)
#: Rows of the window's error terms: the observer's motor, rotor-inertial, friction torque (scaled by the model
#: error) and sampling bound (taken at both ends of the window), the position-mode steps' ``X`` (its change), friction
#: at rest, the steps' phase, the sampling instant and a current pinned at its limit (those four at both ends).
TERM_ROWS = 9
_OBSERVER_ROWS = 4
_SAMPLING_ROW = 3
_STEP_ROW = 4
_REST_ROW = 5
_PHASE_ROW = 6
_INSTANT_ROW = 7
_SATURATED_ROW = 8
#: taken at both ends of the window (the others: their change)
_END_ROWS = (_SAMPLING_ROW, _REST_ROW, _PHASE_ROW, _INSTANT_ROW, _SATURATED_ROW)
#: The most of ``X`` the sample is off by: an ideal speed loop's brake is ``X``; a real one's overshoot adds to it
#: (the example arms' drawn drives: up to 1.2).
STEP_SHARE = 1.25
#: Position mode: how far the sample moves within the drive's response along a path: a share of ``X`` at each end of
#: the window, plus current steps (module doc). Drives drawn within the stated bounds on the example arms' paths
#: (tests/clean_sweep.py, 200 cases each) needed up to 0.004 of ``X`` with 5 current steps (seed 30) and 0.016 with
#: 3.4 (seed 11): taken 0.03 and 6.
STEP_DRIFT = 0.03
STEP_FLOOR_STEPS = 6.0
#: Position mode: the bound is its rows' sum times this (module doc): bench/calibrate_examples.py's corners reached 1.21
#: of the sum (arm6_v3's wrist_roll on the demo's path, every drive tuned twice the factory's).
POSITION_MARGIN = 1.3
#: A joint counts as at rest for the friction-at-rest row within this many smoothing widths of the observer's
#: Coulomb model (tanh(3) = 0.995 of the friction), plus one step of the speed field.
REST_BAND_SMOOTHINGS = 3.0
#: Where the drives' loop settings are not read, their angle-loop gain may be this many times the tracking model's
#: prior (the tuning drawn in the tests: half to twice the factory's).
UNREAD_GAIN_FACTOR = 2.0
#: How far before a request's arrival the state a drive answers with may have been sampled: its loop step, s. Taken
#: as the emulated drives' integration step (``motion.emulator.core.DEFAULT_STEP_S``, 2 kHz); a drive whose loops
#: sample its state more often is within it.
SAMPLE_INSTANT_S = 0.5e-3
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
        families, specs = controller.families, controller.specs
        transmissions = controller.transmission.transmissions
        self._observer = observer
        self._error = np.array((*MODEL_ERROR, 0.0, STEP_SHARE, 0.0, 0.0, 0.0, 0.0), dtype=np.float64)[:, None]
        # the speed field's step in joint rad/s, times 2 K_O (through |M| at each step)
        step_rad_s = np.array(
            [
                math.radians(abs(t.joint_rate(f.speed_step_dps * s.drive_gear_ratio)))
                for s, t, f in zip(specs, transmissions, families, strict=True)
            ]
        )
        self._speed = 2.0 * observer.gain_per_s * step_rad_s
        steps_a = np.array([f.current_step_a for f in families])
        self._current = np.abs(controller.transmission.joint_torque_nm(steps_a))
        self._drift_floor = STEP_FLOOR_STEPS * self._current
        # a sample at the current limit (within a step of it), A, and the swing the mean may then have, N·m
        self._saturated_a = np.array([t.current_limit_a for t in transmissions]) - steps_a
        self._swing_nm = 2.0 * controller.tracking.torque_limit_nm
        self._saturated = np.zeros(len(specs), dtype=bool)
        self._delta = np.zeros((TERM_ROWS, len(specs)))
        #: The latest bound per joint, N·m.
        self.bound_nm = np.zeros(len(specs))
        #: Its speed field's row at the latest step (``2 K_O |M| s``, every joint's step through the joint's row), N·m.
        self.field_nm = np.zeros(len(specs))
        # position mode: the steps' X = |M| (k |v| + |a|) per joint (M from the observer, k from the tracking model, v
        # and a from the reference), filtered as the residual; the terms of the latest step, all rows
        self._controller = controller
        self._steps = controller.options.mode.traits.drive_position_loop
        self._gain_factor = np.array([1.0 if f.reads_loop_settings else UNREAD_GAIN_FACTOR for f in families])
        self._x = np.zeros(len(specs))
        self._gain = np.zeros(len(specs))
        self._speed_before = np.zeros(len(specs))  # the model's expected speed at the previous step, deg/s
        self._mass = np.zeros((len(specs), len(specs)))
        self._dt_before = 0.0
        self._period_s = controller.period_s
        self._instant_gain = observer.gain_per_s * SAMPLE_INSTANT_S
        # friction at rest: the band of measured joint speeds, deg/s, and the breakaway bound, N·m
        self._rest_band_dps = np.degrees(step_rad_s) + REST_BAND_SMOOTHINGS * observer.coulomb_smoothing_dps
        self._breakaway_nm = (1.0 + MODEL_ERROR[2]) * observer.coulomb_nm
        self._at_rest = np.zeros(len(specs), dtype=bool)
        self.terms = np.zeros((TERM_ROWS, len(specs)))

    def restart(self) -> None:
        """The observer (re)started: the filtered terms start again from zero, as the observer's do."""
        self.terms[:] = 0.0
        self._dt_before = 0.0
        self._speed_before[:] = 0.0

    def step(self, dt_s: float) -> FloatArray:
        """The error terms of the observer's latest step (``dt_s`` long), with this bound's own rows: the array the
        window keeps."""
        terms, x, controller = self.terms, self._x, self._controller
        share = min(self._observer.gain_per_s * dt_s, 1.0)
        terms[:_OBSERVER_ROWS] = self._observer.error_terms
        np.abs(self._observer.mass_kgm2, out=self._mass)
        at_rest = self._at_rest
        np.abs(controller.axes.qd_dps, out=x)
        np.less_equal(x, self._rest_band_dps, out=at_rest)
        np.multiply(self._breakaway_nm, at_rest, out=x)
        self._filter(_REST_ROW, share)
        # the sampling instant: K_O |ṗ| SAMPLE_INSTANT_S now, or what an earlier step's has decayed to
        instant = terms[_INSTANT_ROW]
        instant *= 1.0 - share
        np.abs(self._observer.momentum_rate_nm, out=x)
        x *= self._instant_gain
        np.maximum(instant, x, out=instant)
        if self._steps:
            gain, reference = self._gain, controller.reference
            # the speed of the step that ends at this sample: the reference's, or the drive's own as the tracking
            # model expects it where the drive is still closing its lag (at a low rate, for a whole period after the
            # stream has stopped); the model's, not the measured speed, which a collision changes
            np.abs(reference.velocity, out=gain)
            np.abs(controller.tracking.expected_dps, out=x)
            np.maximum(gain, x, out=gain)
            np.maximum(gain, self._speed_before, out=gain)
            np.copyto(self._speed_before, x)
            gain *= controller.tracking.angle_gain_per_s
            gain *= self._gain_factor
            gain += np.abs(reference.acceleration, out=x)
            gain *= math.pi / 180.0
            np.dot(self._mass, gain, out=x)  # each joint's own ripple and its neighbours' through M
            # where the sample falls in the drive's response moves with the step's length: a step longer or shorter
            # than the one before by a share f of the period moves it by up to f of the response (at most all of it)
            change = min(abs(dt_s - self._dt_before) / self._period_s, 1.0) if self._dt_before else 0.0
            np.multiply(x, change, out=gain)
            self._filter(_STEP_ROW, share)
            np.copyto(x, gain)
            self._filter(_PHASE_ROW, share)
            np.abs(controller.axes.iq_a, out=x)
            np.greater_equal(x, self._saturated_a, out=self._saturated)
            np.multiply(self._swing_nm, self._saturated, out=x)
            self._filter(_SATURATED_ROW, share)
        self._dt_before = dt_s
        return terms

    def _filter(self, row: int, share: float) -> None:
        """Take the row's new value (in ``self._x``) up through the residual's filter (``share`` of the step)."""
        x, terms = self._x, self.terms
        x -= terms[row]
        x *= share
        terms[row] += x

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
        for row in _END_ROWS:
            bound += head[row]
            if window.window_s:
                bound += start[row]
        np.dot(self._mass, self._speed, out=self.field_nm)
        bound += self.field_nm
        bound += self._current
        if self._steps:  # the sample's drift within the drive's response (module doc), at each end of the window
            np.add(head[_STEP_ROW], start[_STEP_ROW], out=self._delta[0])
            self._delta[0] *= STEP_DRIFT
            bound += self._delta[0]
            bound += self._drift_floor
            bound *= POSITION_MARGIN
        return np.maximum(configured, bound, out=out)
