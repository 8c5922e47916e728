"""Clean paths on drawn drives (issue 30): nothing touches the arm, so any fault is a false one.

A :class:`Case` is an example arm in a control mode at a rate, emulated drives drawn by :mod:`tests.drive_models`
(loop tuning, torque constant, rotor inertia, friction, reply latency and its jitter, the generation the example
speaks), and a clean path: moves and waypoint follows to poses well inside the limits at drawn speed scales, each
from where the last one ended. :func:`run` plays it in simulated time with the configuration's own thresholds and
returns any fault and the worst ratios of the collision signal to the threshold in force, of the following error
to the limit in force and of the measured speed to the overspeed limit. Seeded and reproducible (:func:`drawn`): case
``k`` of seed ``s`` is drawn alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import multiprocessing
import random
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from motion import Arm
from motion.api import MotionHandle
from motion.cli.collision import propose
from motion.config import ArmConfig, load_config
from motion.config.schema import ControlMode, SafetyConfig, link_timeout_problem
from motion.control.ratecheck import RateError
from motion.control.stability import StabilityError
from motion.emulator.timing import TimingModel
from motion.errors import MotionFault
from tests.collision_trials import Trial, collision_trial, nominal_run, with_thresholds, without_thresholds
from tests.drive_models import DriveDraw, draw_drives, with_drives
from tests.fault_explorer import target_pose

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
#: The arms swept (those with collision thresholds, and arm2 for the following error), and the rates drawn for each
#: in position mode (torque mode runs at the example's own rate).
ARMS: dict[str, tuple[float, ...]] = {
    "arm6.yaml": (125.0, 250.0),
    "arm6_v3.yaml": (62.5, 125.0),
    "arm2.yaml": (100.0, 250.0, 500.0),
}
#: The lowest rate drawn with ``low_rates`` (:func:`draw`), Hz.
LOWEST_RATE_HZ = 10.0
#: The reply latency's jitter drawn, s (on top of the drawn latency, per reply).
JITTER_RANGE_S = (0.0, 0.0005)
#: How long a case waits for each step of its path, simulated s.
STEP_WAIT_S = 20.0
#: When the collision of :func:`detect` comes, s after its step started (mid-move, or at rest after a short one).
ONSET_RANGE_S = (0.2, 1.2)
#: The collision threshold of every joint with ``bound_only`` (the bound is then the threshold in force), N·m.
BOUND_ONLY_NM = 1e-3
#: The margin of the thresholds :func:`calibrated` proposes (``collision-calibrate --margin``).
CALIBRATION_MARGIN = 1.5
#: The most control cycles a collision of :data:`tests.collision_trials.STEP_SHARE` of the joint's peak torque may
#: take to be detected (issue 30).
DETECTION_CYCLES = 5


@dataclass(frozen=True)
class Case:
    """One clean run: see the module docstring."""

    arm: str
    mode: ControlMode
    rate_hz: float
    drives: DriveDraw
    jitter_s: float
    steps: tuple[tuple[str, float, tuple[tuple[float, ...], ...]], ...]  # (move | follow, speed scale, poses)
    collision: tuple[int, float, float] | None = None  # for detect(): joint, onset s into the first step, sign

    def describe(self) -> str:
        """The case as a Python literal."""
        return (
            f"Case({self.arm!r}, ControlMode.{self.mode.name}, {self.rate_hz!r}, {self.drives.describe()}, "
            f"{self.jitter_s!r}, {self.steps!r}, {self.collision!r})"
        )


@dataclass
class Outcome:
    """What a case showed: the fault (None: none), the worst |signal| / threshold, |following error| / limit and
    |measured speed| / overspeed limit per joint over the cycles the checks ran, and the control cycles run."""

    case: Case
    fault: MotionFault | None = None
    refused: str | None = None  # the rate check refused the case's rate on its drawn drives (nothing moved)
    collision_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    following_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    following_peak_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))  # the largest |following error|
    speed_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cycles: int = 0


@functools.cache
def example(arm: str) -> ArmConfig:
    """The example configuration ``arm`` (loaded once per process: a frozen dataclass)."""
    return load_config(CONFIGS / arm)


def draw(rng: random.Random, *, quick: bool = False, low_rates: bool = False) -> Case:
    """A random clean case (``quick``: a path of one step, a move or a follow of two poses, as the test command's
    sweep runs; else one to three steps of up to three poses; ``low_rates``: the rate drawn log-uniformly from
    :data:`LOWEST_RATE_HZ` up to the arm's highest in :data:`ARMS`, in both modes: a torque-mode rate its gains do not
    hold is refused at connect, which is right; drawn last, so that the other draws are those of the same case
    without it)."""
    arm = rng.choice(sorted(ARMS))
    config = example(arm)
    tuned = all(j.kp_nm_per_deg > 0 for j in config.joints)
    mode = ControlMode.TORQUE if tuned and rng.random() < 0.3 else ControlMode.POSITION
    steps: list[tuple[str, float, tuple[tuple[float, ...], ...]]] = []
    for _ in range(1 if quick else rng.choice((1, 2, 2, 3))):
        scale = round(rng.uniform(0.2, 1.0), 2)
        if rng.random() < 0.5:
            steps.append(("move", scale, (target_pose(rng, config),)))
        else:
            poses = 2 if quick else rng.choice((2, 3))
            steps.append(("follow", scale, tuple(target_pose(rng, config) for _ in range(poses))))
    # the torque-mode gains are tuned for the example's rate (a discrete PD that holds at 125 Hz may not at half)
    rate = config.control.rate_hz if mode is ControlMode.TORQUE else rng.choice(ARMS[arm])
    drives = draw_drives(rng, len(config.joints))
    jitter = round(rng.uniform(*JITTER_RANGE_S), 6)
    collision = (rng.randrange(len(config.joints)), round(rng.uniform(*ONSET_RANGE_S), 3), rng.choice((-1.0, 1.0)))
    if low_rates:
        rate = float(round(10 ** rng.uniform(math.log10(LOWEST_RATE_HZ), math.log10(max(ARMS[arm])))))
    return Case(arm, mode, rate, drives, jitter, tuple(steps), collision)


def drawn(seed: int, k: int, *, quick: bool = False, low_rates: bool = False) -> Case:
    """Case ``k`` of the sweep seeded ``seed`` (each case from its own generator)."""
    return draw(random.Random(f"{seed}:{k}"), quick=quick, low_rates=low_rates)


def config_of(case: Case, *, bound_only: bool = False) -> ArmConfig:
    """The case's configuration: the example at the case's mode and rate, its emulated drives drawn (with
    ``bound_only``, every joint's collision threshold 1 mN·m: the bound is the threshold in force)."""
    config = with_drives(example(case.arm), case.drives)
    control = dataclasses.replace(config.control, mode=case.mode, rate_hz=case.rate_hz)
    config = dataclasses.replace(config, control=control)
    config = _link_timeout_for_rate(config)
    if bound_only and config.collision_watched:
        config = with_thresholds(config, [BOUND_ONLY_NM] * len(config.joints))
    return config


def _link_timeout_for_rate(config: ArmConfig) -> ArmConfig:
    """``config`` with the default communication-loss time where its own is too short for its rate (a rate below the
    one the example's is set for: the default, as a user would)."""
    if link_timeout_problem(config.safety.link_timeout_ms, config.control.rate_hz) is None:
        return config
    return dataclasses.replace(config, safety=dataclasses.replace(config.safety, link_timeout_ms=None))


def _arm(case: Case, config: ArmConfig, *, observe: bool = False) -> Arm:
    """An emulated arm of ``config`` whose drives answer with the case's latency and jitter (not connected;
    ``observe``: the collision observer runs without thresholds)."""
    arm = Arm(config, emulate=True, observe_collisions=observe)
    start = arm._start_simulation

    def started() -> Any:
        transport, clock = start()
        assert arm.simulation is not None
        arm.simulation.timing = TimingModel(case.drives.latency_s, jitter_s=case.jitter_s)
        return transport, clock

    arm._start_simulation = started  # type: ignore[method-assign]
    return arm


def _step(arm: Arm, step: tuple[str, float, tuple[tuple[float, ...], ...]]) -> MotionHandle:
    """Start one step of a path (not waiting for it)."""
    how, scale, poses = step
    targets = [dict(zip(arm.names, pose, strict=True)) for pose in poses]
    if how == "move":
        return arm.move_to(targets[0], speed_scale=scale, wait=False)
    return arm.follow(targets, speed_scale=scale, wait=False)


def calibrated(case: Case, config: ArmConfig) -> ArmConfig:
    """``config`` with thresholds calibrated as ``rmd-motion collision-calibrate --margin`` :data:`CALIBRATION_MARGIN`
    would on the case's own drives: per joint, the bound alone, or the margin times the largest |signal| of its
    first step, clean, whose margin times left the bound."""
    unarmed = without_thresholds(config)

    def motion(arm: Arm) -> MotionHandle:
        return _step(arm, case.steps[0])

    run = nominal_run(unarmed, motion, arm=_arm(case, unarmed, observe=True), margin=CALIBRATION_MARGIN)
    return with_thresholds(config, list(propose(run.beyond_nm, CALIBRATION_MARGIN)))


def detect(case: Case, *, bound_only: bool = False, calibrating: bool = False) -> Trial | None:
    """The case's first step with its collision: :data:`tests.collision_trials.STEP_SHARE` of the joint's peak
    torque, the case's onset after the step started (see :func:`tests.collision_trials.collision_trial`); None for an
    arm without a collision check (no joint has a threshold). ``calibrating``: with thresholds calibrated on the
    case's own drives and step (:func:`calibrated`) instead of the example's."""
    assert case.collision is not None and case.steps
    config = config_of(case, bound_only=bound_only)
    if not config.collision_watched:
        return None
    if calibrating:
        config = calibrated(case, config)
    joint, onset_s, sign = case.collision
    return collision_trial(
        config, lambda arm: _step(arm, case.steps[0]), joint, onset_s, sign=sign, arm=_arm(case, config)
    )


def run(case: Case, *, safety: SafetyConfig | None = None, bound_only: bool = False, watched: bool = True) -> Outcome:
    """Play ``case`` (with ``safety`` instead of the example's, if given; not ``watched``: no collision check); the
    first fault ends it."""
    config = config_of(case, bound_only=bound_only)
    if safety is not None:
        config = _link_timeout_for_rate(dataclasses.replace(config, safety=safety))
    if not watched:
        config = without_thresholds(config)
    n = len(config.joints)
    outcome = Outcome(
        case,
        collision_ratio=np.zeros(n),
        following_ratio=np.zeros(n),
        following_peak_deg=np.zeros(n),
        speed_ratio=np.zeros(n),
    )
    arm = _arm(case, config)
    ratio = np.zeros(n)
    try:
        arm.connect()
    except (RateError, StabilityError) as refused:
        outcome.refused = str(refused)
        arm.close()
        return outcome
    with contextlib.closing(arm):
        supervisor, controller = arm.supervisor, arm.controller
        assert supervisor is not None and controller is not None
        watchdog = supervisor.watchdog

        def watch(*_: object) -> None:
            outcome.cycles += 1
            checked = watchdog.following_limit_deg > 0.0  # (zero until the first check)
            if watchdog.collision_guarding and watchdog.collision_armed:
                np.abs(watchdog.collision_signal_nm, out=ratio)
                np.divide(ratio, watchdog.collision_limit_nm, out=ratio)
                np.fmax(outcome.collision_ratio, ratio, out=outcome.collision_ratio)
            np.divide(watchdog.following_error_deg, watchdog.following_limit_deg, out=ratio, where=checked)
            np.fmax(outcome.following_ratio, ratio, out=outcome.following_ratio, where=checked)
            np.fmax(outcome.following_peak_deg, watchdog.following_error_deg, out=outcome.following_peak_deg)
            np.abs(controller.axes.qd_dps, out=ratio)
            np.divide(ratio, watchdog.overspeed_limit_dps, out=ratio)
            np.fmax(outcome.speed_ratio, ratio, out=outcome.speed_ratio)

        controller.cycle_hooks.append(watch)
        try:
            for step in case.steps:
                _step(arm, step).wait(STEP_WAIT_S)
            arm.sleep(0.3)
        except MotionFault as fault:
            outcome.fault = fault
    return outcome


@dataclass
class Swept:
    """One case of :func:`sweep`, as a worker process sends it back: the outcome (its fault as text: a MotionFault
    does not pickle) and, with ``detecting``, the collision's joint, the cycles it took (None: not isolated) and the
    fault it met."""

    k: int
    outcome: Outcome
    fault: str | None
    detection: tuple[str, int | None, str] | None = None
    calibrated_detection: tuple[str, int | None, str] | None = None  # with thresholds calibrated on its drives


def sweep_one(seed: int, k: int, quick: bool, bound_only: bool, detecting: bool, low_rates: bool = False) -> Swept:
    """Play case ``k`` of the draw ``seed`` (and, with ``detecting``, its first step again with its collision, with
    the example's thresholds and with thresholds calibrated on the case's drives)."""
    logging.disable(logging.CRITICAL)
    case = drawn(seed, k, quick=quick, low_rates=low_rates)
    outcome = run(case, bound_only=bound_only)
    fault, outcome.fault = outcome.fault, None
    swept = Swept(k, outcome, None if fault is None else str(fault))
    if detecting and outcome.refused is None:
        swept.detection = _detected(detect(case, bound_only=bound_only))
        if not bound_only:
            swept.calibrated_detection = _detected(detect(case, calibrating=True))
    return swept


def _detected(trial: Trial | None) -> tuple[str, int | None, str] | None:
    return None if trial is None else (trial.joint, trial.latency_cycles if trial.isolated else None, str(trial.fault))


def _sweep_one(args: tuple[int, int, bool, bool, bool, bool]) -> Swept:
    return sweep_one(*args)


def sweep(
    seed: int,
    count: int,
    *,
    first: int = 0,
    jobs: int = 1,
    quick: bool = False,
    bound_only: bool = False,
    detecting: bool = False,
    low_rates: bool = False,
) -> Iterator[Swept]:
    """Cases ``first .. first + count - 1`` of the draw ``seed`` in ``jobs`` worker processes (1: in this one), each
    as it comes."""
    work = [(seed, k, quick, bound_only, detecting, low_rates) for k in range(first, first + count)]
    if jobs == 1:
        yield from map(_sweep_one, work)
        return
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        yield from pool.imap_unordered(_sweep_one, work)
