"""The live page of an arm driven in this process: :class:`LiveView` in the arm's process, and the page's own
process it starts (see :mod:`motion.view`)."""

from __future__ import annotations

import contextlib
import logging
import math
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from motion.config import ArmConfig
from motion.control.snapshot import JOINT_ROWS, CycleSnapshot
from motion.errors import MotionError
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

# the view's one logger, whichever of its modules logs
logger = logging.getLogger("motion.view")

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
        # the latest snapshot published, when (wall clock), and the latest sent: a picture the rate or a full socket
        # held back is sent once the loop pauses (simulated time stops while the program does not wait)
        self._sending = threading.Lock()
        self._latest: CycleSnapshot | None = None
        self._latest_wall_s = 0.0
        self._sent: CycleSnapshot | None = None
        self._tried: CycleSnapshot | None = None
        self._thread = threading.Thread(target=self._receive, name="rmd-motion view", daemon=True)
        self._thread.start()
        self._flusher = threading.Thread(target=self._flush, name="rmd-motion view flush", daemon=True)
        self._flusher.start()

    def publish(self, snapshot: CycleSnapshot) -> None:
        """Called by the loop after each cycle: send the snapshot when :data:`VIEW_RATE_HZ` allows or the state
        changed (one held back is sent once the loop pauses: :meth:`_flush`); never waits for the page."""
        self._latest = snapshot
        self._latest_wall_s = time.monotonic()
        if snapshot.time_s < self._next_s and snapshot.state == self._state:
            return
        self._next_s = snapshot.time_s + self._period_s
        with self._sending:
            self._send(snapshot)

    def _send(self, snapshot: CycleSnapshot) -> None:
        """One snapshot to the page's process (under ``_sending``; one tried before is not counted again when the page
        is still behind)."""
        again, self._tried = snapshot is self._tried, snapshot
        state = snapshot.state
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
            self._sent = snapshot
        except OSError:  # full (the page is behind) or gone: a view misses a picture, the arm goes on
            self.dropped += not again
        except Exception:  # the view must never take the loop down: it says so (once) and goes on
            self.failures += 1
            if self.failures == 1:
                logger.exception("the view could not be sent a cycle (further failures are counted, not logged)")

    def _flush(self) -> None:
        """While the view is open: the latest snapshot, where the loop has published none for a period since it and it
        was not sent (the rate held it back, or the page was behind), goes to the page now."""
        while not self._closing:
            time.sleep(self._period_s)
            latest = self._latest
            if latest is None or latest is self._sent or time.monotonic() - self._latest_wall_s < self._period_s:
                continue
            with self._sending:
                if latest is self._latest and latest is not self._sent:
                    self._send(latest)

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
        for thread in (self._thread, self._flusher):
            if thread.is_alive() and thread is not threading.current_thread():
                thread.join(2.0)
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
    "import socket; from motion.view.live import _serve_live; "
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
        server = start_server(host, port)
        page = Page(server, config, figure(config))
    except Exception as exc:  # the arm's process raises it as a MotionError
        send(("error", f"{type(exc).__name__}: {exc}"))
        return
    button = server.gui.add_button("STOP", color="red")
    button.on_click(lambda _event: send(("stop", None)))
    history = History(len(config.joints), int(HISTORY_S * VIEW_RATE_HZ))
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
        stop_server(server)


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
    page: Page,
    history: History,
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
