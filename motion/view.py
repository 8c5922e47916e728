"""See the arm: a live 3D view and plots in the browser, and replay of recorded runs (viser).

:class:`LiveView` shows an arm that a program of the same process drives (``Arm(..., view=True)``, ``--view`` on
``move``, ``run`` and ``demo``, ``rmd-motion view --config FILE``): the measured pose, the reference pose as a
translucent ghost, the arm's state and its last fault in words, a table of every joint, and per joint (chosen in a
list) rolling plots of position against reference and expected position, following error, torque current and the
collision signal against its threshold. Its one control is STOP, which E-stops the arm as Ctrl-C does (every axis
halted); the page sends no motion command.

:class:`Replay` shows a recorded telemetry log (``rmd-motion view RUN.npz``) with the same panels, a time slider and
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
"""

from __future__ import annotations

import contextlib
import html
import io
import logging
import math
import select
import socket
import struct
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from motion.config import ArmConfig
from motion.control.snapshot import JOINT_ROWS, CycleSnapshot
from motion.errors import MotionError
from motion.telemetry import TelemetryLog

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
#: The plots are sent every this many updates (10 Hz): a browser rendering in software keeps up.
_PLOT_EVERY = 3
#: The snapshot rows the page shows (:data:`JOINT_ROWS` index), by their names in the page's history.
_LIVE_ROWS = {
    key: JOINT_ROWS.index(row)
    for key, row in (
        ("q", "position_deg"),
        ("q_ref", "reference_deg"),
        ("iq", "iq_a"),
        ("q_exp", "expected_deg"),
        ("signal", "collision_signal_nm"),
        ("limit", "collision_limit_nm"),
    )
}
#: The largest snapshot datagram read, bytes (a few hundred for six joints).
_FEED_MAX = 65536
#: How long the page's process may take to start (it imports viser and builds the arm's model), s.
START_TIMEOUT_S = 60.0
_PLOTS = ("position", "following error", "torque current", "collision signal")
_PLOT_SERIES = (
    ("reference", "expected", "measured"),
    ("expected − measured",),
    ("iq",),
    ("signal", "threshold in force"),
)
_SERIES_COLORS = ("#f0a028", "#999999", "#466ebe")
_FAULTED_STATES = frozenset({"holding", "halting", "halted", "complying", "bus_lost"})

FloatArray = NDArray[np.float64]


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


# ------------------------------------------------------------------------------------------------ the figure


def _z_to(direction: FloatArray) -> FloatArray:
    """The rotation (w, x, y, z) that turns +z into ``direction`` (a unit vector)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, direction)
    s, c = float(np.linalg.norm(axis)), float(np.dot(z, direction))
    if s < 1e-9:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    angle = math.atan2(s, c)
    return np.array([math.cos(angle / 2), *(axis / s * math.sin(angle / 2))])


def _has_visuals(config: ArmConfig) -> bool:
    urdf = config.model.urdf
    if urdf is None:
        return False
    try:
        return ET.parse(urdf).getroot().find(".//visual") is not None
    except (OSError, ET.ParseError):
        return False


class ArmGeometry(Protocol):
    """The arm's shape for drawing (:class:`kinematics.figure.ArmFigure`, built by :func:`motion.compose.arm_figure`;
    this module never builds the model itself)."""

    links: tuple[tuple[FloatArray, ...], ...]
    reach: float
    up: FloatArray

    def placements(self, q_deg: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Every joint's origin (J×3) and orientation (J×4, w x y z) at ``q_deg``."""
        ...


class _StickFigure:
    """The arm from its model: a sphere per joint, a cylinder per link segment (see the module docstring)."""

    def __init__(
        self, server: Any, geometry: ArmGeometry, name: str, rgb: tuple[int, int, int], opacity: float | None
    ) -> None:
        self._geometry = geometry
        radius = min(max(0.04 * geometry.reach, 0.005), 0.05)
        looks = {"color": rgb, "opacity": opacity, "cast_shadow": False, "receive_shadow": False}
        self._nodes = []
        for j, ends in enumerate(geometry.links):
            node = server.scene.add_frame(f"/{name}/joint{j}", show_axes=False)
            self._nodes.append(node)
            server.scene.add_icosphere(f"/{name}/joint{j}/hub", radius=1.4 * radius, subdivisions=1, **looks)
            for k, end in enumerate(ends):
                length = float(np.linalg.norm(end))
                server.scene.add_cylinder(
                    f"/{name}/joint{j}/link{k}",
                    radius=radius,
                    height=length,
                    radial_segments=12,
                    wxyz=_z_to(end / length),
                    position=end / 2,
                    **looks,
                )

    def pose(self, q_deg: FloatArray) -> None:
        """Place the figure at the joint angles ``q_deg`` (configuration order, deg)."""
        if not np.isfinite(q_deg).all():
            return
        positions, quaternions = self._geometry.placements(q_deg)
        for node, position, wxyz in zip(self._nodes, positions, quaternions, strict=True):
            node.position = position
            node.wxyz = wxyz


class _UrdfFigure:
    """The arm from its URDF's visual meshes (yourdfpy, through viser's URDF helper)."""

    def __init__(self, server: Any, config: ArmConfig, name: str, rgb: tuple[int, int, int], opacity: float | None):
        from viser.extras import ViserUrdf  # noqa: PLC0415 - as viser

        assert config.model.urdf is not None
        red, green, blue = (c / 255 for c in rgb)
        color = None if opacity is None else (red, green, blue, opacity)
        self._urdf = ViserUrdf(server, Path(config.model.urdf), root_node_name=f"/{name}", mesh_color_override=color)
        actuated = list(self._urdf.get_actuated_joint_names())
        index = {joint: i for i, joint in enumerate(config.joint_names)}
        self._order = np.array([index[joint] for joint in actuated], dtype=np.intp)

    def pose(self, q_deg: FloatArray) -> None:
        """Place the figure at the joint angles ``q_deg`` (configuration order, deg)."""
        if np.isfinite(q_deg).all():
            self._urdf.update_cfg(np.radians(q_deg[self._order]))


def _frame_the_arm(server: Any, geometry: ArmGeometry) -> None:
    """Up against gravity, a floor grid and a camera that sees the whole arm (its reach at the zero pose)."""
    reach, up = 1.3 * geometry.reach, geometry.up
    server.scene.set_up_direction(tuple(up))
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    server.initial_camera.position = tuple(2.2 * reach * side + 1.2 * reach * up + 0.8 * reach * np.cross(side, up))
    server.initial_camera.look_at = tuple(0.3 * reach * up)
    plane = {0: "yz", 1: "xz", 2: "xy"}[int(np.argmax(np.abs(up)))]
    server.scene.add_grid("/grid", width=2 * reach, height=2 * reach, cell_size=reach / 10, plane=plane)


def _figure(
    server: Any,
    *,
    config: ArmConfig,
    geometry: ArmGeometry,
    name: str,
    rgb: tuple[int, int, int],
    opacity: float | None,
) -> Any:
    if _has_visuals(config):
        return _UrdfFigure(server, config, name, rgb, opacity)
    return _StickFigure(server, geometry, name, rgb, opacity)


# ------------------------------------------------------------------------------------------------ the panels


#: The page's per-joint series.
_HISTORY_KEYS = ("q", "q_ref", "q_exp", "iq", "signal", "limit")


class _History:
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


class _Page:
    """The page's panels and the two figures, shared by the live view and the replay."""

    def __init__(self, server: Any, config: ArmConfig, geometry: ArmGeometry) -> None:
        viser = _viser()
        self.server = server
        self.names = [html.escape(name, quote=True) for name in config.joint_names]
        server.gui.configure_theme(control_width="large", show_share_button=False)
        self.measured = _figure(
            server, config=config, geometry=geometry, name="measured", rgb=_MEASURED_RGB, opacity=None
        )
        self.reference = _figure(
            server, config=config, geometry=geometry, name="reference", rgb=_REFERENCE_RGB, opacity=_GHOST_OPACITY
        )
        _frame_the_arm(server, geometry)
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
        rows = ["| joint | measured ° | reference ° | error ° | iq A |", "|---|---:|---:|---:|---:|"]
        for i, name in enumerate(self.names):
            rows.append(
                f"| {name} | <span data-joint='{name}'>{q[i]:.2f}</span> | {q_ref[i]:.2f} | {q_exp[i] - q[i]:.3f} | "
                f"{iq[i]:.2f} |"
            )
        self.table.content = "\n".join(rows)
        self.measured.pose(q)
        self.reference.pose(q_ref)

    def show_plots(self, history: _History) -> None:
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


def _start_server(host: str, port: int) -> Any:
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


def _stop_server(server: Any) -> None:
    with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
        server.stop()


# ------------------------------------------------------------------------------------------------ live


class LiveView:
    """The live page of an arm driven in this process (see the module docstring).

    The page (viser, the figures, the plots) runs in a process of its own, so that none of its work shares the
    control loop's interpreter or competes with it for a CPU. The loop itself hands it the published snapshot
    (:meth:`publish`, its publisher's ``tap``): at most :data:`VIEW_RATE_HZ` times a second, and at once when
    the arm's state changes, one datagram of a few hundred bytes on a non-blocking socket (gathered from its parts:
    no copy of the joint rows), dropped (and counted) when the page is behind; no other thread of this process runs
    while the arm runs. A thread blocked on the page's messages takes back STOP and the number of browsers.

    Args:
        config: the arm's configuration.
        figure: builds its shape in the page's process (:func:`motion.compose.arm_figure`; picklable).
        stop: called in the receiving thread when STOP is pressed: must only *request* the halt, never wait for the
            loop (``supervisor.request_estop``).
        host: the address to bind (default this computer only).
        port: the port (0: any free one; :attr:`url` tells which).

    Raises:
        MotionError: viser is not installed, the port cannot be bound, or the page did not start in
            :data:`START_TIMEOUT_S`.
    """

    def __init__(
        self,
        config: ArmConfig,
        figure: Callable[[ArmConfig], ArmGeometry],
        stop: Callable[[], None],
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
    ) -> None:
        # A fresh interpreter started as a program (not multiprocessing's spawn, which runs the caller's main module
        # again: a script without a main guard would start a second arm): messages on a stream socket pair, the
        # snapshots on a datagram pair (each one whole or not at all).
        ours, theirs = socket.socketpair()
        self._feed, feed = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._feed.setblocking(False)
        with theirs, feed:
            fds = (theirs.fileno(), feed.fileno())
            self._process = subprocess.Popen(
                [sys.executable, "-c", _CHILD.format(fd=fds[0], feed=fds[1])],
                pass_fds=fds,
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # Ctrl-C goes to the arm's program, which closes the view
            )
        self._conn = Connection(ours.detach())
        self._conn.send(list(sys.path))
        self._conn.send({"config": config, "figure": figure, "host": host, "port": port})
        if not self._conn.poll(START_TIMEOUT_S):
            self._end_process()
            raise MotionError(f"the view did not start in {START_TIMEOUT_S:g} s")
        try:
            kind, text = self._conn.recv()
        except EOFError:
            kind, text = "error", f"its process ended with exit code {self._process.wait(5.0)}"
        if kind != "ready":
            self._end_process()
            raise MotionError(f"the view cannot start: {text}")
        #: Where the page is.
        self.url: str = text
        #: The page's process.
        self.pid = self._process.pid
        self._stop = stop
        #: Browsers that have the page open (as the page's process last said).
        self.clients = 0
        #: Snapshots sent to the page so far, and those dropped because it was behind.
        self.updates = 0
        self.dropped = 0
        #: Snapshots that could not be sent for another reason (the first one is logged).
        self.failures = 0
        self._period_s = 1.0 / VIEW_RATE_HZ
        self._next_s = -math.inf
        # the datagram's parts, kept between sends: the header packed in place, the texts encoded once per change
        self._header = bytearray(_FEED_HEADER.size)
        self._state = ""
        self._state_text = b""
        self._fault: object = None
        self._fault_text = b""
        self._closing = False
        self._thread = threading.Thread(target=self._receive, name="rmd-motion view", daemon=True)
        self._thread.start()

    def publish(self, snapshot: CycleSnapshot) -> None:
        """Called by the loop after each cycle: send the snapshot when :data:`VIEW_RATE_HZ` allows or the state
        changed; never waits."""
        state = snapshot.state
        if snapshot.time_s < self._next_s and state == self._state:
            return
        self._next_s = snapshot.time_s + self._period_s
        try:
            if state != self._state:
                self._state_text = state.encode()
                self._state = state
            fault = snapshot.fault
            if fault is not self._fault:
                self._fault_text = b"" if fault is None else str(fault).encode()
                self._fault = fault
            _FEED_HEADER.pack_into(self._header, 0, snapshot.time_s, len(self._state_text), len(self._fault_text))
            # one datagram gathered from its parts (the joint rows straight from the snapshot's array: no copy)
            self._feed.sendmsg((self._header, self._state_text, self._fault_text, snapshot.joints.data))
            self.updates += 1
        except OSError:  # full (the page is behind) or gone: a view misses a picture, the arm goes on
            self.dropped += 1
        except Exception:  # the view must never take the loop down: it says so (once) and goes on
            self.failures += 1
            if self.failures == 1:
                logger.exception("the view could not be sent a cycle (further failures are counted, not logged)")

    def wait_for_client(self, timeout_s: float) -> bool:
        """Wait until a browser has the page open (or ``timeout_s`` passed); returns whether one has."""
        end = time.monotonic() + timeout_s
        while not self.clients:
            if time.monotonic() >= end or not self._thread.is_alive():
                return False
            time.sleep(0.05)
        return True

    def _receive(self) -> None:
        try:
            while True:
                kind, value = self._conn.recv()  # blocked here, without the interpreter, nearly all the time
                if kind == "stop":
                    self._stop()
                elif kind == "clients":
                    self.clients = value
        except (EOFError, OSError) as exc:  # the page's process ended: the arm goes on without a view
            if not self._closing:
                logger.error("the view's process ended: %s: %s", type(exc).__name__, exc)

    def close(self) -> None:
        """End the page's process; safe to call twice."""
        if self._closing:
            return
        self._closing = True
        with contextlib.suppress(OSError):
            self._conn.send(None)
        self._end_process()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        self._conn.close()
        self._feed.close()

    def _end_process(self) -> None:
        try:
            self._process.wait(5.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(5.0)


#: A snapshot on the feed: its time (s), the lengths of the state's and the fault's text; then those texts, then
#: the snapshot's joint rows (float64, :data:`JOINT_ROWS` by joint).
_FEED_HEADER = struct.Struct("<dHH")

#: The page's process: scheduled as SCHED_IDLE before any of its threads starts (they inherit it), so that it runs
#: only on CPU time nothing else wants: the loop, the bus I/O and the rest of the host always go first (where the
#: host is saturated the page stalls, not the arm); then it takes the arm's import path, then the arguments of
#: :func:`_serve_live`, from the socket.
_CHILD = (
    "import os, sys; from multiprocessing.connection import Connection; "
    "os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0)) if hasattr(os, 'SCHED_IDLE') else os.nice(19); "
    "c = Connection({fd}); sys.path[:0] = c.recv(); "
    "import socket; from motion.view import _serve_live; "
    "_serve_live(c, socket.socket(fileno={feed}), **c.recv())"
)


def _serve_live(
    conn: Connection,
    feed: socket.socket,
    *,
    config: ArmConfig,
    figure: Callable[[ArmConfig], ArmGeometry],
    host: str,
    port: int,
) -> None:
    """The page's process: serve the page, show the snapshots the loop sends, send back STOP and the number of
    browsers; end when the arm's process says so (None) or goes away."""
    logging.basicConfig(level=logging.WARNING, format="rmd-motion view: %(message)s")
    sending = threading.Lock()

    def send(message: tuple[str, Any]) -> None:
        with sending, contextlib.suppress(OSError):
            conn.send(message)

    try:
        server = _start_server(host, port)
        page = _Page(server, config, figure(config))
    except Exception as exc:  # the arm's process raises it as a MotionError
        send(("error", f"{type(exc).__name__}: {exc}"))
        return
    button = server.gui.add_button("STOP", color="red")
    button.on_click(lambda _event: send(("stop", None)))
    history = _History(len(config.joints), int(HISTORY_S * VIEW_RATE_HZ))
    shape = (len(JOINT_ROWS), len(config.joints))
    feed.setblocking(False)
    send(("ready", f"http://{server.get_host()}:{server.get_port()}"))
    clients, shown, failures = 0, 0, 0
    try:
        while not conn.poll():
            latest = None
            if select.select([feed], [], [], 1.0 / VIEW_RATE_HZ)[0]:
                with contextlib.suppress(BlockingIOError):  # behind: every waiting one into the plots, the last shown
                    while True:
                        latest = _unpack(feed.recv(_FEED_MAX), shape)
                        history.push(latest[0], latest[3])
            if latest is not None:
                try:
                    _show_live(server, page, history, latest, plots=shown % _PLOT_EVERY == 0)
                except Exception:  # a picture the page could not show: it says so (once) and goes on
                    failures += 1
                    if failures == 1:
                        logger.exception("the view could not show a cycle (further failures are counted, not logged)")
                shown += 1
            now = len(server.get_clients())
            if now != clients:
                clients = now
                send(("clients", clients))
        conn.recv()  # None: the arm's process closes the view (or EOFError: it went away)
    except (EOFError, OSError):  # the arm's process ended
        pass
    finally:
        _stop_server(server)


def _unpack(message: bytes, shape: tuple[int, int]) -> tuple[float, str, str | None, dict[str, FloatArray]]:
    """A snapshot from the feed (see :data:`_FEED_HEADER`): time, state, fault and the rows the page shows."""
    time_s, n_state, n_fault = _FEED_HEADER.unpack_from(message)
    at = _FEED_HEADER.size
    state = message[at : at + n_state].decode()
    fault = message[at + n_state : at + n_state + n_fault].decode() or None
    joints = np.frombuffer(message, np.float64, offset=at + n_state + n_fault).reshape(shape)
    rows = {key: joints[index] for key, index in _LIVE_ROWS.items()}
    return time_s, state, fault, rows


def _show_live(
    server: Any,
    page: _Page,
    history: _History,
    snapshot: tuple[float, str, str | None, dict[str, FloatArray]],
    *,
    plots: bool,
) -> None:
    time_s, state, fault, rows = snapshot
    q, q_ref, q_exp, iq = rows["q"], rows["q_ref"], rows["q_exp"], rows["iq"]
    with server.atomic():
        page.show_state(state, fault, time_s)
        page.show_joints(q, q_ref, q_exp, iq)
        if plots:
            page.show_plots(history)


# ------------------------------------------------------------------------------------------------ replay


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
        self.server = _start_server(host, port)
        self._page = _Page(self.server, config, geometry)
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
        self._history = _History(len(names), int(HISTORY_S / log.period_s))
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
        _stop_server(self.server)
