"""How much CPU the emulated arms take: CPU seconds per simulated second of each example arm's emulator left at
rest (its drives powered up, holding nothing; a V3 arm's brakes locked), and microseconds per CAN frame timed on the
emulated bus. The real-time emulator (``rmd-motion emulate``) must do this work as the clock runs: on a host busy
with other work it falls behind above about half a CPU.

    .venv/bin/python bench/emulator_speed.py
    PYTHONPATH=OTHER_TREE .venv/bin/python bench/emulator_speed.py     # another version of the code, same host

The best of five half-second runs per arm.
"""

from __future__ import annotations

import os
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path

if not os.environ.get("PYTHONPATH"):  # (PYTHONPATH: another tree's code is measured)
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from motion.config import load_config
from motion.emulator.arm import arm_emulator
from motion.emulator.timing import can_frame_bits
from motion.protocol.table import ProtocolFamily

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ARMS = (("arm2.yaml", ProtocolFamily.V2), ("arm6.yaml", ProtocolFamily.V2), ("arm6_v3.yaml", ProtocolFamily.V3))


def main() -> None:
    import motion

    print(f"code: {Path(motion.__file__).resolve().parent.parent}")
    for name, family in ARMS:
        emulator, _ = arm_emulator(load_config(CONFIGS / name), family=family)
        emulator.advance(0.1)
        best = min(_timed(lambda e=emulator: e.advance(0.5)) for _ in range(5))
        print(f"{name} ({family.value}) at rest: {2.0 * best:.3f} CPU s per simulated s")
    rng = random.Random(1)
    frames = [(rng.randrange(0x800), rng.randbytes(rng.randrange(9))) for _ in range(2000)]
    best = min(_timed(lambda: [can_frame_bits(i, d) for i, d in frames]) for _ in range(5))
    print(f"can_frame_bits: {best / len(frames) * 1e6:.1f} µs per frame")


def _timed(work: Callable[[], object]) -> float:
    start = time.perf_counter()
    work()
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
