"""``python -m motion.protocol`` prints the command × transport table of docs/protocol.md."""

from __future__ import annotations

import sys

from motion.protocol.reference import markdown_table

sys.stdout.write(markdown_table())
