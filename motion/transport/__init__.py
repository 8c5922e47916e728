"""Bus transports: python-can (any interface) and RS485 over pyserial.

The backends are imported lazily: ``from motion.transport import CanTransport`` (or :func:`open_transport`)
loads python-can only then, and likewise pyserial for :class:`Rs485Transport`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from motion.transport.base import BusCounters, MotorCounters, Reply, Request, Transport
from motion.transport.registry import BACKENDS, open_transport, transport_class

if TYPE_CHECKING:
    from motion.transport.can_transport import CanTransport
    from motion.transport.rs485_transport import Rs485Transport

__all__ = [
    "BACKENDS",
    "BusCounters",
    "CanTransport",
    "MotorCounters",
    "Reply",
    "Request",
    "Rs485Transport",
    "Transport",
    "open_transport",
    "transport_class",
]

_LAZY = {"CanTransport": "can", "Rs485Transport": "rs485"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return transport_class(_LAZY[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
