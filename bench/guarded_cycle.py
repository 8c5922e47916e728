"""Host work of one guarded cycle, beyond the bus exchange: what the rate check times at connect (issues 11 and 12).

`cycle_bench.py` part 1 times the controller's cycle on a loopback bus; the loop really runs the safety supervisor's
guarded cycle, which adds the watchdog (every monitor, the lag-aware following error and the collision observer with
Pinocchio's crba and Coriolis matrix). This times both halves on the example arms, connected to emulated drives in
simulated time, each on the replies of one real cycle-shaped exchange, with nothing sent:

- `Controller.rehearse`: reference sample, set-points (torque mode: PD + feed-forward), absorb, tracking model,
  snapshot;
- `Watchdog.rehearse`: the above plus the set-point check and every monitor of the watchdog.

    .venv/bin/python bench/guarded_cycle.py [--cycles 3000]

Prints a Markdown table of p50 / p99 in µs and the watchdog's share (the difference of the two).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from motion.api import Arm  # noqa: E402
from motion.compose import rehearsal_watchdog  # noqa: E402
from motion.config import load_config_or_example  # noqa: E402
from motion.config.schema import ControlMode  # noqa: E402
from motion.protocol import Bare, Command  # noqa: E402
from motion.transport.base import Request  # noqa: E402
from tests.motion_rig import arm_config  # noqa: E402

CASES = (("arm2.yaml", ControlMode.POSITION), ("arm2.yaml", ControlMode.TORQUE), ("arm6.yaml", ControlMode.POSITION))


def _times_us(work, replies, start_s: float, period_s: float, cycles: int) -> np.ndarray:  # type: ignore[no-untyped-def]
    samples = np.empty(cycles)
    t = start_s
    for k in range(cycles):
        t += period_s
        t0 = time.perf_counter_ns()
        work(replies, t)
        samples[k] = time.perf_counter_ns() - t0
    return samples / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=3000, help="timed rehearsals per case (default 3000)")
    args = parser.parse_args()
    print("| arm | mode | joints | controller p50 / p99 | guarded (with watchdog) p50 / p99 | watchdog p50 |")
    print("|---|---|---:|---:|---:|---:|")
    for name, mode in CASES:
        config = arm_config(name, mode=mode) if name != "arm6.yaml" else load_config_or_example(name)
        with Arm(config, emulate=True) as arm:
            controller = arm.controller
            assert controller is not None
            watchdog = rehearsal_watchdog(config, controller)
            reads = [Request(i, Bare(Command.READ_STATUS_2)) for i in controller.ids]
            replies = controller.bus.transact(reads, controller.clock.now() + 0.1)
            period, now = controller.period_s, controller.clock.now()
            _times_us(watchdog.rehearse, replies, now, period, 200)  # warm up
            alone = _times_us(controller.rehearse, replies, now, period, args.cycles)
            guarded = _times_us(watchdog.rehearse, replies, now + args.cycles * period, period, args.cycles)
        a50, a99, g50, g99 = (float(np.percentile(x, p)) for x in (alone, guarded) for p in (50, 99))
        print(
            f"| {name} | {mode.value} | {len(config.joints)} | {a50:.0f} / {a99:.0f} | {g50:.0f} / {g99:.0f} "
            f"| {g50 - a50:.0f} |"
        )


if __name__ == "__main__":
    main()
