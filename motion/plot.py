"""Plots of a telemetry log (:mod:`motion.telemetry`): one PNG with a row per joint and a row of loop timing.

Per joint, five panels on a shared time axis: position (reference, measured and expected: where the joint should be
under its control loop), velocity (reference and measured), torque current (measured, with the cycles where the
current limit clipped the command marked), the following error (expected minus measured,
:meth:`~motion.telemetry.TelemetryLog.following_error_deg`, with the configured limit) and the collision observer
(the signal its threshold applies to, the residual itself, and the joint's threshold; empty where no observer ran).
The last
row shows every cycle's wake-up jitter and busy time against the period. Faults are vertical lines on every panel
(the ``close`` halt at the end of a run is not a fault and is left out).

The figure is drawn on matplotlib's Agg canvas directly: no pyplot, no global backend switch, no display needed.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from motion.telemetry import TelemetryLog, load_log

#: Panel columns of a joint row: (title, unit).
PANELS = (
    ("position", "deg"),
    ("velocity", "deg/s"),
    ("torque current", "A"),
    ("following error", "deg"),
    ("collision observer", "N·m"),
)
_REFERENCE: dict[str, Any] = {"color": "0.45", "linestyle": "--", "linewidth": 1.0, "label": "reference"}
_MEASURED: dict[str, Any] = {"color": "tab:blue", "linewidth": 1.0, "label": "measured"}
_EXPECTED: dict[str, Any] = {"color": "tab:orange", "linewidth": 0.8, "linestyle": ":", "label": "expected"}
_FAULT: dict[str, Any] = {"color": "tab:red", "linewidth": 1.0, "alpha": 0.8}
_DPI = 90


def figure(log: TelemetryLog) -> Figure:
    """Draw ``log`` (see the module docstring); the figure is not attached to any window or pyplot state.

    Data lines come first in each panel, in this order: position ``[reference, measured, expected]``, velocity
    ``[reference, measured]``, current ``[measured]``, following error ``[error]``, collision ``[signal, residual]``,
    timing ``[jitter, busy]`` (µs); limit (and threshold) and fault lines follow them.
    """
    names = log.joint_names
    rows = len(names) + 1
    height_in = 2.0 * rows + 0.9
    fig = Figure(figsize=(16.0, height_in), dpi=_DPI)
    FigureCanvasAgg(fig)
    # fixed margins, in inches, rather than a constrained layout, which measures every panel's ticks and labels to
    # place them (most of the drawing time of a six-joint figure: it is drawn at the end of every demo run)
    grid = fig.add_gridspec(
        rows,
        len(PANELS),
        left=0.75 / 16.0,
        right=1.0 - 0.15 / 16.0,
        top=1.0 - 0.75 / height_in,
        bottom=0.55 / height_in,
        hspace=0.35,
        wspace=0.22,
    )
    t = log["t_s"]
    t_ref = t + log.period_s
    error = log.following_error_deg()
    faults = [(float(when), str(kind)) for when, kind in zip(log["fault_t_s"], log["fault_kind"], strict=True)]
    faults = [(when, kind) for when, kind in faults if kind != "close"]
    limit = log.meta.get("following_error_limit_deg")
    thresholds = log.meta.get("collision_threshold_nm") or [None] * len(names)
    first: Axes | None = None
    for j, name in enumerate(names):
        axes = [fig.add_subplot(grid[j, c], sharex=first) for c in range(len(PANELS))]
        first = first or axes[0]
        position, velocity, current, following, collision = axes
        position.plot(t_ref, log["q_ref_deg"][:, j], **_REFERENCE)
        position.plot(t, log["q_deg"][:, j], **_MEASURED)
        position.plot(t, log["q_exp_deg"][:, j], **_EXPECTED)
        velocity.plot(t_ref, log["qd_ref_dps"][:, j], **_REFERENCE)
        velocity.plot(t, log["qd_dps"][:, j], **_MEASURED)
        current.plot(t, log["iq_a"][:, j], **_MEASURED)
        clipped = log["limited"][:, j]
        if clipped.any():
            current.scatter(t[clipped], log["iq_a"][clipped, j], s=6, color="tab:orange", label="current limited")
        following.plot(t, error[:, j], color="tab:purple", linewidth=1.0, label="expected - measured")
        if limit is not None:
            for sign in (1.0, -1.0):
                following.axhline(sign * float(limit), color="0.6", linestyle=":", linewidth=1.0)
        collision.plot(t, log["collision_signal_nm"][:, j], color="tab:green", linewidth=1.0, label="signal")
        collision.plot(t, log["residual_nm"][:, j], color="0.6", linewidth=0.8, label="residual")
        in_force = log["collision_limit_nm"][:, j]
        if np.isfinite(in_force).any():  # the threshold in force, cycle by cycle (version 5 logs)
            for sign in (1.0, -1.0):
                label = "threshold in force" if sign > 0 else None
                collision.plot(t, sign * in_force, color="tab:red", linestyle=":", linewidth=1.0, label=label)
        elif thresholds[j] is not None:
            for sign in (1.0, -1.0):
                collision.axhline(sign * float(thresholds[j]), color="tab:red", linestyle=":", linewidth=1.0)
        position.set_ylabel(f"{name}\n{PANELS[0][1]}")
        for c, panel in enumerate(axes):
            if j == 0:
                panel.set_title(f"{PANELS[c][0]} ({PANELS[c][1]})", fontsize=10)
            panel.grid(True, alpha=0.3)
            panel.tick_params(labelsize=8, labelbottom=j == len(names) - 1)
            _mark_faults(panel, faults)
        if j == 0:
            position.legend(fontsize=7, loc="upper right")
            collision.legend(fontsize=7, loc="upper right")
    timing = fig.add_subplot(grid[rows - 1, :], sharex=first)
    _draw_timing(timing, log, faults)
    fig.suptitle(_title(log), fontsize=12)
    return fig


def _draw_timing(axes: Axes, log: TelemetryLog, faults: list[tuple[float, str]]) -> None:
    t = log["t_s"]
    axes.plot(t, log["jitter_s"] * 1e6, color="tab:blue", linewidth=0.8, label="wake-up jitter")
    axes.plot(t, log["busy_s"] * 1e6, color="tab:green", linewidth=0.8, alpha=0.7, label="busy (wake-up to end)")
    axes.axhline(log.period_s * 1e6, color="tab:red", linestyle="--", linewidth=1.0, label="period")
    axes.set_yscale("symlog", linthresh=10.0)
    axes.set_ylim(bottom=0.0)
    axes.set_ylabel("cycle timing\nµs")
    axes.set_xlabel("time since start of recording, s")
    axes.grid(True, alpha=0.3)
    axes.tick_params(labelsize=8)
    axes.legend(fontsize=7, loc="upper right", ncols=3)
    for when, kind in faults:
        axes.axvline(when, **_FAULT)
        axes.annotate(kind, (when, 1.0), xycoords=("data", "axes fraction"), fontsize=7, color="tab:red")
    stats = log.meta.get("loop")
    if stats:
        axes.set_title(
            f"{stats['cycles']} cycles at {stats['achieved_rate_hz']:.1f} Hz (target {stats['rate_hz']:g} Hz); jitter "
            f"p50 {stats['jitter_p50_s'] * 1e6:.0f} µs, p99 {stats['jitter_p99_s'] * 1e6:.0f} µs, max "
            f"{stats['jitter_max_s'] * 1e6:.0f} µs; busy p99 {stats['busy_p99_s'] * 1e6:.0f} µs; "
            f"{stats['overruns']} overruns",
            fontsize=9,
        )
    if not len(t):
        axes.text(0.5, 0.5, "no cycles recorded", transform=axes.transAxes, ha="center")


def _mark_faults(axes: Axes, faults: list[tuple[float, str]]) -> None:
    for when, _ in faults:
        axes.axvline(when, **_FAULT)


def _title(log: TelemetryLog) -> str:
    meta = log.meta
    emulated = ", emulated" if meta.get("emulated") else ""
    error = log.following_error_deg()[log.active_rows()]
    worst = f", max following error {np.nanmax(np.abs(error)):.3f} deg" if error.size else ""
    return (
        f"{meta.get('config', '?')}: {meta['mode']} mode over {meta.get('transport', '?')}"
        f"{' (' + meta['protocol'] + ' drives)' if meta.get('protocol', 'v2') != 'v2' else ''}{emulated}, "
        f"{log.cycles} cycles in {log.duration_s:.2f} s{worst}"
    )


def plot_log(log: str | os.PathLike[str] | TelemetryLog, out_png: str | os.PathLike[str]) -> None:
    """Draw a telemetry log into a PNG file.

    Args:
        log: a recording (``.mcap`` written by :class:`~motion.telemetry.TelemetrySession`, or an exported ``.npz``)
            or a loaded log.
        out_png: the image to write (PNG whatever the suffix).

    Raises:
        OSError: the log cannot be read or the image cannot be written.
        ValueError: the file is not a telemetry log.
    """
    loaded = log if isinstance(log, TelemetryLog) else load_log(log)
    figure(loaded).savefig(out_png, format="png", dpi=_DPI)
