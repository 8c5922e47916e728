"""A recorded run on the page: :class:`Replay` (see :mod:`motion.view`)."""

from __future__ import annotations

import math
import threading

import numpy as np

from motion.config import ArmConfig
from motion.errors import MotionError
from motion.telemetry import TelemetryLog
from motion.view.figure import ArmGeometry, FloatArray
from motion.view.page import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    HISTORY_S,
    VIEW_RATE_HZ,
    History,
    Page,
    start_server,
    stop_server,
)


def _limit_in_force(log: TelemetryLog) -> FloatArray:
    """The collision threshold in force per cycle and joint; a log from before it was recorded (version < 5) gives
    the configured thresholds instead (NaN where none)."""
    limit: FloatArray = log["collision_limit_nm"]
    if np.isnan(limit).all():
        configured = log.meta.get("collision_threshold_nm") or [None] * limit.shape[1]
        limit = np.broadcast_to(
            np.array([math.nan if t is None else t for t in configured], dtype=np.float64), limit.shape
        )
    return limit


class Replay:
    """A recorded run on the page: a time slider, play/pause, the same panels (see the module docstring).

    Args:
        log: the telemetry log.
        config: the configuration it was recorded with.
        geometry: its shape (:func:`motion.compose.arm_figure`).
        host, port: as :class:`LiveView`.
    """

    def __init__(
        self,
        log: TelemetryLog,
        config: ArmConfig,
        geometry: ArmGeometry,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
    ) -> None:
        names = log.joint_names
        if list(config.joint_names) != names:
            raise MotionError(f"the log's joints {names} are not those of {config.source} ({list(config.joint_names)})")
        if log.cycles == 0:
            raise MotionError("the log holds no cycle to replay")
        self.log = log
        self.server = start_server(host, port)
        self._page = Page(self.server, config, geometry)
        t = log["t_s"]
        self._t = t
        self._values = {
            "q": log["q_deg"],
            "q_ref": log["q_ref_deg"],
            "q_exp": log["q_exp_deg"],
            "iq": log["iq_a"],
            "signal": log["collision_signal_nm"],
            "limit": _limit_in_force(log),
        }
        faults = log["fault_t_s"]
        self._fault_t = faults
        self._fault_text = [str(text) for text in log["fault_text"]]
        gui = self.server.gui
        self.slider = gui.add_slider(
            "t (s)", min=float(t[0]), max=float(t[-1]), step=log.period_s, initial_value=float(t[0])
        )
        self.play = gui.add_button("play / pause")
        self._history = History(len(names), int(HISTORY_S / log.period_s))
        self._playing = threading.Event()
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self.slider.on_update(lambda _event: self.show(self.slider.value))
        self.play.on_click(lambda _event: self._toggle())
        self._thread = threading.Thread(target=self._run, name="rmd-motion replay", daemon=True)
        self._thread.start()
        self.show(float(t[0]))

    @property
    def url(self) -> str:
        """Where the page is."""
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _toggle(self) -> None:
        if self._playing.is_set():
            self._playing.clear()
        else:
            if self.slider.value >= self._t[-1]:
                self.slider.value = float(self._t[0])
            self._playing.set()

    def _run(self) -> None:
        period = 1.0 / VIEW_RATE_HZ
        while not self._closing.wait(period):
            if not self._playing.is_set():
                continue
            value = min(float(self.slider.value) + period, float(self._t[-1]))
            self.slider.value = value  # its update shows the row
            if value >= self._t[-1]:
                self._playing.clear()

    def show(self, t_s: float) -> None:
        """Show the recorded cycle at ``t_s`` (the last one at or before it) and the window before it."""
        with self._lock:
            row = max(int(np.searchsorted(self._t, t_s, side="right")) - 1, 0)
            values = self._values
            self._history.fill(self._t[: row + 1], {k: v[: row + 1] for k, v in values.items()})
            page = self._page
            fault = None
            for when, text in zip(self._fault_t, self._fault_text, strict=True):
                if when <= self._t[row]:
                    fault = text
                    break
            state = "halted" if fault is not None else self._motion_state(row)
            with self.server.atomic():
                page.show_state(state, fault, float(self._t[row]))
                page.show_joints(*(values[k][row] for k in ("q", "q_ref", "q_exp", "iq")))
                page.show_plots(self._history)

    def _motion_state(self, row: int) -> str:
        q_ref = self._values["q_ref"]
        before = q_ref[max(row - 1, 0)]
        return "moving" if np.nanmax(np.abs(q_ref[row] - before), initial=0.0) > 1e-9 else "ready"

    def close(self) -> None:
        """Stop the player and the server."""
        self._closing.set()
        self._playing.clear()
        if self._thread.is_alive():
            self._thread.join(2.0)
        stop_server(self.server)
