"""Sans-I/O RMD protocol core (CAN v2.3 and RS485 v1.62): bytes <-> typed messages."""

from __future__ import annotations
