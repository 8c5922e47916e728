"""Control: clocks, the fixed-rate scheduler, axis state and the controller."""

from __future__ import annotations
