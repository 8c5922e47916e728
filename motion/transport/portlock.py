"""One session per port: an advisory lock on every port and CAN channel a transport opens.

A transport that opens a serial device (RS485, an slcan adapter), a SocketCAN interface or another python-can channel
takes an exclusive ``flock`` on a lock file named after it (:class:`PortLock`), before anything is sent, and releases
it when it closes. The system releases a ``flock`` when its descriptor closes, so a session that ended in any way,
a killed process too, leaves no stale lock behind (as a PID file would). Each opening of the lock file is a lock of
its own: a second ``Arm`` in the same process is refused as one in another process is, with
:class:`~motion.errors.PortHeld` naming the port and the process that holds it.

The lock files live where a user without root may write: ``$XDG_RUNTIME_DIR/rmd-motion``, else
``rmd-motion-<uid>`` in the temporary directory. A serial device is named by its resolved path (a symlink and the
device it points to are one port); a python-can ``virtual`` channel exists only in its process, so its lock is that
process's. The emulator's own side of a pseudo-terminal (the master, and the slave it keeps open) is no session and
takes no lock. Where the system has no ``flock`` (not POSIX), or no lock file can be made, the port opens unlocked,
with a warning in the second case.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import sys
import tempfile
import weakref
from pathlib import Path
from typing import Final

from motion.errors import PortHeld

try:
    import fcntl

    _HAVE_FLOCK = True
except ImportError:  # (not a POSIX system)
    _HAVE_FLOCK = False

logger = logging.getLogger("motion.transport")

#: The directory of the lock files under ``$XDG_RUNTIME_DIR`` (else ``rmd-motion-<uid>`` in the temporary directory).
LOCK_DIR_NAME: Final = "rmd-motion"
#: The longest readable part of a lock file's name (the rest is a digest of the port's key).
_NAME_CHARS: Final = 60
_UNSAFE: Final = re.compile(r"[^A-Za-z0-9._-]+")
#: What a lock file tells of its holder, at most, bytes.
_HOLDER_BYTES: Final = 300


def lock_dir() -> Path:
    """Where the lock files are (created, for this user only, when missing).

    Raises:
        OSError: it cannot be created.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isdir(runtime) and os.access(runtime, os.W_OK | os.X_OK):
        base = Path(runtime) / LOCK_DIR_NAME
    else:
        uid = os.getuid() if hasattr(os, "getuid") else 0
        base = Path(tempfile.gettempdir()) / f"{LOCK_DIR_NAME}-{uid}"
    base.mkdir(mode=0o700, parents=True, exist_ok=True)
    return base


def device_key(path: str) -> str:
    """The key of a serial device: its resolved path (a symlink to it is the same port)."""
    return "tty:" + os.path.realpath(path)


def can_key(interface: str, channel: str) -> str:
    """The key of a python-can channel: the adapter's serial device for ``slcan`` (without the ``@baud`` suffix), the
    channel of this process for ``virtual`` (its buses exist only here), else the interface and the channel."""
    if interface == "slcan":
        device = channel.split("@", 1)[0]
        return device_key(device) if os.sep in device else f"slcan:{device}"
    if interface == "virtual":
        return f"virtual:{os.getpid()}:{channel}"
    return f"{interface}:{channel}"


def _file_name(key: str) -> str:
    """A lock file's name: the key's readable part and a digest of the whole key (two keys never share a file)."""
    readable = _UNSAFE.sub("_", key).strip("_")[-_NAME_CHARS:]
    return f"{readable}-{hashlib.sha256(key.encode()).hexdigest()[:12]}.lock"


class PortLock:
    """An exclusive advisory lock on the port ``key`` names, held until :meth:`release` (or until the process ends).

    Args:
        key: the port's key (:func:`device_key`, :func:`can_key`).
        port: how messages name the port (``"RS485 port '/dev/ttyUSB0'"``).
        link: the kind of link, for the error (``"can"``, ``"rs485"``).

    Raises:
        PortHeld: another session (of this process or another) holds the port.
    """

    def __init__(self, key: str, port: str, link: str) -> None:
        self.key = key
        self.path: Path | None = None
        self._release: weakref.finalize[..., PortLock] | None = None
        if not _HAVE_FLOCK:
            return
        try:
            path = lock_dir() / _file_name(key)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o600)
        except OSError as exc:
            logger.warning("%s opens without a session lock (no lock file could be made: %s)", port, exc)
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _holder(fd)
            os.close(fd)
            raise PortHeld(
                f"{port} is held by another rmd-motion session ({holder}): nothing was sent; close that session "
                f"first (its lock: {path}; {exc.strerror})",
                link,
            ) from None
        try:  # who holds it, for the message a second opener gets
            os.ftruncate(fd, 0)
            os.write(fd, f"process {os.getpid()}: {' '.join(sys.argv)}"[:_HOLDER_BYTES].encode(errors="replace"))
        except OSError:
            pass
        self.path = path
        # (a lock whose transport was never closed is released when it is collected, as its port's descriptor is)
        self._release = weakref.finalize(self, os.close, fd)

    def release(self) -> None:
        """Release the lock; safe to call more than once."""
        if self._release is not None:
            self._release()


def _holder(fd: int) -> str:
    """What the lock file says of the session that holds it ("process 1234: rmd-motion run ..."; this process's)."""
    try:
        text = os.pread(fd, _HOLDER_BYTES, 0).decode(errors="replace").strip()
    except OSError:
        text = ""
    if not text:
        return "a process that has not said which"
    if text.startswith(f"process {os.getpid()}:"):
        return f"{text}, this process"
    return text
