"""The overspeed check: a measured joint speed beyond what a healthy joint reaches is a fault in the cycle it is seen.

Nothing asks a joint for more than its ``velocity_limit_dps`` ``v``: the planner plans at most that (position mode
90 % of it), and in position mode the 0xA4 speed cap, which limits the drive's own position loop ("maxSpeed limits
the maximum speed at which the motor rotates", v2.3's 0xA4; V4.2's likewise for the output shaft), is at most ``v``
too (:class:`motion.control.setpoints.PositionSetpoints`). A healthy joint's measured speed differs from what it is
asked for, per joint (joint side, deg/s), by:

- **the loop's overshoot**, ``ε Q v``: the loop that moves the joint (the drive's speed loop under the cap in position
  mode; in torque mode the controller's PD with the feed-forward, which the tracking model runs on the model arm,
  :mod:`motion.control.tracking`) asks for torque through the drive's torque constant, and a drive within the stated
  model error delivers ``1 + ε`` of it (``ε`` = :data:`OVERSHOOT_SHARE`, the torque constant's share of
  :data:`motion.safety.collision_bound.MODEL_ERROR`, 20 %; the following error's torque-mode allowance takes the same
  share of the motion the loop's torques make). The excess torque moves the joint against the loop, whose response
  to it peaks at the loop's resonance: the joint's speed error is the reference's speed through the loop's
  high-pass ``s² / (s² + 2ζω s + ω²)``, whose peak gain is ``Q = 1 / (2ζ √(1 − ζ²))`` for ``ζ < 1/√2`` and 1 above.
  Position mode: the drive's speed loop, which the tracking model takes as ideal (tuned to its load), ``Q = 1``.
  Torque mode: the PD on the joint's inertia ``J`` (the model arm's ``M(q)`` diagonal, the largest the arm has had
  since the loop started: its inertia grows as it stretches out, and a lightly damped loop rings most there),
  ``ω = √(Kp / J)``, ``ζ = Kd / (2 √(Kp J))``: arm6_v3's stretched-out base (Kp 0.2 N·m/deg, Kd 0.009 N·m·s/deg)
  has ``ζ`` ≈ 0.1 and rings up to several times the torque error's share (a drive 19 % weak, its base sped up by the
  arm folding in, read 1.5 ``v``: ``tests/test_false_faults.py``), arm2's elbow ``ζ`` ≈ 0.5. Without an inertia (no
  arm model) the tracking model has no loop to take it from, and ``Q = 1``;
- **the reading's step**: the speed field counts whole steps of what the drive reports (1 deg/s of the motor for the
  older family, of the output shaft for V3: the table's ``speed_dps`` of 0x9C), rounded or cut: up to one step,
  through the gear (:attr:`motion.control.axes.AxisStates.speed_step_dps`: 0.11 deg/s on a 1:9 joint of the older
  family, 1 deg/s on a V3 drive's). Neither document states a noise of the speed measurement beyond its field;
- **the cap's step** (position mode): the cap goes out in whole steps of its field (1 deg/s of the motor on the older
  family's CAN, 0.01 on its RS485, 1 deg/s of the output on V3), rounded to the nearest: taken as one step.

So the limit is ``v (1 + ε Q) + reading step (+ cap step)``, per joint: :attr:`OverspeedCheck.limit_dps` (in torque
mode it grows with the inertia, never shrinks). A joint beyond it is moved by something no healthy loop does: a loop
that diverged (a torque-mode PD at a rate its gains do not hold: arm2 at 40 Hz sends its elbow to six times its
velocity limit and its encoder past half a motor turn between two readings), a drive that no longer keeps to its own
cap, a transmission that slipped, or a push the drive does not resist. The limit follows the arm's inertia at the
reference's poses, never the loop's own state, so that a loop that diverges does not carry its limit with it. It is
not holdable (:data:`motion.errors.HOLDABLE`): the stop ramp would stream through the same loop.

:class:`OverspeedCheck` is one of the watchdog's monitors (:class:`motion.safety.watchdog.Watchdog` runs it in every
evaluated cycle but those of an arm yielding to a collision (``comply``), every joint, both modes).
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np

from motion.control.controller import Controller
from motion.errors import FaultKind, MotionFault
from motion.protocol.table import split_address
from motion.safety.collision_bound import MODEL_ERROR
from motion.transmission import FloatArray

#: The share of the torque a drive within the stated model error delivers beyond what its loop asks: the torque
#: constant's (module doc).
OVERSHOOT_SHARE: Final = MODEL_ERROR[0]
_DEG_PER_RAD = 180.0 / math.pi


def resonance_gain(damping_ratio: FloatArray) -> FloatArray:
    """The peak gain of the second-order high-pass ``s² / (s² + 2ζω s + ω²)`` per damping ratio ``ζ`` (inf at 0)."""
    zeta = np.asarray(damping_ratio, dtype=np.float64)
    light = zeta < math.sqrt(0.5)
    gain = np.ones_like(zeta)
    with np.errstate(divide="ignore"):
        np.divide(1.0, 2.0 * zeta * np.sqrt(np.maximum(1.0 - zeta * zeta, 0.0)), out=gain, where=light)
    return gain


class OverspeedCheck:
    """Every joint's measured speed against its overspeed limit (module doc; control thread only).

    Args:
        controller: the controller whose measured speeds are checked (its joints' velocity limits, drives, wires,
            control mode, PD gains and tracking model give the limits).
    """

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        specs, families = controller.specs, controller.families
        n = len(specs)
        self.names = tuple(s.name for s in specs)
        transmissions = controller.transmission.transmissions
        #: Per joint, the velocity limit, joint deg/s.
        self.velocity_limit_dps = np.abs(np.array(controller.limits.velocity_dps, dtype=np.float64))
        # what the limit adds to the loop's overshoot: the steps of the reading and, in position mode, of the cap
        self._steps_dps = controller.axes.speed_step_dps.copy()
        self._host_loop = controller.options.mode.traits.host_torque
        if controller.options.mode.traits.drive_position_loop:
            wires = controller.options.wires
            self._steps_dps += [
                abs(t.joint_rate(f.speed_cap_step_dps(wires[split_address(s.motor_id)[0]]) * s.drive_gear_ratio))
                for s, t, f in zip(specs, transmissions, families, strict=True)
            ]
        # torque mode: the PD's stiffness (N·m/rad) and damping (N·m·s/rad) per joint, and the largest inertia seen
        self._kp = np.array([s.kp_nm_per_deg for s in specs], dtype=np.float64) * _DEG_PER_RAD
        self._kd = np.array([s.kd_nm_per_dps for s in specs], dtype=np.float64) * _DEG_PER_RAD
        self._inertia_kgm2 = np.zeros(n)
        self._inertia_seen = -1  # the tracking model's inertia evaluation the limit is from
        #: Per joint, the loop's peak gain ``Q`` (module doc; 1 where the tracking model gives no loop to take it from).
        self.resonance = np.ones(n)
        #: Per joint, the fastest measured speed that is no fault, joint deg/s (module doc; updated in place): what a
        #: test asks for.
        self.limit_dps = np.zeros(n)
        self._set_limit()
        self._speed = np.zeros(n)
        self._over = np.zeros(n, dtype=bool)

    @property
    def margin(self) -> FloatArray:
        """Per joint, :attr:`limit_dps` as a multiple of the velocity limit."""
        return self.limit_dps / self.velocity_limit_dps

    def _set_limit(self) -> None:
        """``v (1 + ε Q) + steps`` into :attr:`limit_dps`."""
        limit = self.limit_dps
        np.multiply(self.resonance, OVERSHOOT_SHARE, out=limit)
        limit += 1.0
        limit *= self.velocity_limit_dps
        limit += self._steps_dps

    def _follow_inertia(self) -> None:
        """Torque mode: the PD's peak gain at the largest inertia the tracking model has had (from its evaluations at
        the reference's poses), where it has one."""
        tracking = self.controller.tracking
        inertia = tracking.inertia_kgm2
        if inertia is None or tracking.inertia_evaluations == self._inertia_seen:
            return
        self._inertia_seen = tracking.inertia_evaluations
        np.maximum(self._inertia_kgm2, np.diagonal(inertia), out=self._inertia_kgm2)
        stiff = self._kp * self._inertia_kgm2
        tuned = stiff > 0.0
        zeta = np.divide(self._kd, 2.0 * np.sqrt(stiff), out=np.full_like(stiff, np.inf), where=tuned)
        np.copyto(self.resonance, resonance_gain(zeta), where=tuned)
        self._set_limit()

    def check(self, qd_dps: FloatArray) -> MotionFault | None:
        """The measured speeds ``qd_dps`` (joint deg/s, joint order) against the limits: the ``overspeed`` fault
        naming the joint furthest beyond its limit (every joint beyond in the detail), or None."""
        if self._host_loop:
            self._follow_inertia()  # (an int compared per cycle: the work is once per evaluation of the inertia)
        speed, over = self._speed, self._over
        np.abs(qd_dps, out=speed)
        np.greater(speed, self.limit_dps, out=over)
        if not over.any():
            return None
        speed /= self.limit_dps
        worst = int(speed.argmax())
        beyond = np.flatnonzero(over)
        detail = "measured speed beyond the velocity limit × its margin: " + ", ".join(
            f"{self.names[i]} {qd_dps[i]:+.1f} deg/s (limit {self.limit_dps[i]:.1f}, velocity limit "
            f"{self.velocity_limit_dps[i]:g})"
            for i in beyond
        )
        return MotionFault(
            FaultKind.OVERSPEED,
            joint=self.names[worst],
            value=float(qd_dps[worst]),
            threshold=float(self.limit_dps[worst]),
            time_s=self.controller.clock.now(),
            detail=detail,
            joints=tuple(self.names[i] for i in beyond),
        )
