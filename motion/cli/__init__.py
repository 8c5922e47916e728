"""The ``rmd-motion`` command.

Exit codes: 0 done, 1 motion fault (axes halted), 2 usage or configuration error, 3 communication error,
130 interrupted by Ctrl-C (after every axis was halted). See :func:`motion.cli.app.build_parser` for the commands.

Like :mod:`motion.api`, this package is a composition root: it may build the Pinocchio model (``emulate --config``).
"""

from __future__ import annotations

from motion.cli.app import build_parser, main
from motion.cli.common import EXIT_COMMUNICATION, EXIT_FAULT, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE

__all__ = [
    "EXIT_COMMUNICATION",
    "EXIT_FAULT",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "build_parser",
    "main",
]
