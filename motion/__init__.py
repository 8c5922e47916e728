"""rmd-motion: trajectory-level multi-axis motion control for MyActuator RMD servo drives."""

from __future__ import annotations

__version__ = "0.1.0"
