"""The ``--log`` file: every frame in and out, one human-readable line each.

Line format (columns separated by spaces)::

    TIME_S DIR CHANNEL WIRE | DECODED

``TIME_S`` is seconds of the log's clock (monotonic, or a simulation's) since the log was opened (6 decimals);
``DIR`` is ``IN`` (request), ``OUT`` (reply),
``BAD`` (input that breaks the protocol, with the decode error) or ``NOTE`` (an event, such as a fault that swallowed
a request); ``CHANNEL`` names the attachment; ``WIRE`` is the frame in hex (CAN: ``ID: payload``).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from typing import TextIO

from motion.closing import Closing


class FrameLog(Closing):
    """Thread-safe line writer for frame traffic.

    Args:
        path: file to write (truncated).
        clock: time source of the line times, s (default the monotonic clock; a simulation passes its own).

    Raises:
        OSError: the file cannot be opened.
    """

    def __init__(self, path: str | os.PathLike[str], *, clock: Callable[[], float] = time.monotonic) -> None:
        self._file: TextIO = open(path, "w", encoding="utf-8", buffering=1)  # noqa: SIM115 - closed by close()
        self._lock = threading.Lock()
        self.clock = clock
        self._t0 = clock()
        #: Time of the log's zero on its clock, s (line times are relative to it).
        self.start_s = self._t0

    def write(self, direction: str, channel: str, wire: str, decoded: str, *, time_s: float | None = None) -> None:
        """Append one line (see the module docstring); ``time_s`` on the log's clock, default now."""
        stamp = (self.clock() if time_s is None else time_s) - self._t0
        line = f"{stamp:12.6f} {direction:<4} {channel:<8} {wire} | {decoded}\n"
        with self._lock:
            if not self._file.closed:
                self._file.write(line)

    def close(self) -> None:
        """Flush and close the file; safe to call twice."""
        with self._lock:
            self._file.close()
