"""``python -m motion.cli``: the ``rmd-motion`` command."""

from __future__ import annotations

import sys

from motion.cli.app import main

sys.exit(main())
