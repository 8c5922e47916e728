"""The ``--log`` file: every frame in and out, one human-readable line each.

Line format (columns separated by spaces)::

    TIME_S DIR CHANNEL WIRE | DECODED

``TIME_S`` is monotonic seconds since the log was opened (6 decimals); ``DIR`` is ``IN`` (request), ``OUT`` (reply),
``BAD`` (input that breaks the protocol, with the decode error) or ``NOTE`` (an event, such as a fault that swallowed
a request); ``CHANNEL`` names the attachment; ``WIRE`` is the frame in hex (CAN: ``ID: payload``).
"""

from __future__ import annotations

import os
import threading
import time
import types
from typing import TextIO


class FrameLog:
    """Thread-safe line writer for frame traffic.

    Args:
        path: file to write (truncated).

    Raises:
        OSError: the file cannot be opened.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._file: TextIO = open(path, "w", encoding="utf-8", buffering=1)  # noqa: SIM115 - closed by close()
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        #: Monotonic time of the log's zero, s (line times are relative to it).
        self.start_s = self._t0

    def write(self, direction: str, channel: str, wire: str, decoded: str) -> None:
        """Append one line (see the module docstring)."""
        line = f"{time.monotonic() - self._t0:12.6f} {direction:<4} {channel:<8} {wire} | {decoded}\n"
        with self._lock:
            if not self._file.closed:
                self._file.write(line)

    def close(self) -> None:
        """Flush and close the file; safe to call twice."""
        with self._lock:
            self._file.close()

    def __enter__(self) -> FrameLog:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: types.TracebackType | None
    ) -> None:
        self.close()
