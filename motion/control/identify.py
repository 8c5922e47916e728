"""Identification of the drives' position loops: each joint moved alone out and back at full speed, and the
expected-tracking model's loop (:mod:`motion.control.tracking`) fitted to what was measured.

The moves themselves are the caller's (:func:`motion.compose.identify_position_loops` passes the supervisor's, so a
fault during identification halts the arm as in any other move): safety sits above control, and what is identified
here is only what the cycles sent and measured.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from motion.config.schema import ArmConfig
from motion.control.tracking import MoveRecord, PositionLoopFit, fit_position_loop
from motion.errors import MotionError
from motion.transmission import FloatArray
from motion.transport.base import Reply

if TYPE_CHECKING:
    from motion.control.controller import Controller

#: An identification move goes this far from where the joint is, deg (at most a quarter of the joint's range).
IDENTIFY_MOVE_DEG = 60.0


def identify_position_loops(
    controller: Controller, config: ArmConfig, move_to: Callable[[FloatArray], None]
) -> dict[str, PositionLoopFit]:
    """Move each joint alone out and back with ``move_to`` (:data:`IDENTIFY_MOVE_DEG`, toward the side with more
    room) and fit its position loop to what was measured (:func:`~motion.control.tracking.fit_position_loop`); the
    controller's tracking model uses the result from then on.

    Args:
        controller: the arm's controller, its loop running: every cycle of a move is recorded through its
            ``cycle_hooks``.
        config: the arm (its control mode, its joints and their limits).
        move_to: moves the arm to these joint angles (deg, configuration order) at full speed and returns when the
            move has ended; what it raises (the supervisor's ``MotionFault``: a fault halted the arm) passes through,
            the recording taken off the controller's hooks.

    Raises:
        MotionError: the arm is not in position mode.
    """
    if not config.control.mode.traits.drive_position_loop:
        raise MotionError("identification moves need position mode (the drive's own loop is what is identified)")
    tracking = controller.tracking
    ratios = tracking.gear_ratio
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray, FloatArray]] = []

    def record(c: Controller, start_s: float, _replies: list[Reply]) -> None:
        caps = c.setpoints.max_speed_dps / ratios
        rows.append((start_s, c.reference.position.copy(), caps, c.axes.q_deg.copy(), c.axes.qd_dps.copy()))

    fits: dict[str, PositionLoopFit] = {}
    loops = list(tracking.position_loops())
    for j, joint in enumerate(config.joints):
        home = controller.reference.position.copy()
        room_up, room_down = joint.position_max_deg - home[j], home[j] - joint.position_min_deg
        step = min(IDENTIFY_MOVE_DEG, 0.25 * (joint.position_max_deg - joint.position_min_deg))
        out = home.copy()
        out[j] += step if room_up >= room_down else -step
        rows.clear()
        controller.cycle_hooks.append(record)
        try:
            for target in (out, home):
                move_to(target)
        finally:
            controller.cycle_hooks.remove(record)
        t, target_deg, cap, q, qd = (np.array([row[i] for row in rows]) for i in range(5))
        move = MoveRecord(t, target_deg[:, j], cap[:, j], q[:, j], qd[:, j])
        fits[joint.name] = fit = fit_position_loop(move, loops[j])
        loops[j] = fit.loop
    tracking.set_position_loops(loops)
    return fits
