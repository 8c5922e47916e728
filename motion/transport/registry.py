"""Transports by name, with the backend module imported only when it is used (python-can's ``BACKENDS``).

``open_transport("can", interface="socketcan", channel="can0")`` imports python-can, ``open_transport("rs485",
port="/dev/ttyUSB0", baudrate=115200)`` imports pyserial; a program that uses one never loads the other.

The names come from the entry-point group :data:`ENTRY_POINT_GROUP` (declared in ``pyproject.toml``, as python-can
finds its interfaces): an installed package adds a kind of link by declaring its :class:`Transport` class there.
:data:`BACKENDS` holds this package's own, for a source tree used without installing it.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any, Final

from motion.errors import TransportError
from motion.transport.base import Transport

#: The entry-point group transports are declared in.
ENTRY_POINT_GROUP: Final = "rmd_motion.transports"
#: This package's transports: name -> (module, class name).
BACKENDS: Final[Mapping[str, tuple[str, str]]] = {
    "can": ("motion.transport.can_transport", "CanTransport"),
    "rs485": ("motion.transport.rs485_transport", "Rs485Transport"),
}


def transport_class(name: str) -> type[Transport]:
    """Import and return the transport class registered as ``name``.

    Raises:
        TransportError: ``name`` is not a registered transport, or its backend cannot be imported.
    """
    declared = {entry.name: entry.value for entry in entry_points(group=ENTRY_POINT_GROUP)}
    target = declared.get(name) or (":".join(BACKENDS[name]) if name in BACKENDS else None)
    if target is None:
        raise TransportError(f"unknown transport {name!r}; valid: {', '.join(sorted(set(declared) | set(BACKENDS)))}")
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise TransportError(f"cannot import the {name!r} transport ({module_name}): {exc}") from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise TransportError(f"the {name!r} transport ({target}) is not a motion.transport.Transport class")
    return cls


def open_transport(name: str, *args: Any, **kwargs: Any) -> Transport:
    """Open a transport by name; the arguments go to its class unchanged.

    Args:
        name: ``"can"`` (:class:`~motion.transport.can_transport.CanTransport`) or ``"rs485"``
            (:class:`~motion.transport.rs485_transport.Rs485Transport`).

    Raises:
        TransportError: unknown name, backend not importable, or the bus or port could not be opened.
        EncodeError: a setting the protocol does not allow (an RS485 baud rate outside 9600..115200).
    """
    return transport_class(name)(*args, **kwargs)
