"""What the live view and the replay share: where the page listens, its server, its panels (the two figures, the
state, the joint table, the plots) and their rolling history."""

from __future__ import annotations

import contextlib
import html
import io
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from motion.config import ArmConfig
from motion.errors import MotionError
from motion.view.figure import ArmGeometry, FloatArray, frame_the_arm, new_figure

# the view's one logger, whichever of its modules logs
logger = logging.getLogger("motion.view")

#: Most snapshots read per second (and page updates sent).
VIEW_RATE_HZ = 30.0
#: Time span of the rolling plots, s.
HISTORY_S = 10.0
#: The default port.
DEFAULT_PORT = 8080
#: The address the server binds by default (this computer only).
DEFAULT_HOST = "127.0.0.1"
#: The TCP ports (0: any free one).
PORTS = range(1 << 16)

_MEASURED_RGB = (70, 110, 190)
_REFERENCE_RGB = (240, 160, 40)
_GHOST_OPACITY = 0.3
_PLOTS = ("position", "following error", "torque current", "collision signal")
_PLOT_SERIES = (
    ("reference", "expected", "measured"),
    ("expected − measured",),
    ("iq",),
    ("signal", "threshold in force"),
)
_SERIES_COLORS = ("#f0a028", "#999999", "#466ebe")
_FAULTED_STATES = frozenset({"holding", "halt_pending", "halting", "halted", "complying", "bus_lost"})


@dataclass(frozen=True, slots=True)
class ViewOptions:
    """Where the live page listens.

    Attributes:
        host: the address to bind (default :data:`DEFAULT_HOST`, this computer only; another one is warned about).
        port: the port (0: any free one; ``LiveView.url`` tells which).
    """

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT

    def __post_init__(self) -> None:
        if self.port not in PORTS:
            raise ValueError(f"view port {self.port} is outside {PORTS[0]}..{PORTS[-1]}")


def _viser() -> Any:
    try:
        import viser  # noqa: PLC0415 - the optional ``view`` extra, loaded when a page opens
    except ImportError:
        raise MotionError("the view needs viser and yourdfpy: pip install 'rmd-motion[view]'") from None
    return viser


def host_warning(host: str) -> str | None:
    """The warning for a server that listens beyond this computer (None for a loopback address)."""
    if host in {"127.0.0.1", "localhost", "::1"}:
        return None
    return (
        f"the view listens on {host}: anyone who can reach its port sees the arm and can press STOP "
        "(which halts every axis)"
    )


#: The page's per-joint series.
_HISTORY_KEYS = ("q", "q_ref", "q_exp", "iq", "signal", "limit")


class History:
    """Rolling per-joint series for the plots (the page's own arrays)."""

    def __init__(self, joints: int, length: int) -> None:
        self.t = np.full(length, np.nan)
        self.rows = {key: np.full((length, joints), np.nan) for key in _HISTORY_KEYS}
        self._n = 0

    def push(self, t_s: float, values: dict[str, FloatArray]) -> None:
        """Append one sample (the oldest goes)."""
        for array in (self.t, *self.rows.values()):
            array[:-1] = array[1:]
        self.t[-1] = t_s
        for key, row in values.items():
            self.rows[key][-1] = row
        self._n = min(self._n + 1, len(self.t))

    def fill(self, t_s: FloatArray, values: dict[str, FloatArray]) -> None:
        """Replace the whole history (replay: the window before the slider)."""
        n = min(len(t_s), len(self.t))
        self.t[:] = np.nan
        self.t[len(self.t) - n :] = t_s[len(t_s) - n :]
        for key, array in self.rows.items():
            array[:] = np.nan
            array[len(array) - n :] = values[key][len(t_s) - n :]
        self._n = n

    def window(self) -> tuple[FloatArray, dict[str, FloatArray]]:
        """The filled part: times and per-joint rows."""
        n = self._n
        return self.t[len(self.t) - n :], {k: v[len(v) - n :] for k, v in self.rows.items()}


class Page:
    """The page's panels and the two figures, shared by the live view and the replay."""

    def __init__(self, server: Any, config: ArmConfig, geometry: ArmGeometry) -> None:
        viser = _viser()
        self.server = server
        self.names = [html.escape(name, quote=True) for name in config.joint_names]
        #: An arm on several buses: each joint's bus, a column of the table (none on one bus).
        self.buses = [html.escape(j.bus) for j in config.joints] if len(config.buses) > 1 else []
        server.gui.configure_theme(control_width="large", show_share_button=False)
        self.measured = new_figure(
            server, config=config, geometry=geometry, name="measured", rgb=_MEASURED_RGB, opacity=None
        )
        self.reference = new_figure(
            server, config=config, geometry=geometry, name="reference", rgb=_REFERENCE_RGB, opacity=_GHOST_OPACITY
        )
        frame_the_arm(server, geometry)
        self.state = server.gui.add_markdown("**state**: connecting")
        self.table = server.gui.add_markdown("")
        self.joint = server.gui.add_dropdown("joint", tuple(self.names), initial_value=self.names[0])
        self.plots = {}
        for title, labels in zip(_PLOTS, _PLOT_SERIES, strict=True):
            lines = tuple(
                viser.uplot.Series(label=label, stroke=color, width=2, points={"show": False})
                for label, color in zip(labels, _SERIES_COLORS, strict=False)
            )
            series = (viser.uplot.Series(label="t (s)"), *lines)
            self.plots[title] = server.gui.add_uplot(
                data=tuple(np.zeros(2) for _ in series),
                series=series,
                title=title,
                aspect=2.0,
                scales={"x": {"time": False}},
                legend=viser.uplot.Legend(show=True),
            )

    def show_state(self, state: str, fault: str | None, t_s: float) -> None:
        """The state line: READY / MOVING / FAULTED (with the fault in words)."""
        label = "FAULTED" if fault is not None or state in _FAULTED_STATES else state.upper()
        text = f"**{label}** ({state}) at t = {t_s:.2f} s"
        if fault is not None:
            text += f"\n\n**fault**: {html.escape(fault)}"
        self.state.content = text

    def show_joints(self, q: FloatArray, q_ref: FloatArray, q_exp: FloatArray, iq: FloatArray) -> None:
        """The per-joint table, and both figures."""
        bus, rule = ("| bus ", "|---") if self.buses else ("", "")
        rows = [f"| joint {bus}| measured ° | reference ° | error ° | iq A |", f"|---{rule}|---:|---:|---:|---:|"]
        for i, name in enumerate(self.names):
            on = f"| {self.buses[i]} " if self.buses else ""
            rows.append(
                f"| {name} {on}| <span data-joint='{name}'>{q[i]:.2f}</span> | {q_ref[i]:.2f} | "
                f"{q_exp[i] - q[i]:.3f} | {iq[i]:.2f} |"
            )
        self.table.content = "\n".join(rows)
        self.measured.pose(q)
        self.reference.pose(q_ref)

    def show_plots(self, history: History) -> None:
        """The chosen joint's rolling plots."""
        t, rows = history.window()
        if len(t) < 2:
            return
        j = self.names.index(self.joint.value)
        q, q_ref, q_exp, iq, signal, limit = (rows[k][:, j] for k in _HISTORY_KEYS)
        threshold = np.where(np.isfinite(limit), limit, np.nan)  # (inf: a joint not watched)
        self.plots["position"].data = (t, q_ref, q_exp, q)
        self.plots["following error"].data = (t, q_exp - q)
        self.plots["torque current"].data = (t, iq)
        self.plots["collision signal"].data = (t, signal, threshold)


def start_server(host: str, port: int) -> Any:
    """viser's server on ``host``:``port`` (a host beyond this computer is warned about in the log)."""
    viser = _viser()
    warning = host_warning(host)
    if warning is not None:
        logger.warning(warning)
    # viser 1.1 prints a banner to stdout whatever ``verbose`` says: a command's stdout is its output (JSON with
    # --json), so the banner goes to the log instead
    with contextlib.redirect_stdout(io.StringIO()) as banner:
        server = viser.ViserServer(host=host, port=port, verbose=False)
    logger.debug("viser: %s", banner.getvalue())
    return server


def stop_server(server: Any) -> None:
    """Stop viser's server."""
    with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
        server.stop()
