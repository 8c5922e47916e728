"""A pseudo-terminal in raw mode with a stable symlink to its slave, for serial-port clients in other processes.

The emulator keeps the master and one slave descriptor open: with a slave open, the master never reads EIO when a
client closes the port, and the terminal settings survive between clients. Raw mode matters because a pty starts in
canonical mode with echo: it would echo the host's bytes back and turn slcan's CR into LF.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
from pathlib import Path

from motion.closing import Closing
from motion.errors import TransportError

#: Bytes read from the master per call.
_READ_CHUNK = 4096


def set_raw(fd: int) -> None:
    """Put a terminal in raw mode (as ``cfmakeraw``): 8-bit bytes, no echo, no line editing, no signals."""
    attrs = termios.tcgetattr(fd)
    iflag, oflag, cflag, lflag = 0, 1, 2, 3
    attrs[iflag] &= ~(
        termios.IGNBRK
        | termios.BRKINT
        | termios.PARMRK
        | termios.ISTRIP
        | termios.INLCR
        | termios.IGNCR
        | termios.ICRNL
        | termios.IXON
    )
    attrs[oflag] &= ~termios.OPOST
    attrs[lflag] &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    attrs[cflag] = (attrs[cflag] & ~(termios.CSIZE | termios.PARENB)) | termios.CS8
    cc = 6
    attrs[cc][termios.VMIN] = 1
    attrs[cc][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class PseudoTerminal(Closing):
    """A raw-mode pty; the emulator reads and writes the master, a client opens :attr:`path`.

    Args:
        link: where to create a symlink to the slave device (an existing symlink there is replaced; any other file
            is an error), or None for no link.

    Raises:
        TransportError: the pty or the link could not be created.
    """

    def __init__(self, link: str | os.PathLike[str] | None = None) -> None:
        try:
            self._master, self._slave = os.openpty()
        except OSError as exc:
            raise TransportError(f"cannot create a pseudo-terminal: {exc}") from exc
        self.slave_path = os.ttyname(self._slave)
        self.link = Path(link) if link is not None else None
        try:
            set_raw(self._slave)
            os.set_blocking(self._master, False)
            if self.link is not None:
                self._make_link(self.link)
        except (OSError, TransportError) as exc:
            self._close_fds()
            raise TransportError(f"cannot set up the pseudo-terminal {self.slave_path}: {exc}") from exc
        self._closed = False
        # The part of an accepted write that did not fit yet: sent before anything else, so that a full pty drops
        # whole writes (frames) and never the end of one, which would garble the client's stream.
        self._unsent = b""

    def _make_link(self, link: Path) -> None:
        if os.path.lexists(link) and not link.is_symlink():
            raise TransportError(f"{link} exists and is not a symlink; not replacing it")
        # Replace atomically, so that a client never sees the path missing.
        temporary = link.with_name(f".{link.name}.{os.getpid()}.tmp")
        with contextlib.suppress(FileNotFoundError):
            temporary.unlink()
        temporary.symlink_to(self.slave_path)
        os.replace(temporary, link)

    @property
    def path(self) -> str:
        """What a client opens: the link if there is one, else the slave device."""
        return str(self.link) if self.link is not None else self.slave_path

    def read(self, timeout_s: float) -> bytes:
        """Bytes the client wrote, waiting at most ``timeout_s``; empty if none. Sends what is left of a write first."""
        self._send_unsent()
        ready, _, _ = select.select([self._master], [], [], max(0.0, timeout_s))
        if not ready:
            return b""
        try:
            return os.read(self._master, _READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""

    def write(self, data: bytes) -> int:
        """Write to the client without blocking; returns the bytes dropped because the client does not read.

        A write is dropped whole or delivered whole: when only its beginning fits, the rest is kept and sent before
        anything else (by the next read or write); a write that finds such a rest still waiting is dropped.
        """
        if not self._send_unsent():
            return len(data)
        self._unsent = data
        self._send_unsent()
        return 0

    def _send_unsent(self) -> bool:
        """Send what is left of the last write; True when nothing is left."""
        view = memoryview(self._unsent)
        while view:
            try:
                written = os.write(self._master, view)
            except BlockingIOError:
                break
            view = view[written:]
        self._unsent = bytes(view)
        return not self._unsent

    def _close_fds(self) -> None:
        for fd in (self._slave, self._master):
            with contextlib.suppress(OSError):
                os.close(fd)

    def close(self) -> None:
        """Remove the link (if it still points here) and close the pty; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self.link is not None:
            with contextlib.suppress(OSError):
                if os.readlink(self.link) == self.slave_path:
                    self.link.unlink()
        self._close_fds()
