"""Run the fault-schedule explorer (issue 29) over many seeded schedules; print the count and every violation.

    .venv/bin/python bench/fault_explorer.py --count 10000 --jobs 2
    .venv/bin/python bench/fault_explorer.py --count 200 --seed 7 --no-shrink

Schedule ``k`` of a run is drawn from ``random.Random(seed * 1_000_003 + k)``: a schedule is reproduced alone with
``--first k --count 1``, whatever ``--jobs``. Each violation is printed with its schedule, shrunk to its smallest
failing form (unless ``--no-shrink``), as the literal to add to ``tests/test_halted.py``'s ``REGRESSIONS``.
"""

from __future__ import annotations

import argparse
import collections
import logging
import multiprocessing
import random
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests import fault_explorer  # noqa: E402 - after the path


def _one(args: tuple[int, int, bool]) -> tuple[int, str, list[str], int, str]:
    seed, k, do_shrink = args
    logging.disable(logging.CRITICAL)
    schedule = fault_explorer.draw(random.Random(seed * 1_000_003 + k))
    outcome = fault_explorer.run(schedule)
    if outcome.violations and do_shrink:
        smallest = fault_explorer.shrink(schedule, fault_explorer.fails_like(outcome.kinds))
        outcome = fault_explorer.run(smallest)
    described = f"{schedule.arm} {schedule.policy.value} {schedule.mode.value}"
    return k, outcome.schedule.describe(), outcome.violations, outcome.cycles, described


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=1000, help="schedules to run (default 1000)")
    parser.add_argument("--first", type=int, default=0, help="index of the first schedule (default 0)")
    parser.add_argument("--seed", type=int, default=29, help="seed of the draw (default 29)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--no-shrink", action="store_true", help="print failing schedules as drawn")
    args = parser.parse_args()
    if args.count < 1 or args.jobs < 1 or args.first < 0:
        parser.error("--count and --jobs must be >= 1, --first >= 0")
    work = [(args.seed, k, not args.no_shrink) for k in range(args.first, args.first + args.count)]
    began = time.perf_counter()
    failed: list[tuple[int, str, list[str]]] = []
    cycles = 0
    kinds: collections.Counter[str] = collections.Counter()
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for done, (k, schedule, violations, n, described) in enumerate(pool.imap_unordered(_one, work), 1):
            cycles += n
            kinds[described] += 1
            if violations:
                failed.append((k, schedule, violations))
                print(f"schedule {k}: {len(violations)} violation(s)\n  {schedule}", flush=True)
                for violation in violations:
                    print(f"    {violation}", flush=True)
            if done % 100 == 0:
                elapsed = time.perf_counter() - began
                print(f"... {done}/{args.count} schedules, {len(failed)} failing, {elapsed:.0f} s", file=sys.stderr)
    elapsed = time.perf_counter() - began
    print(
        f"\n{args.count} schedules (seed {args.seed}, first {args.first}), {cycles} control cycles checked, "
        f"{elapsed:.0f} s with {args.jobs} worker(s): {len(failed)} with violations"
    )
    print("\n| arm, policy, mode | schedules |\n|---|---|")
    for described, count in sorted(kinds.items()):
        print(f"| {described} | {count} |")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
