"""``python -m motion.emulator``: run the emulate command."""

from __future__ import annotations

import sys

from motion.emulator.cli import main

sys.exit(main())
