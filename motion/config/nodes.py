"""The reader of a configuration's YAML mappings: :class:`Node` and the conversion of each kind of value.

A :class:`Node` is one mapping of the file being read into a schema dataclass (:mod:`motion.config.schema`): it knows
its file and key path, rejects unknown keys and takes the defaults from the dataclass. The section parsers
(:mod:`motion.config.sections`, :mod:`motion.config.joints`) ask it for typed values within an allowed range; every
problem raises :class:`~motion.errors.ConfigError` naming the file, the key path, what is allowed and what was found.
"""

from __future__ import annotations

import difflib
import math
import re
import sys
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import MISSING, dataclass, fields
from enum import StrEnum
from typing import Any, TypeVar, cast

from motion.config import schema
from motion.errors import ConfigError

_T = TypeVar("_T")
_E = TypeVar("_E", bound=StrEnum)

_FLOAT_MAX = sys.float_info.max
#: A name of the configuration's own (a bus under ``buses:``): it also appears in ``--channel NAME=VALUE``.
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")


@dataclass(frozen=True, slots=True)
class Range:
    """Allowed interval of a number; ``None`` leaves that side unbounded."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, value: float) -> bool:
        above = self.lo is None or value > self.lo or (not self.lo_open and value == self.lo)
        below = self.hi is None or value < self.hi or (not self.hi_open and value == self.hi)
        return above and below

    def __str__(self) -> str:
        low = "" if self.lo is None else f"{self.lo:g} {'<' if self.lo_open else '<='} "
        high = "" if self.hi is None else f" {'<' if self.hi_open else '<='} {self.hi:g}"
        return f"{low}x{high}" if low or high else "any finite number"


@dataclass(frozen=True, slots=True)
class OneOf:
    """Allowed set of numbers."""

    values: tuple[int, ...]

    def __contains__(self, value: float) -> bool:
        return value in self.values

    def __str__(self) -> str:
        return "one of " + ", ".join(str(v) for v in self.values)


#: What a number may be.
Allowed = Range | OneOf
ANY = Range()
POSITIVE = Range(lo=0, lo_open=True)
NON_NEGATIVE = Range(lo=0)


class Invalid(Exception):
    """A value is wrong; the reader adds file and key path (``suffix`` extends the path, e.g. ``[1]``)."""

    def __init__(self, message: str, suffix: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.suffix = suffix


def _describe(value: object) -> str:
    if isinstance(value, bool):
        return f"the boolean {value}"
    if value is None:
        return "nothing (null)"
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return f"the string {value!r}"
        return f"the string {value!r} (write numbers unquoted; YAML 1.1 needs a dot in exponents: 1.0e-4)"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list | tuple):
        return "a list"
    return repr(value)


def to_number(value: object, allowed: Allowed = ANY) -> float:
    """A finite number (an int or a float, not a bool) within ``allowed``, as a float."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise Invalid(f"expected a number ({allowed}); found {_describe(value)}")
    number = float(value) if abs(value) < _FLOAT_MAX else math.inf  # a huge YAML int would overflow float()
    if not math.isfinite(number) or number not in allowed:
        raise Invalid(f"out of range (allowed: {allowed}); found {value!r}")
    return number


def _to_integer(value: object, allowed: Allowed) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise Invalid(f"expected an integer ({allowed}); found {_describe(value)}")
    if value not in allowed:
        raise Invalid(f"out of range (allowed: {allowed}); found {value!r}")
    return value


def _to_flag(value: object) -> bool:
    if not isinstance(value, bool):
        raise Invalid(f"expected true or false; found {_describe(value)}")
    return value


def _to_text(value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise Invalid(f"expected a non-empty string; found {_describe(value)}")
    return value


def _to_choice(value: object, choices: type[_E], false_alias: _E | None, refused: Mapping[_E, str]) -> _E:
    if value is False and false_alias is not None:
        return false_alias  # YAML 1.1 reads an unquoted `off` as False
    for member, why in refused.items():
        if value == member.value:
            raise Invalid(why)
    if isinstance(value, str) and value in {c.value for c in choices}:
        return choices(value)
    hint = " (YAML 1.1 reads unquoted on/off/yes/no as booleans; quote the value)" if isinstance(value, bool) else ""
    allowed = ", ".join(c.value for c in choices if c not in refused)
    raise Invalid(f"expected one of {allowed}; found {_describe(value)}{hint}")


def _to_numbers(value: object, count: int, form: str) -> list[float]:
    """A list of ``count`` finite numbers (``form`` names them in the message, e.g. ``[x, y, z]``)."""
    if not isinstance(value, list | tuple) or len(value) != count:
        raise Invalid(f"expected a list of {count} numbers {form}; found {_describe(value)}")
    items: list[float] = []
    for i, item in enumerate(value):
        try:
            items.append(to_number(item))
        except Invalid as exc:
            raise Invalid(exc.message, f"[{i}]") from None
    return items


def _to_vector3(value: object) -> schema.Vec3:
    x, y, z = _to_numbers(value, 3, "[x, y, z]")
    return (x, y, z)


def _to_interval(value: object) -> tuple[float, float]:
    low, high = _to_numbers(value, 2, "[min, max]")
    if low >= high:
        raise Invalid(f"expected [min, max] with min < max; found [{low:g}, {high:g}]")
    return (low, high)


#: Keys of earlier versions, and what replaced them (a key in control cycles changed its meaning with the rate).
_REPLACED = {
    "collision_window_cycles": "replaced by collision_window_s, in seconds (the cycles times the control period: "
    "8 cycles at 250 Hz is 0.032)",
    "collision_gain_per_cycle": "replaced by collision_observer_gain_per_s, the observer gain K_O in 1/s (the gain "
    "per cycle times control.rate_hz: 0.5 at 250 Hz is 125)",
}


class Node:
    """A YAML mapping being read into one of the schema dataclasses.

    It knows its file and key path, rejects unknown keys up front (so that a misspelt key is reported as such,
    not as a missing one) and takes each key's default from the dataclass field.
    """

    def __init__(
        self,
        data: object,
        source: str,
        path: str,
        *schemas: type[Any],
        extra: Iterable[str] = (),
        hidden: Iterable[str] = (),
    ) -> None:
        self.source = source
        self.path = path
        if not isinstance(data, Mapping):
            raise ConfigError(source, path or "<root>", f"expected a mapping of keys; found {_describe(data)}")
        self._data: Mapping[Hashable, object] = data
        self._defaults: dict[str, object] = {}
        allowed = set(extra)
        for kind in schemas:
            for f in fields(kind):
                if f.metadata.get("derived"):
                    continue  # set from another key (e.g. the torque-mode half of collision_threshold_nm)
                allowed.add(f.name)
                if f.default is not MISSING:
                    self._defaults[f.name] = f.default
                elif f.default_factory is not MISSING:
                    self._defaults[f.name] = f.default_factory()
        allowed -= set(hidden)
        for key in data:
            if key in _REPLACED and key not in allowed:
                raise self.error(str(key), _REPLACED[str(key)])
            if key not in allowed:
                close = difflib.get_close_matches(str(key), allowed, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                known = ", ".join(sorted(allowed))
                raise self.error(str(key), f"unknown key{hint}; allowed keys: {known}")

    def key_path(self, key: str) -> str:
        """Full key path of ``key`` in this mapping (the mapping's own path for ``""``)."""
        if not key:
            return self.path
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, message: str) -> ConfigError:
        """A ConfigError for ``key`` of this mapping."""
        return ConfigError(self.source, self.key_path(key), message)

    def has(self, key: str) -> bool:
        """Whether the file gives ``key``."""
        return key in self._data

    def defaults(self, **values: object) -> Node:
        """Replace the schema's defaults of some keys (defaults that depend on another section); returns self."""
        self._defaults.update(values)
        return self

    def read(self, key: str, expected: str, convert: Callable[[object], _T], required: bool | None) -> _T:
        """``key`` converted by ``convert`` (which raises :class:`Invalid`), else the default; ``expected`` names what
        a missing required key takes, ``required`` (when not None) overrides the schema."""
        if key in self._data:
            try:
                return convert(self._data[key])
            except Invalid as exc:
                raise ConfigError(self.source, self.key_path(key) + exc.suffix, exc.message) from None
        if required or key not in self._defaults:
            raise self.error(key, f"required key is missing (expected {expected})")
        return cast(_T, self._defaults[key])

    def number(self, key: str, allowed: Allowed = ANY, *, required: bool | None = None) -> float:
        """A finite number (int or float, not bool) within ``allowed``; ``required`` overrides the schema."""
        return self.read(key, f"a number, {allowed}", lambda v: to_number(v, allowed), required)

    def integer(self, key: str, allowed: Allowed) -> int:
        """An integer (not bool, not float) within ``allowed``."""
        return self.read(key, f"an integer, {allowed}", lambda v: _to_integer(v, allowed), None)

    def flag(self, key: str) -> bool:
        """A boolean."""
        return self.read(key, "true or false", _to_flag, None)

    def text(self, key: str) -> str:
        """A non-empty string."""
        return self.read(key, "a non-empty string", _to_text, None)

    def choice(
        self, key: str, choices: type[_E], *, false_alias: _E | None = None, refused: Mapping[_E, str] | None = None
    ) -> _E:
        """One of the values of a StrEnum; ``false_alias`` is what a YAML 1.1 boolean False stands for; ``refused``
        members are not valid here (each with the reason given)."""
        no = refused or {}
        expected = "one of " + ", ".join(c.value for c in choices if c not in no)
        return self.read(key, expected, lambda v: _to_choice(v, choices, false_alias, no), None)

    def vector3(self, key: str) -> schema.Vec3:
        """A list of three finite numbers."""
        return self.read(key, "a list of 3 numbers", _to_vector3, None)

    def interval(self, key: str) -> tuple[float, float]:
        """A list of two finite numbers, the first smaller."""
        return self.read(key, "a list of 2 numbers [min, max]", _to_interval, None)

    def child(self, key: str, *schemas: type[Any], extra: Iterable[str] = ()) -> Node:
        """The sub-mapping ``key`` (an empty one when absent and the schema gives it a default)."""
        if key not in self._data and key not in self._defaults:
            raise self.error(key, "required section is missing")
        return Node(self._data.get(key, {}), self.source, self.key_path(key), *schemas, extra=extra)

    def names(self, key: str) -> list[str]:
        """The keys of the non-empty mapping ``key`` (names such as ``buses``' ``left``, ``right``), in file order:
        each a letter, then letters, digits, ``_`` or ``-``."""
        items = self._data.get(key)
        if not isinstance(items, Mapping) or not items:
            found = (
                "nothing (missing)"
                if key not in self._data
                else "an empty mapping"
                if items == {}
                else _describe(items)
            )
            raise self.error(key, f"expected a non-empty mapping of names to sections; found {found}")
        for name in items:
            if not isinstance(name, str) or _NAME.fullmatch(name) is None:
                raise self.error(
                    key, f"{name!r} is not a name: a letter, then letters, digits, '_' or '-' (at most 32 characters)"
                )
        return list(cast(Mapping[str, object], items))

    def entry(self, key: str, name: str, *schemas: type[Any], extra: Iterable[str] = ()) -> Node:
        """The section ``name`` of the mapping ``key`` (see :meth:`names`)."""
        items = cast(Mapping[str, object], self._data[key])
        return Node(items[name], self.source, f"{self.key_path(key)}.{name}", *schemas, extra=extra)

    def children(self, key: str, kind: type[Any]) -> list[Node]:
        """The non-empty list of mappings ``key``."""
        items = self._data.get(key)
        if not isinstance(items, list) or not items:
            found = "nothing (missing)" if key not in self._data else _describe(items)
            raise self.error(key, f"expected a non-empty list of mappings; found {found}")
        return [Node(item, self.source, f"{self.key_path(key)}[{i}]", kind) for i, item in enumerate(items)]
