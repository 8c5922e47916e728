"""A virtual USB-CAN adapter speaking the slcan (LAWICEL / CAN232 / CANUSB) ASCII protocol, sans I/O.

Feed it the bytes the host wrote; it returns the bytes to write back and the CAN frames to put on the bus. Every
command ends with CR; the adapter answers CR for OK and BELL (0x07) for an error, as the LAWICEL documents and
python-can's ``slcan`` interface expect. Supported commands (channel state they need in brackets):

- ``Sn`` bit rate n = 0..8: 10k, 20k, 50k, 100k, 125k, 250k, 500k, 800k, 1M bit/s [closed];
- ``sxxyy`` bit rate from SJA1000 BTR0/BTR1 at an 8 MHz clock [closed];
- ``O`` open; ``L`` open listen-only, frames from the host are refused [closed]; ``C`` close [open];
- ``tiiildd..`` standard data frame, answered ``z`` CR; ``Tiiiiiiiildd..`` extended, answered ``Z`` CR;
  ``riiil`` / ``Riiiiiiiil`` remote frames, answered ``z`` / ``Z`` CR [open, not listen-only];
- ``V`` versions ``Vhhss`` CR; ``N`` serial number ``Nxxxx`` CR [any];
- ``F`` status flags ``Fxx`` CR, always 00: no overrun, no bus error [open];
- ``Z0`` / ``Z1`` time stamps off / on: 4 hex digits of milliseconds (mod 60000) after each frame [closed];
- ``Mxxxxxxxx`` / ``mxxxxxxxx`` acceptance code / mask, stored but every frame passes [closed];
- ``X0`` / ``X1`` auto-poll off / on (default on) [closed]; with auto-poll off, ``P`` polls one received frame
  (CR alone if none) and ``A`` all of them followed by ``A`` CR [open];
- ``Un`` UART speed, accepted (a pseudo-terminal has none) [closed]; ``Qn`` auto-startup, accepted [any];
- an empty command is a no-op answered CR (python-can sends one when it sets no data bit rate).

Anything else, a command in the wrong channel state, or a malformed frame answers BELL (counted in ``errors``).
The bit rate defaults to 1 Mbit/s, so ``O`` works without ``S`` as on common adapters.
"""

from __future__ import annotations

import string
from collections import deque
from dataclasses import dataclass
from typing import Final

from motion.protocol import CanFrame

OK: Final = b"\r"
BELL: Final = b"\a"
#: ``Sn`` bit rates, bit/s (LAWICEL: S7 is 800 kbit/s).
BITRATES: Final = {
    "0": 10_000,
    "1": 20_000,
    "2": 50_000,
    "3": 100_000,
    "4": 125_000,
    "5": 250_000,
    "6": 500_000,
    "7": 800_000,
    "8": 1_000_000,
}
DEFAULT_BITRATE: Final = 1_000_000
#: SJA1000 clock behind the ``s`` command's BTR registers, Hz.
_BTR_CLOCK_HZ: Final = 8_000_000
#: A command line longer than this is garbage (the longest valid one, an extended 8-byte frame, is 26).
_MAX_LINE: Final = 64
#: Time stamps count milliseconds modulo one minute.
_TIMESTAMP_MODULO_MS: Final = 60_000
_STANDARD_ID_MAX: Final = 0x7FF
_EXTENDED_ID_MAX: Final = 0x1FFFFFFF
_HEX_DIGITS: Final = string.hexdigits


@dataclass(frozen=True, slots=True)
class SlcanFrame:
    """A frame the host asked the adapter to send.

    Attributes:
        arbitration_id: 11- or 29-bit identifier.
        data: data bytes (empty for remote frames).
        extended: 29-bit identifier.
        remote: remote-transmission request.
    """

    arbitration_id: int
    data: bytes
    extended: bool = False
    remote: bool = False


def _is_hex(text: str) -> bool:
    return bool(text) and not text.strip(_HEX_DIGITS)


def _btr_bitrate(btr: str) -> int | None:
    """Bit rate of SJA1000 BTR0/BTR1 given as 4 hex digits, or None if they are not a valid timing."""
    if len(btr) != 4 or not _is_hex(btr):
        return None
    btr0, btr1 = int(btr[:2], 16), int(btr[2:], 16)
    prescaler = 2 * ((btr0 & 0x3F) + 1)
    quanta = 1 + ((btr1 & 0x0F) + 1) + (((btr1 >> 4) & 0x07) + 1)
    return round(_BTR_CLOCK_HZ / (prescaler * quanta))


class SlcanDevice:
    """The adapter's state machine (see the module docstring).

    Args:
        hardware_version: two decimal digits reported by ``V``.
        software_version: two decimal digits reported by ``V``.
        serial_number: four characters reported by ``N``.
    """

    def __init__(self, *, hardware_version: int = 10, software_version: int = 13, serial_number: str = "EMU1") -> None:
        self._version = f"V{hardware_version:02d}{software_version:02d}".encode() + OK
        self._serial = f"N{serial_number[:4]:<4}".encode() + OK
        self.is_open = False
        self.listen_only = False
        self.bitrate = DEFAULT_BITRATE
        self.timestamps = False
        self.auto_poll = True
        #: Commands answered with BELL.
        self.errors = 0
        self._line = bytearray()
        self._overlong = False
        self._polled: deque[bytes] = deque()

    def feed(self, data: bytes) -> tuple[bytes, list[SlcanFrame]]:
        """Process bytes the host wrote; return ``(bytes to send back, frames to put on the bus)``."""
        out = bytearray()
        frames: list[SlcanFrame] = []
        if b"\n" in data:  # some terminals send CR LF
            data = data.replace(b"\n", b"")
        *ended, rest = data.split(OK)
        for chunk in ended:  # each ended by a CR
            if self._overlong:
                self._overlong = False  # already answered BELL; the CR only ends the garbage
            elif len(self._line) + len(chunk) > _MAX_LINE:
                self.errors += 1
                out += BELL  # (and the CR ends the garbage)
            else:
                self._line += chunk
                line = self._line.decode("ascii", errors="replace")
                out += self._command(line, frames)
            self._line.clear()
        if rest and not self._overlong:
            if len(self._line) + len(rest) > _MAX_LINE:
                self._line.clear()
                self._overlong = True
                self.errors += 1
                out += BELL
            else:
                self._line += rest
        return bytes(out), frames

    def to_host(self, frame: CanFrame, now_s: float) -> bytes:
        """The bytes that deliver a received bus frame to the host: empty if the channel is closed, or queued for
        ``P`` / ``A`` when auto-poll is off.
        """
        if not self.is_open:
            return b""
        line = f"t{frame.arbitration_id:03X}{len(frame.data)}{frame.data.hex().upper()}"
        if self.timestamps:
            line += f"{int(now_s * 1000) % _TIMESTAMP_MODULO_MS:04X}"
        wire = line.encode() + OK
        if self.auto_poll:
            return wire
        self._polled.append(wire)
        return b""

    def _command(self, line: str, frames: list[SlcanFrame]) -> bytes:
        head, arg = line[:1], line[1:]
        if not line:
            return OK
        closed = not self.is_open
        answer = self._closed_command(head, arg) if closed else self._open_command(head, arg, frames)
        if answer is None:
            if head == "V" and not arg:
                answer = self._version
            elif head == "N" and not arg:
                answer = self._serial
            elif _acknowledged_setting(head, arg, closed):
                answer = OK
        if answer is None:
            self.errors += 1
            return BELL
        return answer

    def _closed_command(self, head: str, arg: str) -> bytes | None:
        """The commands of a closed channel (bit rate, open, time stamps, auto-poll); None for any other."""
        if head == "S" and arg in BITRATES:
            self.bitrate = BITRATES[arg]
            return OK
        if head == "s" and (bitrate := _btr_bitrate(arg)) is not None:
            self.bitrate = bitrate
            return OK
        if head in ("O", "L") and not arg:
            self.is_open, self.listen_only = True, head == "L"
            return OK
        if head in ("Z", "X") and arg in ("0", "1"):
            if head == "Z":
                self.timestamps = arg == "1"
            else:
                self.auto_poll = arg == "1"
            return OK
        return None

    def _open_command(self, head: str, arg: str, frames: list[SlcanFrame]) -> bytes | None:
        """The commands of an open channel (close, frames, status flags, polls); None for any other."""
        if head == "C" and not arg:
            self.is_open = False
            self._polled.clear()
            return OK
        if head in ("t", "T", "r", "R") and not self.listen_only:
            frame = _parse_frame(head, arg)
            if frame is None:
                return None
            frames.append(frame)
            return (b"Z" if frame.extended else b"z") + OK
        if head == "F" and not arg:
            return b"F00" + OK
        if head in ("P", "A") and not self.auto_poll and not arg:
            return self._poll(head == "A")
        return None

    def _poll(self, all_frames: bool) -> bytes:
        if not all_frames:
            return self._polled.popleft() if self._polled else OK
        out = b"".join(self._polled) + b"A" + OK
        self._polled.clear()
        return out


def _acknowledged_setting(head: str, arg: str, closed: bool) -> bool:
    """Settings a pty adapter accepts without effect: acceptance filter, UART speed, auto-startup."""
    if head in ("M", "m"):
        return closed and len(arg) == 8 and _is_hex(arg)
    if head == "U":
        return closed and len(arg) == 1 and arg in "0123456"
    return head == "Q" and arg in ("0", "1", "2")


def _parse_frame(kind: str, arg: str) -> SlcanFrame | None:
    """Parse the part after ``t``/``T``/``r``/``R``; None if malformed."""
    extended = kind in ("T", "R")
    remote = kind in ("r", "R")
    id_digits = 8 if extended else 3
    if len(arg) < id_digits + 1 or not _is_hex(arg[:id_digits]) or not arg[id_digits].isdigit():
        return None
    arbitration_id = int(arg[:id_digits], 16)
    length = int(arg[id_digits])
    payload = arg[id_digits + 1 :]
    if arbitration_id > (_EXTENDED_ID_MAX if extended else _STANDARD_ID_MAX) or length > 8:
        return None
    if remote:
        return SlcanFrame(arbitration_id, b"", extended, True) if not payload else None
    if len(payload) != 2 * length or (payload and not _is_hex(payload)):
        return None
    return SlcanFrame(arbitration_id, bytes.fromhex(payload), extended, False)
