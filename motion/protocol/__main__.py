"""``python -m motion.protocol`` prints the command × transport table of docs/protocol.md (``... v3``: the V3 family's
table)."""

from __future__ import annotations

import sys

from motion.protocol.reference import markdown_table, markdown_table_v3

sys.stdout.write(markdown_table_v3() if sys.argv[1:] == ["v3"] else markdown_table())
