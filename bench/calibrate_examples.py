"""The example arms' collision check on drives at the corners of the stated bounds: each joint's largest signal /
bound and what ``rmd-motion collision-calibrate --margin 1.5`` would propose, over the demo's waypoint path (position
mode) and torque move, and each joint alone moved from rest to 80 % of its range, to the other side and back (in both
modes), all at speed scale 1.0, on the example's emulated drives as configured and on four corners of the drive
models the checks must bear (every joint's loop tuning at half or twice the factory's, its torque constant, rotor
inertia and friction at the ends of their stated error: ``tests/drive_models.py``), in simulated time (the same
figures on any host): per joint and control mode, ``bound`` (the collision bound alone in force,
``motion/safety/collision_bound.py``) where 1.5 times the signal stayed within the bound in every cycle, else a floor
of 1.5 times the largest signal that did not. The examples ship ``bound`` on every joint: the signal stays below the
bound on every corner (2026-11-28: at most 0.93, arm6_v3's wrist_roll in position mode), which the margin's proposal
would turn into floors where it passes two thirds of it.

    .venv/bin/python bench/calibrate_examples.py --jobs 2              # print them
    .venv/bin/python bench/calibrate_examples.py --jobs 2 --write      # and write them into configs/
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from motion.api import Arm
from motion.config import ArmConfig, load_config
from motion.config.schema import ControlMode
from tests.collision_trials import demo_path, nominal_run, torque_move, torque_variant, without_thresholds
from tests.drive_models import DriveDraw, JointDraw, with_drives

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
EXAMPLES = ("arm6.yaml", "arm6_v3.yaml")
MARGIN = 1.5
#: The drive models calibrated on besides the configured one: each applied to every joint.
CORNERS = (
    JointDraw(2.0, 0.8, 1.3, 1.5),
    JointDraw(2.0, 1.2, 0.7, 0.5),
    JointDraw(0.5, 0.8, 1.3, 1.5),
    JointDraw(0.5, 1.2, 0.7, 0.5),
)
#: A joint alone goes to this share of its range, to the same share of the other side, and back to 0.
SHARE = 0.8


def _alone(name: str, far_deg: float, other_deg: float) -> Callable[[Arm], object]:
    def motion(arm: Arm) -> object:
        arm.move_to({name: far_deg}, speed_scale=1.0)
        arm.move_to({name: other_deg}, speed_scale=1.0)
        return arm.move_to({name: 0.0}, speed_scale=1.0, wait=False)

    return motion


def peaks(config: ArmConfig) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per control mode, the largest |collision signal| per joint over the calibration motions whose margin times
    left the bound (``{mode}``), the largest signal / bound (``{mode} share``) and the largest |signal| (``{mode}
    signal``: against 15 % of the joint's peak torque, what a collision the check must see within 5 cycles puts in
    it), and any fault they met."""
    position = without_thresholds(config)
    torque = torque_variant(position)
    n = len(config.joints)
    keys = ("position", "torque", "position share", "torque share", "position signal", "torque signal")
    peak = {key: np.zeros(n) for key in keys}
    faults: list[str] = []
    runs = [("position", position, demo_path(1.0)), ("torque", torque, torque_move(1.0))]
    for joint in config.joints:
        motion = _alone(joint.name, SHARE * joint.position_max_deg, SHARE * joint.position_min_deg)
        runs += [("position", position, motion), ("torque", torque, motion)]
    for mode, run_config, motion in runs:
        run = nominal_run(run_config, motion, margin=MARGIN)
        if run.fault is not None:
            faults.append(str(run.fault))
        np.fmax(peak[mode], run.beyond_nm, out=peak[mode])
        np.fmax(peak[f"{mode} share"], run.limit_share_peak, out=peak[f"{mode} share"])
        np.fmax(peak[f"{mode} signal"], run.signal_peak_nm, out=peak[f"{mode} signal"])
    return peak, faults


def _peaks_on(name_corner: tuple[str, int]) -> tuple[str, int, dict[str, np.ndarray], list[str]]:
    """:func:`peaks` of the example ``name`` on its configured drives (corner -1) or on a corner of the models."""
    name, corner = name_corner
    logging.disable(logging.CRITICAL)
    config = load_config(CONFIGS / name)
    if corner >= 0:
        config = with_drives(config, DriveDraw((CORNERS[corner],) * len(config.joints)))
    peak, faults = peaks(config)
    return name, corner, peak, faults


def _yaml(threshold: float) -> str:
    return "bound" if threshold == 0.0 else f"{threshold:.4g}"


def write(path: Path, thresholds: list[tuple[float, float]]) -> None:
    """Replace the file's ``collision_threshold_nm`` values, in joint order, with ``{position: N, torque: N}`` (one
    value where both are the same; ``bound`` for 0)."""
    text = path.read_text()
    values = iter(thresholds)

    def value(match: re.Match[str]) -> str:
        position, torque = next(values)
        if position == torque:
            return f"{match.group(1)}{_yaml(position)}"
        return f"{match.group(1)}{{position: {_yaml(position)}, torque: {_yaml(torque)}}}"

    text, count = re.subn(r"(collision_threshold_nm: )(?:[0-9.]+|bound|\{[^}]*\})", value, text)
    if count != len(thresholds):
        raise SystemExit(f"{path}: {count} collision_threshold_nm keys for {len(thresholds)} joints")
    path.write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help="write the thresholds into the example files")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    args = parser.parse_args()
    work = [(name, corner) for name in EXAMPLES for corner in range(-1, len(CORNERS))]
    found: dict[str, dict[str, np.ndarray]] = {}
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for name, corner, peak, faults in pool.imap_unordered(_peaks_on, work):
            drives = "configured drives" if corner < 0 else f"corner {CORNERS[corner]}"
            shares = f"position {np.round(peak['position share'], 2)}, torque {np.round(peak['torque share'], 2)}"
            print(f"{name}, {drives}: largest signal / bound: {shares}")
            signals = f"position {np.round(peak['position signal'], 2)}, torque {np.round(peak['torque signal'], 2)}"
            print(f"  largest |signal|, N·m: {signals}")
            for fault in faults:
                print(f"  fault on the way: {fault}")
            mine = found.setdefault(name, {key: np.zeros(len(value)) for key, value in peak.items()})
            for key in mine:
                np.fmax(mine[key], peak[key], out=mine[key])
    for name in EXAMPLES:
        path = CONFIGS / name
        config = load_config(path)
        peak = found[name]
        thresholds = [
            (float(f"{MARGIN * p:.4g}"), float(f"{MARGIN * t:.4g}"))
            for p, t in zip(peak["position"], peak["torque"], strict=True)
        ]
        print(f"{name}:")
        for i, joint in enumerate(config.joints):
            print(
                f"  {joint.name}: largest signal / bound {peak['position share'][i]:.2f} in position mode, "
                f"{peak['torque share'][i]:.2f} in torque mode; thresholds {thresholds[i]} (0: bound; were "
                f"{joint.collision_threshold_nm}, {joint.collision_threshold_in(ControlMode.TORQUE)})"
            )
        if args.write:
            write(path, thresholds)


if __name__ == "__main__":
    main()
