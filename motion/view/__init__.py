"""See the arm: a live 3D view and plots in the browser, and replay of recorded runs (viser).

:class:`LiveView` shows an arm that a program of the same process drives (``Arm(..., view=True)``, ``--view`` on
``move``, ``run`` and ``demo``, ``rmd-motion view --config FILE``): the measured pose, the reference pose as a
translucent ghost, the arm's state and its last fault in words, a table of every joint, and per joint (chosen in a
list) rolling plots of position against reference and expected position, following error, torque current and the
collision signal against its threshold. Its one control is STOP, which E-stops the arm as Ctrl-C does (every axis
halted); the page sends no motion command.

:class:`Replay` shows a recorded telemetry log (``rmd-motion view RUN.mcap``) with the same panels, a time slider and
play/pause.

The view never slows the control loop: the page (viser's server, the figures, the plots, the view's own Pinocchio
model) runs in a process of its own, scheduled as SCHED_IDLE, and the loop hands it the published snapshot
(:class:`~motion.control.snapshot.CycleSnapshot`) itself, at most :data:`VIEW_RATE_HZ` times a second, as one datagram
on a non-blocking socket (:meth:`LiveView.publish`): no other thread of the arm's process runs while the arm runs.
(The page in a thread of the arm's process took the interpreter from the loop long enough to miss replies at 370 Hz;
a thread that only fed it the snapshots 30 times a second still raised the loop's jitter p99 from 1 µs to about
100 µs: held the interpreter when the CPU was taken from it, it made the loop wait. ``bench/view_jitter.py``.)

The arm is drawn from its Pinocchio model: per joint a sphere at its origin and a cylinder to each child joint (at a
tip, a stub toward the link's centre of mass). A URDF with ``<visual>`` elements is drawn from its meshes instead
(yourdfpy, through viser's URDF helper).

The server binds 127.0.0.1 unless told otherwise; anyone who can reach its port sees the arm and can press STOP.
viser and yourdfpy are the ``view`` extra: ``pip install 'rmd-motion[view]'``.

The modules: :mod:`~motion.view.figure` (the arm drawn), :mod:`~motion.view.page` (the server, the panels and
their history, shared), :mod:`~motion.view.live` (:class:`LiveView` and the page's process) and
:mod:`~motion.view.replay` (:class:`Replay`).
"""

from __future__ import annotations

from motion.view.figure import ArmGeometry
from motion.view.live import START_TIMEOUT_S, LiveView
from motion.view.page import DEFAULT_HOST, DEFAULT_PORT, HISTORY_S, PORTS, VIEW_RATE_HZ, ViewOptions, host_warning
from motion.view.replay import Replay

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "HISTORY_S",
    "PORTS",
    "START_TIMEOUT_S",
    "VIEW_RATE_HZ",
    "ArmGeometry",
    "LiveView",
    "Replay",
    "ViewOptions",
    "host_warning",
]
