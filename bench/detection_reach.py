"""Where a collision of the clean sweep was not detected in time, was it within the check's reach? (issue 30)

For each case named (``tests.clean_sweep.drawn(seed, k)``), play its first step clean (nothing touches the arm) with
the example's thresholds and, over the control cycles the collision of ``bench/clean_sweep.py`` would have had to be
detected in (its onset and the :data:`tests.clean_sweep.DETECTION_CYCLES` after it), print the smallest threshold in
force on the collided joint as a share of the collision's torque (15 % of the joint's peak), and what the bound's
rows were at that cycle (and the speed field's steps' row, ``2 K_O |M| s``: the field's step ``s`` through
the joint's row of M). A share above 1 in every one of those cycles: the collision was smaller than what a drive
within the stated model error may show on that path at that instant, so no threshold the bound allows could have
caught it then; below 1: the signal's rise or the detector, not the bound, was slow.

    .venv/bin/python bench/detection_reach.py --seed 41 --cases 3,13,17
    .venv/bin/python bench/clean_sweep.py --seed 41 --count 400 --jobs 1 > sweep.txt
    .venv/bin/python bench/detection_reach.py --seed 41 --from-sweep sweep.txt   # every late case of that run
    .venv/bin/python bench/detection_reach.py --seed 41 --from-sweep sweep.txt --detect   # ... and its trial again
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from motion.safety import collision_bound as cb
from tests import clean_sweep
from tests.collision_trials import STEP_SHARE

ROW_NAMES = (
    "torque constant",
    "rotor inertia",
    "friction",
    "sampling",
    "0xA4 steps",
    "rest",
    "phase",
    "instant",
    "saturated",
)
_LATE = re.compile(r"^case (\d+) \(.*\): a collision on ")


def reach(seed: int, k: int) -> str:
    """One case's line (see the module doc)."""
    case = clean_sweep.drawn(seed, k)
    assert case.collision is not None
    joint, onset_s, _ = case.collision
    config = clean_sweep.config_of(case)
    torque = STEP_SHARE * config.joints[joint].peak_torque_nm
    arm = clean_sweep._arm(case, config)
    seen: list[tuple[int, float, float, np.ndarray, float]] = []
    with arm:
        supervisor, controller = arm.supervisor, arm.controller
        assert supervisor is not None and controller is not None
        check = supervisor.watchdog.collision
        bound = check.bound
        if bound is None:
            return f"case {k}: no collision check"

        def hook(*_: object) -> None:
            # (the watchdog evaluates after the hooks: these are the previous cycle's figures)
            seen.append(
                (
                    controller.loop.cycles,
                    float(check.limit_nm[joint]),
                    float(check.signal_nm[joint]),
                    bound.terms[:, joint].copy(),
                    float(bound.field_nm[joint]),
                )
            )

        controller.cycle_hooks.append(hook)
        clean_sweep._step(arm, case.steps[0])
        arm.sleep(onset_s)
        first = controller.loop.next_cycle
        arm.sleep((clean_sweep.DETECTION_CYCLES + 2) * controller.period_s)
        span = [s for s in seen if first < s[0] <= first + clean_sweep.DETECTION_CYCLES + 1]
        qd = controller.reference.velocity[joint]
    if not span:
        return f"case {k}: no cycles after the onset"
    cycle, limit, signal, terms, field = min(span, key=lambda s: s[1])
    rows = ", ".join(f"{name} {value:.3g}" for name, value in zip(ROW_NAMES, terms, strict=True) if abs(value) > 1e-9)
    verdict = "beyond reach" if limit > torque else "within reach"
    return (
        f"case {k} ({case.arm} {case.mode.value} {case.rate_hz:g} Hz, {config.joints[joint].name}): smallest "
        f"threshold in force / collision {limit / torque:.2f} ({limit:.3g} of {torque:.3g} N·m, cycle "
        f"{cycle - first} after the onset; clean signal {signal:.3g}; reference {qd:.0f} deg/s after): {verdict}; "
        f"the speed field's steps' row {field:.3g} N·m; the rows' latest terms: {rows}"
    )


def detected(seed: int, k: int) -> str:
    """The case's collision trial again (``tests.clean_sweep.detect``): the cycles it took to detect, with this code."""
    trial = clean_sweep.detect(clean_sweep.drawn(seed, k))
    if trial is None:
        return "no collision check"
    latency = trial.latency_cycles if trial.isolated else None
    in_time = latency is not None and latency <= clean_sweep.DETECTION_CYCLES
    return f"detected in {latency} cycles ({'in time' if in_time else 'late'}): {trial.fault}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=30, help="seed of the draw (default 30)")
    parser.add_argument("--cases", default="", help="case indices, comma separated")
    parser.add_argument("--from-sweep", type=Path, help="the output of bench/clean_sweep.py: its late cases")
    parser.add_argument("--detect", action="store_true", help="also play each case's collision trial again")
    args = parser.parse_args()
    ks = [int(x) for x in args.cases.split(",") if x.strip()]
    if args.from_sweep is not None:
        for line in args.from_sweep.read_text().splitlines():
            found = _LATE.match(line)
            if found:
                ks.append(int(found.group(1)))
    if not ks:
        parser.error("name cases with --cases or --from-sweep")
    beyond = in_time = 0
    for k in ks:
        line = reach(args.seed, k)
        beyond += "beyond reach" in line
        if args.detect:
            again = detected(args.seed, k)
            in_time += "(in time)" in again
            line += f"\n  again: {again}"
        print(line, flush=True)
    print(f"\n{len(ks)} cases: {beyond} beyond the bound's reach in every cycle of the span, {len(ks) - beyond} not")
    if args.detect:
        print(f"played again: {in_time} detected within {clean_sweep.DETECTION_CYCLES} cycles")
    print(f"(position-mode bound factor {cb.POSITION_MARGIN}, step drift {cb.STEP_DRIFT} of X at each end)")


if __name__ == "__main__":
    np.seterr(all="ignore")
    logging.disable(logging.CRITICAL)
    main()
