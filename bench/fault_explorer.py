"""Run the fault-schedule explorer (issue 29) over many seeded schedules; print the count and every violation.

    .venv/bin/python bench/fault_explorer.py --count 10000 --jobs 2
    .venv/bin/python bench/fault_explorer.py --count 200 --seed 7 --no-shrink

Schedule ``k`` of a run is drawn from its own generator (``tests.fault_explorer.drawn``): a schedule is reproduced
alone with ``--first k --count 1``, whatever ``--jobs``. Each violation is printed with its schedule, shrunk to its
smallest failing form (unless ``--no-shrink``), as the literal to add to ``tests/test_halted.py``'s ``REGRESSIONS``.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests import fault_explorer  # noqa: E402 - after the path


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
    began = time.perf_counter()
    failed: list[fault_explorer.Outcome] = []
    cycles = 0
    kinds: collections.Counter[str] = collections.Counter()
    outcomes = fault_explorer.explore(
        args.seed, args.count, first=args.first, jobs=args.jobs, shrinking=not args.no_shrink
    )
    for done, outcome in enumerate(outcomes, 1):
        cycles += outcome.cycles
        schedule = outcome.schedule
        kinds[f"{schedule.arm} {schedule.policy.value} {schedule.mode.value}"] += 1
        if outcome.violations:
            failed.append(outcome)
            print(f"{len(outcome.violations)} violation(s)\n  {schedule.describe()}", flush=True)
            for violation in outcome.violations:
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
