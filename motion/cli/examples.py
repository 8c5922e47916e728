"""``rmd-motion init [DIR]``: copy the example configurations (and the URDF they name) into a directory to edit."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Final

from motion.cli.common import EXIT_OK, Interrupts, UsageError
from motion.config.examples import CONFIGS_DIR, copy_examples

HELP: Final = "copy the example configurations and their URDF into DIR (default ./configs) to edit"


def add_init_arguments(parser: argparse.ArgumentParser) -> None:
    """``DIR`` and ``--force``."""
    parser.add_argument(
        "dir", nargs="?", type=Path, default=Path(CONFIGS_DIR), metavar="DIR", help=f"default ./{CONFIGS_DIR}"
    )
    parser.add_argument("--force", action="store_true", help="overwrite files of the same names")


def init(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``init [DIR] [--force]``: copy the examples; a file of the same name with other contents stops it (exit 2,
    nothing written) unless ``--force``."""
    try:
        copied = copy_examples(args.dir, overwrite=args.force)
    except FileExistsError as exc:
        raise UsageError(f"{exc} (--force overwrites them)") from None
    for path in copied.written:
        print(f"wrote {path}")
    if copied.unchanged:
        print(f"already there: {', '.join(str(p.relative_to(args.dir)) for p in copied.unchanged)}")
    example = args.dir / "arm2.yaml"
    print(f"next: edit {example} (bus, joints), then: rmd-motion status --config {example}")
    program = args.dir / "programs" / "arm2.yaml"
    print(f"a program, in simulated time first: rmd-motion run --config {example} --emulate {program}")
    return EXIT_OK
