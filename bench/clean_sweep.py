"""Clean paths on drawn drives (issue 30): run many seeded cases of :mod:`tests.clean_sweep` and print the false
faults, the worst collision signal as a share of the threshold in force, the worst following error as a share of its
limit and the fastest measured speed as a share of its overspeed limit, per arm, mode and rate; then each case's first
step again with a collision (15 % of a drawn joint's peak torque at a drawn instant) and the control cycles it took to
detect it.

    .venv/bin/python bench/clean_sweep.py --count 2000 --jobs 2
    .venv/bin/python bench/clean_sweep.py --first 17 --count 1      # case 17 alone, described
    .venv/bin/python bench/clean_sweep.py --count 200 --bound-only  # the bound alone in force

Case ``k`` is drawn from its own generator (``tests.clean_sweep.drawn``), whatever ``--jobs``.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests import clean_sweep
from tests.collision_trials import STEP_SHARE


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=500, help="cases to run (default 500)")
    parser.add_argument("--first", type=int, default=0, help="index of the first case (default 0)")
    parser.add_argument("--seed", type=int, default=30, help="seed of the draw (default 30)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--quick", action="store_true", help="paths of one step, as the test command's sweep")
    parser.add_argument(
        "--bound-only", action="store_true", help="every collision threshold 1 mN·m: the bound is the one in force"
    )
    parser.add_argument(
        "--low-rates", action="store_true", help="rates drawn from 10 Hz up to each arm's highest, in both modes"
    )
    args = parser.parse_args()
    if args.count < 1 or args.jobs < 1 or args.first < 0:
        parser.error("--count and --jobs must be >= 1, --first >= 0")
    began = time.perf_counter()
    faults = refused = late = 0
    latencies: list[int | None] = []
    detections: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0])  # arm and joint: in time, trials
    calibrated_detections: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0])  # ... on its own drives
    cycles = 0
    worst: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0, 0, 0.0])
    worst_case: list[tuple[float, int, str]] = []
    swept = clean_sweep.sweep(
        args.seed,
        args.count,
        first=args.first,
        jobs=args.jobs,
        quick=args.quick,
        bound_only=args.bound_only,
        detecting=True,
        low_rates=args.low_rates,
    )
    for done, one in enumerate(swept, 1):
        k, outcome, fault, detection = one.k, one.outcome, one.fault, one.detection
        if one.calibrated_detection is not None:
            joint, latency, _ = one.calibrated_detection
            tally = calibrated_detections[f"{outcome.case.arm} {outcome.case.mode.value} {joint}"]
            tally[0] += latency is not None and latency <= clean_sweep.DETECTION_CYCLES
            tally[1] += 1
        case = outcome.case
        cycles += outcome.cycles
        key = f"{case.arm} {case.mode.value} {case.rate_hz:g} Hz"
        row = worst[key]
        collision = float(outcome.collision_ratio.max(initial=0.0))
        following = float(outcome.following_ratio.max(initial=0.0))
        row[0], row[1], row[2] = max(row[0], collision), max(row[1], following), row[2] + 1
        row[3] = max(row[3], float(outcome.speed_ratio.max(initial=0.0)))
        worst_case.append((max(collision, following), k, case.describe()))
        if outcome.refused is not None:
            refused += 1
            print(f"case {k}: refused by the rate check ({case.arm}, {case.rate_hz:g} Hz)", flush=True)
            continue
        if detection is not None:  # (None: an arm without a collision check)
            joint, latency, caught = detection
            latencies.append(latency)
            tally = detections[f"{case.arm} {case.mode.value} {joint}"]
            tally[0] += latency is not None and latency <= clean_sweep.DETECTION_CYCLES
            tally[1] += 1
            if latency is None or latency > clean_sweep.DETECTION_CYCLES:
                late += 1
                print(
                    f"case {k} ({key}): a collision on {joint} at {case.collision}: detected in {latency} "
                    f"cycles: {caught}",
                    flush=True,
                )
        if fault is not None or args.count == 1:
            faults += fault is not None
            print(f"case {k}: {fault}\n  {case.describe()}", flush=True)
        if done % 50 == 0:
            print(
                f"... {done}/{args.count} cases, {faults} faults, {time.perf_counter() - began:.0f} s",
                file=sys.stderr,
            )
    elapsed = time.perf_counter() - began
    print(
        f"\n{args.count} cases (seed {args.seed}, first {args.first}), {cycles} control cycles, {elapsed:.0f} s with "
        f"{args.jobs} worker(s): {faults} false faults, {refused} refused by the rate check"
    )
    caught = sorted(x for x in latencies if x is not None)
    if caught:
        print(
            f"collisions of {STEP_SHARE:.0%} of peak torque: {len(caught)} of {len(latencies)} detected (isolated), "
            f"{late} not within {clean_sweep.DETECTION_CYCLES} cycles; cycles to detect: median "
            f"{caught[len(caught) // 2]}, worst {caught[-1]}"
        )
    if detections:
        print(
            f"\n| arm, mode, joint | detected within {clean_sweep.DETECTION_CYCLES} cycles / trials: the example's "
            f"thresholds | calibrated on the case's drives (margin {clean_sweep.CALIBRATION_MARGIN:g}) |"
        )
        print("|---|---|---|")
        for key, (in_time, trials) in sorted(detections.items()):
            mine, theirs = calibrated_detections.get(key, (0, 0))
            print(f"| {key} | {in_time} / {trials} | {mine} / {theirs} |")
    print(
        "\n| arm, mode, rate | cases | worst collision signal / threshold | worst following error / limit "
        "| fastest speed / overspeed limit |"
    )
    print("|---|---|---|---|---|")
    for key, (collision, following, count, speed) in sorted(worst.items()):
        print(f"| {key} | {count} | {collision:.2f} | {following:.2f} | {speed:.2f} |")
    ratio, k, described = max(worst_case)
    print(f"\nclosest to a fault: case {k} ({ratio:.2f}): {described}")
    sys.exit(1 if faults or late else 0)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
