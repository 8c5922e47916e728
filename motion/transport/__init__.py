"""Bus transports: python-can (any interface) and RS485 over pyserial."""

from __future__ import annotations
