"""Could any threshold see 15 % of the peak within 5 cycles on a heavy joint moving in position mode? (issue 30)

Each of the example's heavy joints moved alone (to 80 % of its range, to the other side and back, at full speed) in
position mode, with the collision check running but held off (thresholds of 10⁹ N·m, the following error at 90 deg),
nothing touching the arm, on the example's drives as configured and with every joint's drive at two corners of the
stated bounds (loop tuning twice the factory's with the torque constant −20 %, rotor inertia +30 %, friction +50 %;
half the factory's with +20 %, −30 %, −50 %). Per run it prints the largest |collision signal| (the residual's change
over the window) against 15 % of the joint's peak torque, and the same after taking away the best least-squares fit
of the drive's linear response to the 0xA4 steps: the signal's regression, over the whole run, on the reference's
``M (k v)`` and ``M a`` (``M``: the joint's row of the mass matrix, ``k``: the tracking model's angle-loop gain, ``v``,
``a``: every joint's reference), filtered and differenced over the window as the residual is. The fit uses what no
detector knows in advance (the whole run's clean signal, this drive's own coefficients): where even its residue is
above 15 % of the peak, no threshold on this signal tells that drive's clean move from a contact of that size.

    .venv/bin/python bench/position_reach.py                 # arm6_v3.yaml
    .venv/bin/python bench/position_reach.py arm6.yaml
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.calibrate_examples import CORNERS
from motion.api import Arm
from motion.config import ArmConfig, load_config
from tests.collision_trials import STEP_SHARE, with_thresholds
from tests.drive_models import DriveDraw, JointDraw, with_drives

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: The example's drives, and two of bench/calibrate_examples.py's corners.
DRIVES: dict[str, JointDraw | None] = {"configured": None, "tuning x2": CORNERS[0], "tuning x0.5": CORNERS[3]}
HEAVY = ("shoulder_pitch", "elbow_pitch")
SHARE = 0.8


def record(config: ArmConfig, joint: int) -> tuple[np.ndarray, np.ndarray]:
    """The joint alone out, to the other side and back: per armed cycle its signal, and the two regressors (filtered,
    differenced over the window)."""
    rows: list[tuple[float, float, float]] = []
    spec = config.joints[joint]
    with Arm(config, emulate=True) as arm:
        watchdog, controller = arm.supervisor.watchdog, arm.controller  # type: ignore[union-attr]
        assert controller is not None and watchdog is not None
        observer = watchdog.collision.observer
        gain = controller.tracking.angle_gain_per_s.copy()

        def cycle(*_: object) -> None:
            mass = observer.mass_kgm2[joint]
            speed = np.radians(controller.reference.velocity)
            acceleration = np.radians(controller.reference.acceleration)
            signal = float(watchdog.collision_signal_nm[joint]) if watchdog.collision_armed else np.nan
            rows.append((signal, float(mass @ (gain * speed)), float(mass @ acceleration)))

        controller.cycle_hooks.append(cycle)
        for target in (SHARE * spec.position_max_deg, SHARE * spec.position_min_deg, 0.0):
            arm.move_to({spec.name: target})
        period = controller.period_s
    table = np.array(rows)
    share = min(config.safety.collision_observer_gain_per_s * period, 1.0)
    filtered = np.zeros_like(table[:, 1:])
    for i in range(1, len(table)):
        filtered[i] = filtered[i - 1] + share * (table[i, 1:] - filtered[i - 1])
    span = round(config.safety.collision_window_s / period)
    change = np.zeros_like(filtered)
    change[span:] = filtered[span:] - filtered[:-span]
    armed = ~np.isnan(table[:, 0])
    return table[armed, 0], change[armed]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("example", nargs="?", default="arm6_v3.yaml", help="example configuration (configs/)")
    args = parser.parse_args()
    logging.disable(logging.CRITICAL)
    loaded = load_config(CONFIGS / args.example)
    loaded = dataclasses.replace(loaded, safety=dataclasses.replace(loaded.safety, following_error_deg=90.0))
    held_off = with_thresholds(loaded, [1e9] * len(loaded.joints))
    names = [j.name for j in loaded.joints]
    print(f"{args.example}, position mode at {loaded.control.rate_hz:g} Hz, each joint alone at full speed\n")
    print("| drives | joint | 15 % of peak, N·m | largest |signal| | after the best linear fit | fit (k v, a) |")
    print("|---|---|---:|---:|---:|---|")
    for label, corner in DRIVES.items():
        config = held_off if corner is None else with_drives(held_off, DriveDraw((corner,) * len(names)))
        for name in HEAVY:
            joint = names.index(name)
            signal, change = record(config, joint)
            beta, *_ = np.linalg.lstsq(change, signal, rcond=None)
            residue = signal - change @ beta
            collision = STEP_SHARE * config.joints[joint].peak_torque_nm
            print(
                f"| {label} | {name} | {collision:.2f} | {np.abs(signal).max():.2f} | {np.abs(residue).max():.2f} "
                f"| {beta[0]:.3f}, {beta[1]:.3f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
