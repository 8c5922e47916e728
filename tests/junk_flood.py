"""A pseudo-terminal whose far end streams junk: an adapter that floods its port (issue 29)."""

from __future__ import annotations

import contextlib
import os
import select
import threading
import tty
from typing import Final

from motion.closing import Closing

#: What the flood writes: no ``\r`` (no slcan line ever ends) and no 0x3E (no RS485 frame ever starts).
JUNK: Final = b"x" * 4096


class JunkFlood(Closing):
    """A pty pair whose master a thread fills with :data:`JUNK` as fast as the slave is read (and whose input it
    reads and drops, so that the client's writes never block), until :meth:`close` or ``seconds``.

    Attributes:
        path: the slave device, for the client to open.
        written: bytes of junk written so far.
    """

    def __init__(self, seconds: float = 10.0) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.written = 0
        self._stop = threading.Event()
        self._seconds = seconds
        self._thread = threading.Thread(target=self._run, name="junk-flood", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        timer = threading.Timer(self._seconds, self._stop.set)
        timer.start()
        try:
            while not self._stop.is_set():
                readable, writable, _ = select.select([self._master], [self._master], [], 0.05)
                with contextlib.suppress(BlockingIOError):
                    if readable:
                        os.read(self._master, 65536)
                    if writable:
                        self.written += os.write(self._master, JUNK)
        except OSError:  # the pair was closed under the thread
            pass
        finally:
            timer.cancel()

    def close(self) -> None:
        """Stop the flood and close the pair."""
        self._stop.set()
        self._thread.join()
        os.close(self._master)
        os.close(self._slave)
