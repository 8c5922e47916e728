"""``rmd-motion collision-calibrate``: thresholds for the collision observer from the residuals of a program.

The program runs with the observer on and no threshold armed (the other fault sources stay armed); every cycle's
collision signal (the residual's change over ``safety.collision_window_s``, see :mod:`motion.safety.watchdog`)
is watched against the collision bound of that cycle (:mod:`motion.safety.collision_bound`: what a drive within the
stated model error can show; the threshold in force is never below it). A joint whose signal times ``--margin`` stayed
within the bound in every cycle is proposed ``bound`` (the bound alone in force: the check follows the motion); any
other joint the largest |signal| times ``--margin`` among the cycles where that exceeded the bound (a floor below
which the threshold in force never goes, where this arm's paths need one). The proposal is printed and, with
``--write``, written into a copy of the configuration. Run the arm's real work (its fastest moves) on the real arm: a
floor holds only for motions like the ones it was calibrated on. ``--emulate`` runs the program on the
configuration's emulated drives in simulated time instead.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Final

import numpy as np

from motion.api import Arm
from motion.cli.common import EXIT_OK, Interrupts, Session, add_emulate_flag, add_holding_flag, print_json, print_table
from motion.cli.moves import holding_first, run_program, with_arm
from motion.cli.program import load_program
from motion.config import ArmConfig, write_joint_values
from motion.config.joints import BOUND_ALONE
from motion.config.schema import ControlMode
from motion.errors import MotionError

#: Default margin: proposed threshold = largest |collision signal| × this. On arm6's demo runs, twice the nominal
#: peak stays above what ±20 % torque-constant or friction errors of the drives make of the signal.
DEFAULT_MARGIN: Final = 2.0
HELP: Final = "run a program with the collision observer on and propose per-joint thresholds from its residuals"


def unarmed(config: ArmConfig) -> ArmConfig:
    """``config`` without collision thresholds (nothing can fault on a collision while calibrating)."""
    joints = tuple(j.without_collision_threshold() for j in config.joints)
    return dataclasses.replace(config, joints=joints)


def propose(signal_peak_nm: np.ndarray, margin: float) -> np.ndarray:
    """Thresholds, N·m: ``signal_peak_nm`` (per joint, the largest |signal| of the cycles where ``margin`` times it
    exceeded the bound; 0 where none did) times ``margin``, rounded up to 0.1 mN·m; 0: the bound alone."""
    return np.ceil(np.asarray(signal_peak_nm, dtype=np.float64) * margin * 1e4) / 1e4


def _yaml_threshold(threshold: float) -> float | str:
    return BOUND_ALONE if threshold == 0.0 else threshold


def written_thresholds(config: ArmConfig, thresholds: np.ndarray) -> dict[str, float | str | dict[str, float | str]]:
    """What ``--write`` puts in each joint's ``collision_threshold_nm``: the proposal for the configuration's mode
    (``bound`` for 0), and the other mode's threshold kept where it has one of its own (``{position: N, torque: N}``);
    else one value (both modes: calibrate in the other mode too before running in it)."""
    mode = config.control.mode
    other = ControlMode.POSITION if mode.traits.host_torque else ControlMode.TORQUE  # (the key's other half)
    values: dict[str, float | str | dict[str, float | str]] = {}
    for joint, threshold in zip(config.joints, thresholds, strict=True):
        kept = joint.collision_threshold_in(other)
        if kept is None or kept == float(threshold):
            values[joint.name] = _yaml_threshold(float(threshold))
        else:
            values[joint.name] = {mode.value: _yaml_threshold(float(threshold)), other.value: _yaml_threshold(kept)}
    return values


def _margin_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 1.0):
        raise argparse.ArgumentTypeError(f"{text!r}: the margin must be >= 1")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``collision-calibrate`` (besides the bus options)."""
    parser.add_argument("program", metavar="PROGRAM.yaml")
    parser.add_argument(
        "--margin",
        type=_margin_arg,
        default=DEFAULT_MARGIN,
        metavar="M",
        help=f"threshold = largest |signal| × M (>= 1, default {DEFAULT_MARGIN:g})",
    )
    parser.add_argument("--write", metavar="OUT.yaml", help="write a copy of the configuration with the thresholds")
    add_emulate_flag(parser)
    parser.add_argument(
        "--log", metavar="FILE.mcap", help="record every control cycle as MCAP (Foxglove, rosbags; `rmd-motion plot`)"
    )
    parser.add_argument("--trace", metavar="FILE", help="record every frame on the bus (CAN: candump log)")
    add_holding_flag(parser)
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout (for scripts)")


def calibrate(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``collision-calibrate PROGRAM.yaml``: the program is validated before the bus is opened."""
    session = Session.from_args(args)
    config = session.config
    program = load_program(args.program, config)
    n = len(config.joints)
    peak = np.zeros(n)
    bound = np.zeros(n)  # the largest bound seen: the threshold in force is never below the bound
    beyond = np.zeros(n)  # the largest |signal| of the cycles where the margin times it exceeded the bound
    signal, scaled, over = np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)  # (the hook allocates nothing)

    def body(arm: Arm) -> int:
        supervisor, controller = arm.supervisor, arm.controller
        if supervisor is None or controller is None:
            raise MotionError("the arm did not connect")
        watchdog = supervisor.watchdog

        def record(*_: object) -> None:  # a cycle hook: the signal of the cycle before (NaN ignored)
            if watchdog.collision_armed:
                np.abs(watchdog.collision_signal_nm, out=signal)
                np.fmax(peak, signal, out=peak)
                np.fmax(bound, watchdog.collision_bound_nm, out=bound)
                np.multiply(signal, args.margin, out=scaled)
                np.greater(scaled, watchdog.collision_bound_nm, out=over)
                np.fmax(beyond, signal, out=beyond, where=over)

        holding_first(arm, args)
        controller.cycle_hooks.append(record)
        run_program(arm, program, 1.0)
        arm.sleep(2 * controller.period_s)
        record()
        return EXIT_OK

    with_arm(
        args,
        session,
        interrupts,
        body,
        config=unarmed(config),
        observe_collisions=True,
        emulate=bool(args.emulate),
    )
    thresholds = propose(beyond, args.margin)
    names = config.joint_names
    written = None
    if args.write:
        write_joint_values(config.source, args.write, "collision_threshold_nm", written_thresholds(config, thresholds))
        written = args.write
    if args.json:
        print_json(
            {
                "command": "collision-calibrate",
                "program": program.source,
                "margin": args.margin,
                "joints": [
                    {
                        "name": name,
                        "signal_peak_nm": round(float(peak[i]), 6),
                        "threshold_nm": round(float(thresholds[i]), 6) if thresholds[i] else None,
                        "bound_alone": not thresholds[i],
                        "bound_peak_nm": round(float(bound[i]), 6),
                        "peak_torque_nm": config.joints[i].peak_torque_nm,
                    }
                    for i, name in enumerate(names)
                ],
                "written": written,
            }
        )
        return EXIT_OK
    rows = [
        (
            name,
            f"{peak[i]:.4f}",
            f"{thresholds[i]:.4f}" if thresholds[i] else BOUND_ALONE,
            f"{100 * thresholds[i] / config.joints[i].peak_torque_nm:.1f} %" if thresholds[i] else "",
            f"{bound[i]:.4f}",
        )
        for i, name in enumerate(names)
    ]
    header = ("joint", "largest |signal| N·m", f"threshold N·m (x{args.margin:g})", "of peak torque")
    print_table((*header, "largest bound N·m"), rows)
    print("(in force in every cycle: the bound of what a drive within its model error can show, or the threshold")
    print(" where that is higher; bound: the margin times the signal stayed within the bound; README, How it works)")
    if written:
        print(
            f"wrote {written} (collision_threshold_nm per joint for {config.control.mode.value} mode, the other"
            " mode's kept where it has its own; comments are not copied)"
        )
    return EXIT_OK
