"""The host's record of the drives' ROM-backed settings: what rmd-motion last wrote where the drive cannot be asked
(the V3 driver's 0xB3 communication-loss time has no read), what a drive held before rmd-motion first changed it (for
``rmd-motion restore``), and how many ROM writes rmd-motion has made to each drive.

A session writes a ROM-backed setting only when the drive's value (read, or for 0xB3 recorded here) differs from what
the session needs, so a second connect with the same configuration writes nothing (flash wears with every write).
One JSON file on the host (``drives.json`` in rmd-motion's state folder), keyed by the bus (``Transport.describe()``)
and the motor id. Several programs may share it (two arms on two buses, a ``status`` beside a running program): each
saves only what it changed, merged into the file as it is then, under an exclusive lock (``drives.json.lock``, POSIX
``flock``; without ``fcntl``, e.g. on Windows, the merge runs unlocked). A drive swapped for another,
or changed by another tool, is not seen by the record: ``rmd-motion restore`` (or deleting the file) makes the
next session write again. Emulated drives in simulated time are new in every session: their record stays in memory.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

try:
    import fcntl

    _LOCKS = True
except ImportError:  # (not POSIX: the record is merged without a lock)
    _LOCKS = False

logger = logging.getLogger(__name__)

#: The record file's version (a file of another version is set aside, not read).
_VERSION = 1


class DriveRecord:
    """The record (module docstring): per drive, named settings and the ROM writes counted.

    Args:
        path: the JSON file (None: in memory only). A file that cannot be read is logged and replaced at the next
            write; one that cannot be written is logged (the session goes on: the record only saves writes).
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._drives: dict[str, dict[str, Any]] = self._read() if path is not None else {}
        # what this record changed since its last save: the settings put, the ROM writes counted
        self._puts: dict[tuple[str, str], Any] = {}
        self._counted: dict[str, int] = {}

    def _read(self) -> dict[str, dict[str, Any]]:
        """The file's drives (empty where there is none, or an unreadable one: logged)."""
        path = self.path
        if path is None or not path.exists():
            return {}
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data.get("version") == _VERSION and isinstance(data.get("drives"), dict):
                drives: dict[str, dict[str, Any]] = data["drives"]
                return drives
            logger.warning("%s: not a drive record of version %d; starting a new one", path, _VERSION)
        except (OSError, ValueError, AttributeError) as exc:
            logger.warning("%s: unreadable drive record (%s); starting a new one", path, exc)
        return {}

    @staticmethod
    def key(bus: str, motor_id: int) -> str:
        """The record's key of a drive: its bus's description and its id."""
        return f"{bus} #{motor_id}"

    def get(self, key: str, name: str) -> Any:
        """A setting of drive ``key`` (None: not recorded)."""
        return self._drives.get(key, {}).get(name)

    def put(self, key: str, name: str, value: Any) -> None:
        """Record a setting (None removes it)."""
        _put(self._drives, key, name, value)
        self._puts[key, name] = value

    def count_rom_writes(self, key: str, writes: int) -> None:
        """Add ``writes`` ROM writes to drive ``key``'s count."""
        _count(self._drives, key, writes)
        self._counted[key] = self._counted.get(key, 0) + writes

    def forget(self, key: str) -> None:
        """Remove everything recorded of drive ``key`` (its settings and its ROM-write count)."""
        for name in list(self._drives.get(key, {})):
            self.put(key, name, None)
        self._counted.pop(key, None)

    def rom_writes(self, key: str) -> int:
        """The ROM writes rmd-motion has made to drive ``key`` (as recorded)."""
        return int(self._drives.get(key, {}).get("rom_writes", 0))

    def save(self) -> None:
        """Write what this record changed into the file as it is now (another program may have saved since this one
        read it), under the lock, atomically (a new file renamed over the old one); this record then holds the merge."""
        if self.path is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with self._locked():
                drives = self._read()
                for (key, name), value in self._puts.items():
                    _put(drives, key, name, value)
                for key, writes in self._counted.items():
                    _count(drives, key, writes)
                text = json.dumps({"version": _VERSION, "drives": drives}, indent=1, sort_keys=True)
                with tempfile.NamedTemporaryFile("w", dir=self.path.parent, delete=False, encoding="utf-8") as out:
                    out.write(text)
                os.replace(out.name, self.path)
        except OSError as exc:
            logger.warning("%s: the drive record was not written (%s)", self.path, exc)
            return
        self._drives, self._puts, self._counted = drives, {}, {}

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The record's exclusive lock (a file beside it), held while the file is read, merged and replaced."""
        assert self.path is not None
        if not _LOCKS:
            yield
            return
        with open(self.path.with_name(self.path.name + ".lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)


def _put(drives: dict[str, dict[str, Any]], key: str, name: str, value: Any) -> None:
    entry = drives.setdefault(key, {})
    if value is None:
        entry.pop(name, None)
    else:
        entry[name] = value


def _count(drives: dict[str, dict[str, Any]], key: str, writes: int) -> None:
    entry = drives.setdefault(key, {})
    entry["rom_writes"] = int(entry.get("rom_writes", 0)) + writes


#: A drive's runtime (0xB1) may differ from the host's clock by this share of the time between two readings, plus
#: :data:`RUNTIME_SLACK_S`, for them to be taken as one power-on of one drive.
RUNTIME_DRIFT = 0.01
RUNTIME_SLACK_S = 1.0


def same_power_on(runtime_then_s: float, at_then_s: float, runtime_now_s: float, now_s: float) -> bool:
    """Whether a drive whose runtime (time since its power-on, 0xB1) read ``runtime_then_s`` at host time
    ``at_then_s`` and reads ``runtime_now_s`` at ``now_s`` has run all along since: its runtime went on as the host's
    clock did. False for a drive that was powered off and on since (or another drive on its id)."""
    ran_s, passed_s = runtime_now_s - runtime_then_s, now_s - at_then_s
    return ran_s >= 0.0 and abs(ran_s - passed_s) <= RUNTIME_DRIFT * max(passed_s, 0.0) + RUNTIME_SLACK_S
