"""A stop-gap for python-can's slcan interface: read every waiting byte at once, not one byte per system call.

python-can 4.6.1 (the newest release when this was written) takes in slcan input with one ``serial.read(1)`` per
byte: a 22-byte frame line costs 22 system calls, about 120 µs of CPU per received frame on a 2-vCPU machine,
several times the cost of a whole control cycle. python-can issue 2027 reports it; pull request 2028 (merged
upstream, not yet released) reads everything that is waiting at once. This module does the same in a subclass of
python-can's own ``slcanBus`` (our code, written for this project; only ``_read`` and ``_recv_internal`` differ):

- ``_read`` takes a complete line (``\\r`` or ``\\a`` ends it) from its buffer if there is one; otherwise it reads
  all bytes the port holds in one system call (``os.read`` on pyserial's non-blocking descriptor; ``in_waiting``
  and ``read`` where there is none), and when there are none it waits on the descriptor (or one ``read(1)``)
  until the timeout. Partial lines stay buffered for the next call. The timeout holds also while bytes keep coming
  (an adapter streaming junk), and the buffer is bounded: a line longer than any slcan line
  (:data:`MAX_LINE_BYTES`) is junk, dropped up to its end and counted (:attr:`SlcanShimBus.junk_bytes`, and once in
  :attr:`SlcanShimBus.garbled_lines`).
- ``_recv_internal`` (and :meth:`SlcanShimBus.recv_frame`) drop a garbled line and count it in
  :attr:`SlcanShimBus.garbled_lines`: one python-can's parser raises ValueError on (which would end a control loop),
  and a frame line not as the protocol writes it (:func:`well_formed`), which that parser takes as a frame — it reads
  the characters it needs and ignores the rest: junk after the data, two lines run together by a lost ``\r``. The
  transport then counts the missing reply as a timeout, as it would for a frame lost on the wire.
- :meth:`SlcanShimBus.pending_input` says whether a complete line is buffered: a caller that waits on the port's
  descriptor with ``select`` must not wait while lines it has not taken are already in this buffer.
- ``shutdown`` releases the port also when the adapter is dead (python-can's writes the close command first and,
  when that fails, leaves the descriptor open).
- :meth:`SlcanShimBus.recv_frame` and :meth:`SlcanShimBus.send_frame` carry a standard data frame as
  ``(arbitration id, data)`` without a ``can.Message`` on the way (python-can's ``BusABC.recv`` also formats a log
  call for every frame): the same line python-can writes, the same frame it parses; every other line goes through
  python-can's own parser. The control loop's frames take this path (issue 12: a cycle reads one frame per drive);
  :meth:`SlcanShimBus.send_frames` writes a cycle's batch of lines in one write (one system call and one drain, where
  python-can would make one of each per frame).

:class:`motion.transport.can_endpoint.CanEndpoint` uses it for ``interface: slcan`` only while
:func:`needs_shim` says the installed python-can lacks the fix. **Exit plan**: once a python-can release carries
pull request 2028, raise :data:`LAST_RELEASE_WITHOUT_FIX` no further, check that the upstream ``slcanBus`` does not
hide buffered lines from a ``select`` on ``fileno()`` (``CanEndpoint.recv`` relies on that) and that its parser
refuses the lines :func:`well_formed` refuses (else keep that check in a smaller subclass), then delete this module,
its use in ``can_endpoint.py`` and ``tests/test_slcan_shim.py``.
"""

from __future__ import annotations

import io
import os
import re
import select
import time
from binascii import hexlify
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from typing import Any, Final

import can
from can.interfaces.slcan import slcanBus

from motion.transport.base import PORT_ERRORS

#: The newest python-can release whose slcan reads one byte per call (python-can issue 2027, fixed by PR 2028).
LAST_RELEASE_WITHOUT_FIX: Final = (4, 6, 1)

_LINE_END: Final = re.compile(rb"[\r\a]")
#: The adapter's acknowledgements of a frame it sent (``z``: standard, ``Z``: extended), one per frame written.
_TRANSMIT_ACKS: Final = frozenset(("z\r", "Z\r"))
#: The longest line an slcan adapter sends, bytes: an extended CAN FD frame (``D`` or ``B``, 8 digits of id, the length
#: code, 64 data bytes in 128 digits) with a 4-digit time stamp, and its ``\r``. Anything longer is junk.
MAX_LINE_BYTES: Final = 1 + 8 + 1 + 2 * 64 + 4 + 1
#: A standard (11-bit) data frame line: ``t``, three hex digits of id, the length 0..8, two hex digits per byte.
_STANDARD_DATA: Final = re.compile(r"t([0-9A-Fa-f]{3})([0-8])((?:[0-9A-Fa-f]{2})*)\r")
#: The first letter of each kind of frame line python-can parses (``x``: CANDapter's ``T``), with the digits of its id
#: and whether a data length code counts CAN FD bytes (a hex digit) or plain ones (0..8), and whether data follows.
_FRAME_KINDS: Final = {
    "t": (3, False, True),
    "T": (8, False, True),
    "x": (8, False, True),
    "r": (3, False, False),
    "R": (8, False, False),
    "d": (3, True, True),
    "D": (8, True, True),
    "b": (3, True, True),
    "B": (8, True, True),
}
_HEX: Final = frozenset("0123456789ABCDEFabcdef")
#: Digits of the time stamp an adapter may append to a frame line.
_STAMP_DIGITS: Final = 4
#: Bytes asked of the port per read (a pty or a USB adapter rarely holds more; the rest comes with the next read).
_READ_CHUNK_BYTES: Final = 65536
_RELEASE: Final = re.compile(r"(\d+)(?:\.(\d+))?(?:\.(\d+))?")


def well_formed(line: str) -> bool:
    """Whether a frame line is one as the slcan protocol writes it: its id, length code and exactly the data that code
    says, hex digits only, an optional 4-digit time stamp, and ``\r``. python-can's parser reads the characters it
    needs and ignores the rest, so junk after the data, or two lines run together by a lost ``\r``, would pass as a
    frame."""
    kind = _FRAME_KINDS.get(line[:1])
    if kind is None or not line.endswith("\r"):
        return False
    id_digits, fd, has_data = kind
    body = line[1:-1]
    if not (len(body) > id_digits and _HEX.issuperset(body)):
        return False
    code = int(body[id_digits], 16)
    if fd:
        size = can.util.dlc2len(code)
    elif code <= 8:
        size = code
    else:
        return False
    rest = len(body) - id_digits - 1 - (2 * size if has_data else 0)
    return rest in (0, _STAMP_DIGITS)


def needs_shim(installed: str | None = None) -> bool:
    """True when the python-can release ``installed`` (default: the installed one) lacks the slcan read fix.

    Versions are compared by their release numbers: any release up to :data:`LAST_RELEASE_WITHOUT_FIX` (its
    pre-releases included) lacks the fix; a later one has it. An unreadable version counts as lacking it.
    """
    if installed is None:
        try:
            installed = version("python-can")
        except PackageNotFoundError:
            return True
    match = _RELEASE.match(installed)
    if match is None:
        return True
    release = tuple(int(part) if part is not None else 0 for part in match.groups())
    return release <= LAST_RELEASE_WITHOUT_FIX


class SlcanShimBus(slcanBus):
    """python-can's ``slcanBus`` reading every waiting byte at once (see the module docstring).

    Takes the arguments of ``can.interfaces.slcan.slcanBus``.
    """

    def __init__(self, channel: Any, **kwargs: Any) -> None:
        #: Lines that were neither a frame nor a reply python-can knows, dropped.
        self.garbled_lines = 0
        #: Bytes of lines longer than :data:`MAX_LINE_BYTES`, dropped.
        self.junk_bytes = 0
        self._in_junk = False  # the bytes up to the next line end belong to a junk line
        self._fd: int | None = None
        super().__init__(channel, **kwargs)
        try:
            self._fd = self.serialPortOrig.fileno()
        except (AttributeError, io.UnsupportedOperation, OSError, ValueError):
            self._fd = None

    def pending_input(self) -> bool:
        """True when a complete line is buffered (read from the port, not yet returned)."""
        return _LINE_END.search(self._buffer) is not None

    def _take_line(self) -> str | None:
        buffer = self._buffer
        while True:
            found = _LINE_END.search(buffer)
            if found is None:
                if self._in_junk or len(buffer) > MAX_LINE_BYTES:
                    self._drop_junk(len(buffer), ended=False)
                return None
            end = found.end()
            if end > MAX_LINE_BYTES or self._in_junk:
                self._drop_junk(end, ended=True)
                continue
            line = buffer[:end].decode(errors="replace")
            del buffer[:end]
            return line

    def _drop_junk(self, size: int, *, ended: bool) -> None:
        """Drop the first ``size`` bytes of the buffer, part of a line too long to be slcan (``ended``: up to its end,
        the next byte starts a line again)."""
        if not self._in_junk:
            self.garbled_lines += 1
        self._in_junk = not ended
        self.junk_bytes += size
        del self._buffer[:size]

    def _read(self, timeout: float | None) -> str | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                line = self._take_line()
                if line is not None:
                    return line
                took = self._take_waiting()
                remaining = None if deadline is None else deadline - time.monotonic()
                if took:
                    if remaining is None or remaining > 0.0:
                        continue
                    return self._take_line()  # the time is up, also while bytes keep coming (a flood of junk)
                if remaining is not None and remaining <= 0.0:
                    return None
                if self._fd is not None:
                    if select.select([self._fd], [], [], remaining)[0] and not self._take_waiting():
                        # Readable but nothing to read: the far end hung up (pyserial says the same).
                        raise can.CanOperationError("device reports readiness to read but returned no data")
                else:  # no descriptor: block in the port's own read, for at most its timeout
                    self._buffer += self.serialPortOrig.read(1)
        except PORT_ERRORS as exc:
            raise can.CanOperationError(f"Could not read from serial device: {exc}") from exc

    def _take_waiting(self) -> bool:
        """Append every byte the port holds to the buffer; False when it held none."""
        if self._fd is not None:
            # One system call: pyserial's port is non-blocking, and its in_waiting + read would make three.
            try:
                chunk = os.read(self._fd, _READ_CHUNK_BYTES)
            except BlockingIOError:
                return False
        else:
            waiting = self.serialPortOrig.in_waiting
            chunk = self.serialPortOrig.read(waiting) if waiting else b""
        self._buffer += chunk
        return bool(chunk)

    def shutdown(self) -> None:
        """python-can's shutdown (the adapter's close command, then the port), and the port released also when the
        command could not be written.

        Raises:
            can.CanOperationError: the close command could not be written (the port is released all the same).
        """
        try:
            super().shutdown()
        finally:
            self.serialPortOrig.close()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._queue.qsize():  # (python-can parses what its queue holds first: a line read here goes there)
            line = self._read(timeout)
            if line is None:
                return None, False
            if line[:1] in _FRAME_KINDS and not well_formed(line):
                self.garbled_lines += 1  # junk in the line, or two run together: dropped like a frame lost on the wire
                return None, False
            self._queue.put_nowait(line)
        try:
            return super()._recv_internal(0.0)
        except (ValueError, IndexError):
            # A garbled line (noise on the adapter's serial link): drop it, like a frame lost on the wire.
            self.garbled_lines += 1
            return None, False

    def recv_frame(self, timeout: float | None) -> tuple[int, bytes] | can.Message | None:
        """The next received line as ``(arbitration id, data)`` when it is a standard data frame, else as python-can
        makes it (a ``can.Message`` of another kind, or None: no frame before ``timeout``, an adapter's reply, a
        garbled line). Software filters (``can_filters``) are python-can's: with them set, this is ``recv``.

        Raises:
            can.CanOperationError: the port failed.
        """
        if self._filters is not None or self._queue.qsize():
            return self.recv(timeout)
        line = self._read(timeout)
        if line is None or line in _TRANSMIT_ACKS:  # (python-can's parser makes nothing of an acknowledgement either)
            return None
        match = _STANDARD_DATA.fullmatch(line)
        if match is not None:
            data = bytes.fromhex(match[3])
            if len(data) == int(match[2]):
                return int(match[1], 16), data
        if line[:1] in _FRAME_KINDS and not well_formed(line):
            self.garbled_lines += 1  # junk in the line, or two run together: dropped like a frame lost on the wire
            return None
        # Anything else as python-can parses it (the line goes back first in its queue, where it looks first).
        self._queue.put_nowait(line)
        return self.recv(0.0)

    def send_frames(self, frames: Sequence[tuple[int, bytes]], timeout: float | None) -> None:
        """Send standard data frames, their lines in one write (one system call and one drain for a cycle's batch:
        an adapter takes the lines as they come, whether in one USB transfer or several).

        Raises:
            can.CanOperationError: the port failed or the write timed out.
            ValueError: an id beyond 11 bits or more than 8 bytes (no standard frame; nothing was written).
        """
        lines = []
        for arbitration_id, data in frames:
            if not 0 <= arbitration_id <= 0x7FF or len(data) > 8:
                raise ValueError(
                    f"a standard data frame has an id 0..0x7FF and 0..8 bytes, got 0x{arbitration_id:X}, "
                    f"{len(data)} bytes"
                )
            lines.append(b"t%03X%d%s\r" % (arbitration_id, len(data), hexlify(data).upper()))
        port = self.serialPortOrig
        try:
            if timeout != port.write_timeout:
                port.write_timeout = timeout
            port.write(b"".join(lines))
            port.flush()
        except PORT_ERRORS as exc:
            raise can.CanOperationError(f"Could not write to serial device: {exc}") from exc

    def send_frame(self, arbitration_id: int, data: bytes, timeout: float | None) -> None:
        """Send a standard data frame: the line python-can's ``send`` writes for it, written and drained as it does.

        Raises:
            can.CanOperationError: the port failed or the write timed out.
            ValueError: an id beyond 11 bits or more than 8 bytes (no standard frame).
        """
        self.send_frames(((arbitration_id, data),), timeout)
