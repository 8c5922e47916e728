"""Transports by name, with the backend module imported only when it is used (python-can's ``BACKENDS``).

``open_transport("can", interface="socketcan", channel="can0")`` imports python-can, ``open_transport("rs485",
port="/dev/ttyUSB0", baudrate=115200)`` imports pyserial; a program that uses one never loads the other.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any, Final

from motion.errors import TransportError
from motion.transport.base import Transport

#: Transport name -> (module, class name).
BACKENDS: Final[Mapping[str, tuple[str, str]]] = {
    "can": ("motion.transport.can_transport", "CanTransport"),
    "rs485": ("motion.transport.rs485_transport", "Rs485Transport"),
}


def transport_class(name: str) -> type[Transport]:
    """Import and return the transport class registered as ``name``.

    Raises:
        TransportError: ``name`` is not a registered transport, or its backend cannot be imported.
    """
    try:
        module_name, class_name = BACKENDS[name]
    except KeyError:
        raise TransportError(f"unknown transport {name!r}; valid: {', '.join(sorted(BACKENDS))}") from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise TransportError(f"cannot import the {name!r} transport ({module_name}): {exc}") from exc
    cls: type[Transport] = getattr(module, class_name)
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
