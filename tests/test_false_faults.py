"""No false faults on drives we did not tune for (issue 30): the collision check's bound, its parameters in time, the
following-error allowance for drives whose tuning is unknown, and the clean-path sweep's machinery."""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import numpy as np
import pytest

from motion.api import Arm
from motion.config import load_config
from motion.config.schema import ControlMode
from motion.emulator import Fault, InjectedFault
from motion.emulator.timing import TimingModel
from motion.errors import MotionFault
from motion.safety.collision_bound import TERM_ROWS, Window
from tests import clean_sweep
from tests.collision_trials import collision_trial, torque_move, torque_variant, with_thresholds, without_thresholds
from tests.drive_models import DriveDraw, JointDraw, draw_drives

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_false_fault_1_the_collision_signal_stays_below_the_threshold_in_force() -> None:
    # issue 30, false fault 1: arm6, simulated time, nothing touching the arm: move_to then follow faulted
    # "collision base_yaw +0.21 N·m (threshold 0.174)". The observer took the torque at the step's end for the whole
    # step (the rectangle rule): half a step of the torque's rate of change, 0.16 N·m on base_yaw, whose drive rings.
    # (The following error is held off here: base_yaw's ringing is a case of its own, left open in the issue.)
    config = load_config(CONFIGS / "arm6.yaml")
    config = dataclasses.replace(config, safety=dataclasses.replace(config.safety, following_error_deg=20.0))
    peak = np.zeros(len(config.joints))
    with Arm(config, emulate=True) as arm:
        watchdog = arm.supervisor.watchdog  # type: ignore[union-attr]

        def record(*_: object) -> None:
            if watchdog.collision_armed:
                np.fmax(peak, np.abs(watchdog.collision_signal_nm) / watchdog.collision_limit_nm, out=peak)

        arm.controller.cycle_hooks.append(record)  # type: ignore[union-attr]
        arm.move_to({"base_yaw": 40.0, "shoulder_pitch": -30.0})
        arm.follow([{"base_yaw": -20.0}, {"base_yaw": 10.0, "shoulder_pitch": 20.0}])
    assert peak.max() < 1.0, peak


def test_in_torque_mode_the_bound_alone_holds_clean_moves_and_detects_every_collision() -> None:
    # thresholds of 1 mN·m: the threshold in force is the bound; no calibration takes the check below it, and the
    # bound still sees 15 % of a joint's peak torque in the first cycle that can see it
    config = with_thresholds(torque_variant(load_config(CONFIGS / "arm6.yaml")), [1e-3] * 6)
    arm = Arm(config, emulate=True)
    with arm:
        arm.move_to(dict(zip(arm.names, [30.0, -40.0, 60.0, 45.0, -50.0, 90.0], strict=True)))
        arm.move_to(dict.fromkeys(arm.names, 0.0))
        assert arm.supervisor.fault is None  # type: ignore[union-attr]
    for joint in range(len(config.joints)):
        trial = collision_trial(config, torque_move(), joint, 0.5)
        assert trial.isolated and trial.halted, trial
        assert trial.latency_cycles is not None and trial.latency_cycles <= 2, trial


def test_a_configured_threshold_below_the_bound_is_not_the_one_in_force() -> None:
    config = with_thresholds(torque_variant(load_config(CONFIGS / "arm6.yaml")), [1e-3] * 6)
    with Arm(config, emulate=True) as arm:
        arm.move_to({"shoulder_pitch": -30.0, "elbow_pitch": 40.0}, wait=False)
        arm.sleep(0.4)
        watchdog = arm.supervisor.watchdog  # type: ignore[union-attr]
        assert watchdog.collision_armed
        limit = watchdog.collision_limit_nm
        assert (limit > 1e-3).all() and (limit == np.maximum(1e-3, watchdog.collision_bound_nm)).all()
        # ... and it is the one the snapshots publish (the live view plots it against the signal): each cycle's
        # snapshot carries the evaluation of the cycle before, as it does the signal
        seen: list[tuple[np.ndarray, np.ndarray]] = []

        def record(*_: object) -> None:
            snapshot = arm.controller.snapshot  # type: ignore[union-attr]
            seen.append((snapshot.collision_limit_nm.copy(), watchdog.collision_limit_nm.copy()))

        arm.controller.cycle_hooks.append(record)  # type: ignore[union-attr]
        arm.sleep(0.2)
        matched = [
            np.array_equal(seen[k][0], seen[k - 1][1]) or np.array_equal(seen[k][0], seen[k][1])
            for k in range(1, len(seen))
        ]
        assert len(matched) > 10 and all(matched)
        assert len({tuple(published) for published, _ in seen}) > 1  # it moves with the bound


def test_a_v3_drive_tuned_softer_than_the_prior_is_no_following_error() -> None:
    # the V3 drives' loop settings are not read: the model runs its prior, and a drive tuned at half of it lags twice
    # as far (the wrist joints 5-5.3 deg at full speed against following_error_deg 4): the limit in force takes up
    # to that much of the modelled lag on top
    soft = DriveDraw(tuple(JointDraw(0.5) for _ in range(6)))
    path = (
        ("move", 1.0, ((0.0, 0.0, 0.0, 80.0, 60.0, 100.0),)),
        ("move", 1.0, ((0.0, 0.0, 0.0, -80.0, -60.0, -100.0),)),
    )
    outcome = clean_sweep.run(clean_sweep.Case("arm6_v3.yaml", ControlMode.POSITION, 125.0, soft, 0.0, path))
    assert outcome.fault is None
    configured = clean_sweep.example("arm6_v3.yaml").safety.following_error_deg
    assert outcome.following_peak_deg.max() > configured  # beyond the configured limit: the allowance held it
    assert outcome.following_ratio.max() < 1.0


@pytest.mark.parametrize("period_s", [0.004, 0.008])
def test_the_window_spans_its_time_whatever_the_rate_and_late_steps(period_s: float) -> None:
    window = Window(0.032, period_s, 1)
    times = [k * period_s for k in range(20)]
    times[12:] = [t + 2.5 * period_s for t in times[12:]]  # a late step, and every one after it
    for k, t in enumerate(times):
        base = window.push(t, np.array([float(k)]), np.zeros((TERM_ROWS, 1)))
        start = window.times[base]
        assert start <= t - 0.032 + 1e-9 or k * period_s < 0.032 + 1e-9  # the window's start, or the oldest step
        if k * period_s >= 0.032 + period_s:
            assert window.times[(base + 1) % window.size] > t - 0.032  # ... the latest such step


def test_a_late_cycle_is_no_collision_and_no_following_error() -> None:
    # host stalls of 0.3 to 1.4 periods before every third exchange, during the demo's fastest move: the observer
    # steps over the measured interval, the tracking model from the instant the set-points went out
    config = load_config(CONFIGS / "arm6.yaml")
    with Arm(config, emulate=True) as arm:
        controller = arm.controller
        assert controller is not None
        stalls = iter(np.tile([0.3, 0.0, 0.0, 1.4, 0.0, 0.0, 0.8, 0.0, 0.0], 200))

        def stall(*_: object) -> None:
            controller.clock.sleep_until(controller.clock.now() + next(stalls) * controller.period_s)

        controller.cycle_hooks.append(stall)
        try:
            arm.move_to(dict(zip(arm.names, [60.0, -40.0, 70.0, 80.0, -70.0, 120.0], strict=True)))
        except MotionFault as fault:
            pytest.fail(f"a false fault: {fault}")
        assert controller.loop.overruns > 0  # the stalls made cycles late


def test_reply_jitter_is_drawn_reproducibly_within_its_bound() -> None:
    delays = [TimingModel(0.0003, jitter_s=0.0005, seed=4).reply_delay_s() for _ in range(3)]
    assert len(set(delays)) == 1  # a fresh model with the same seed draws the same first delay
    model = TimingModel(0.0003, jitter_s=0.0005, seed=4)
    drawn = [model.reply_delay_s() for _ in range(500)]
    assert min(drawn) >= 0.0003 and max(drawn) <= 0.0008 and max(drawn) - min(drawn) > 0.0004
    with pytest.raises(ValueError, match="jitter"):
        TimingModel(jitter_s=-1.0)


def test_clean_cases_are_drawn_reproducibly_and_see_a_fault() -> None:
    assert clean_sweep.drawn(30, 5) == clean_sweep.drawn(30, 5)
    assert clean_sweep.drawn(30, 5) != clean_sweep.drawn(30, 6)
    # a case the check cannot pass (a following-error limit far below any lag) reports its fault
    case = clean_sweep.Case(
        "arm2.yaml",
        ControlMode.POSITION,
        250.0,
        DriveDraw((JointDraw(), JointDraw())),
        0.0,
        (("move", 1.0, ((40.0, -40.0),)),),
    )
    config = clean_sweep.config_of(case)
    assert config.control.rate_hz == 250.0
    tight = dataclasses.replace(config.safety, following_error_deg=0.01)
    outcome = clean_sweep.run(case, safety=tight)
    assert outcome.fault is not None and outcome.fault.kind == "following_error"


def test_a_blocked_v3_joint_is_caught_as_fast_as_by_the_raw_reference() -> None:
    # the allowance for an unknown tuning never covers the lag a slower joint lost: blocked mid-move, a soft V3 drive's
    # joint faults no later than |reference - measured| crosses the configured limit
    config = clean_sweep.config_of(
        clean_sweep.Case("arm6_v3.yaml", ControlMode.POSITION, 125.0, DriveDraw((JointDraw(0.5),) * 6), 0.0, ())
    )
    config = without_thresholds(config)  # (the collision check sees the block first otherwise)
    limit = config.safety.following_error_deg
    arm = Arm(config, emulate=True, faults=[Fault(InjectedFault.BLOCKED, 6, 0.9)])
    crossed: list[int] = []
    with arm:
        controller = arm.controller
        assert controller is not None and arm.supervisor is not None

        def raw(*_: object) -> None:
            wrist = abs(controller.reference.position[5] - controller.axes.q_deg[5])
            if not crossed and controller.clock.now() > 0.9 and wrist > limit:
                crossed.append(controller.loop.cycles)

        controller.cycle_hooks.append(raw)
        with pytest.raises(MotionFault) as caught:
            arm.move_to({"flange_roll": 150.0}, speed_scale=0.6)
        assert caught.value.kind == "following_error" and caught.value.joint == "flange_roll"
        assert crossed and arm.supervisor.halts[0].cycle <= crossed[0] + 1, (arm.supervisor.halts[0].cycle, crossed)


#: Clean cases of the sweep (seed 30) that faulted at the start of session 14, each for its own reason: base_yaw's
#: drive tuned at the arm's lightest pose rang ±4° stretched out (0, 1, 7: following error), position-mode steps seen
#: in the sampled current and friction at rest (2, 5, 6: collision), the torque-mode model without C(q, q̇) q̇
#: and a slip counted against a swing the joint trailed by a cycle (19, 23: following error); a torque constant 16 %
#: short of the configured one, whose share of the torque asked for the PD's stiffness turns into an offset (151).
FAULTED_BEFORE = (0, 1, 2, 5, 6, 7, 19, 23, 151)


#: The test command's sweep: this many quick cases (a path of one step) of its own draw, in two worker processes;
#: `bench/clean_sweep.py` runs thousands of the full ones (paths of up to three steps).
SWEEP_SEED = 7
SWEEP_CASES = 240


@pytest.mark.parametrize("torque_constant", [0.84, 1.16])
def test_a_torque_mode_joint_on_a_drive_stronger_or_weaker_than_configured_is_no_following_error(
    torque_constant: float,
) -> None:
    # quick case 56 of seed 7: arm6_v3 in torque mode, base_yaw swinging 137 deg stretched out, where its PD is
    # lightly damped. A drive 16 % off the configured torque constant swings past the waypoint by a degree more or
    # less than the model and turns back cycles later or earlier: the slip rule took that for a blocked joint and
    # added the whole modelled lag (6.8 against 6.3 deg; 10.5 against 5.6); the limit now also takes the torque
    # constant's share of the motion the PD makes (its sensitivity), and a joint swinging the other way is moving
    case = clean_sweep.drawn(7, 56, quick=True)
    joints = list(case.drives.joints)
    joints[0] = dataclasses.replace(joints[0], torque_constant=torque_constant)
    case = dataclasses.replace(case, drives=dataclasses.replace(case.drives, joints=tuple(joints)))
    assert case.arm == "arm6_v3.yaml" and case.mode is ControlMode.TORQUE
    outcome = clean_sweep.run(case)
    assert outcome.fault is None, str(outcome.fault)
    assert 0.3 < outcome.following_ratio[0] < 1.0  # base_yaw's following error came close to the limit in force


def test_the_v3_arms_base_in_torque_mode_follows_a_long_path_on_a_drive_within_the_bounds() -> None:
    # case 123 of seed 11 (bench/clean_sweep.py --seed 11 --first 123 --count 1): arm6_v3 at 125 Hz in torque mode,
    # base_yaw's drive 19 % stronger and its rotor 24 % lighter than configured. With gravity alone fed forward, the
    # quartered PD (what 125 Hz allows the folded arm) moved the stretched-out base by itself: 20 deg behind its
    # reference, ringing at about 1 Hz, and the drive's difference from the tracking model grew past the following
    # error's limit (8.44 > 8.42 deg). The example feeds the reference's acceleration forward too: the PD corrects
    # the model's error only, and the base follows within a few degrees.
    case = clean_sweep.drawn(11, 123)
    assert case.arm == "arm6_v3.yaml" and case.mode is ControlMode.TORQUE
    outcome = clean_sweep.run(case)
    assert outcome.refused is None and outcome.cycles > 1000
    assert outcome.fault is None, str(outcome.fault)
    assert outcome.following_ratio[0] < 0.75, outcome.following_ratio


@pytest.mark.parametrize("k", [469, 830, 1506])
def test_arm6_in_torque_mode_follows_long_paths_on_drives_within_the_bounds(k: int) -> None:
    # cases of seed 41 (bench/clean_sweep.py --seed 41 --first K --count 1), arm6 at 250 Hz in torque mode: with
    # gravity alone fed forward, the stretched-out base (469, 1506) and elbow (830) fell behind and rang past the
    # following-error model's limit (7.30 > 5.23, 6.46 > 5.66, 12.27 > 12.26 deg); the example feeds the reference's
    # acceleration forward too, and each joint follows within a few degrees (at most 0.37 of the limit in force)
    case = clean_sweep.drawn(41, k)
    assert case.arm == "arm6.yaml" and case.mode is ControlMode.TORQUE
    outcome = clean_sweep.run(case)
    assert outcome.refused is None and outcome.cycles > 3000
    assert outcome.fault is None, str(outcome.fault)
    assert outcome.following_ratio.max() < 0.6, outcome.following_ratio


def test_a_base_sped_up_by_the_arm_folding_in_is_within_the_torque_mode_allowance() -> None:
    # seed 41's case 1547: arm6_v3 in torque mode, the base on a drive 19 % weak; while the shoulder and elbow fold the
    # arm in at 40-100 deg/s the base (cruising at 108 deg/s) speeds up to 180 deg/s against its PD's braking: the
    # velocity-product torques undamp its deviation (∂(C q̇)/∂q̇ = Ṁ < 0), and it ran 10.54 deg from the model against a
    # limit of 10.48 while the deviation's model took the PD's damping alone
    case = clean_sweep.drawn(41, 1547)
    assert case.arm == "arm6_v3.yaml" and case.mode is ControlMode.TORQUE
    outcome = clean_sweep.run(case)
    assert outcome.refused is None and outcome.cycles > 2000
    assert outcome.fault is None, str(outcome.fault)
    assert outcome.following_ratio.max() < 0.9, outcome.following_ratio
    # the base read 1.5 times its velocity limit: its PD, lightly damped stretched out, rings at the torque constant's
    # share of its torque; within its overspeed limit, which takes that resonance (a flat 20 % margin did not)
    assert outcome.speed_ratio.max() < 0.8, outcome.speed_ratio


#: Low rates of position mode, both generations: 25 Hz, where the other checks hold too (at 10 Hz the older drives'
#: encoders, unwrapped between readings, slip a turn at full speed on a 1:36 or 1:9 joint, and arm6_v3's following
#: error and position limit see the drives' loops overshoot: faults of their own; the speeds stay within the cap).
LOW_RATES = (("arm6_v3.yaml", 25.0), ("arm2.yaml", 25.0), ("arm6.yaml", 25.0))


@pytest.mark.parametrize(("arm", "rate_hz"), LOW_RATES)
def test_position_mode_at_a_low_rate_on_drawn_drives_is_no_overspeed(arm: str, rate_hz: float) -> None:
    # the drive's own loop under the 0xA4 cap, whatever the rate: joints at up to their velocity limit, none beyond
    # its overspeed limit. (The following error and the collision check are held off: at these rates they have false
    # faults of their own, outside this check.)
    config = clean_sweep.example(arm)
    far = tuple(round(j.position_min_deg + 0.7 * (j.position_max_deg - j.position_min_deg), 1) for j in config.joints)
    near = tuple(round(j.position_min_deg + 0.3 * (j.position_max_deg - j.position_min_deg), 1) for j in config.joints)
    safety = dataclasses.replace(config.safety, following_error_deg=1e3)
    fastest = 0.0
    for k in range(3):
        drives = draw_drives(random.Random(f"overspeed {arm} {k}"), len(config.joints))
        steps = (("move", 1.0, (far,)), ("follow", 1.0, (near, far)))
        case = clean_sweep.Case(arm, ControlMode.POSITION, rate_hz, drives, 0.0003, steps)
        outcome = clean_sweep.run(case, safety=safety, watched=False)
        assert outcome.refused is None and outcome.fault is None, (case.describe(), str(outcome.fault))
        assert outcome.speed_ratio.max() < 1.0, outcome.speed_ratio
        fastest = max(fastest, float(outcome.speed_ratio.max()))
    assert fastest > 0.7  # (a joint at 85 % of its velocity limit or more: the margin is 1.2)


@pytest.mark.parametrize("k", [134, 1718, 415])
def test_a_drives_sampling_instant_moving_within_its_loop_step_is_no_collision(k: int) -> None:
    # cases of seed 41 (bench/clean_sweep.py --seed 41 --first K --count 1): arm6's elbow in torque mode (134, 1718)
    # and arm6_v3's in position mode (415) faulted on a one-cycle spike (0.253 > 0.193, 0.245 > 0.225, 4.12 > 3.92
    # N·m): the reply jitter moved the request's arrival across the emulated drive's 0.5 ms loop step, so the state
    # it answered with was sampled that much earlier or later than the cycle before, and the measured momentum's
    # change was off the interval's by the momentum's rate of change times that (the bound's sampling-instant row)
    case = clean_sweep.drawn(41, k)
    outcome = clean_sweep.run(case)
    assert outcome.refused is None and outcome.cycles > 300
    assert outcome.fault is None, str(outcome.fault)
    assert outcome.collision_ratio.max() < 0.95, outcome.collision_ratio


@pytest.mark.timeout(3600)  # (about three minutes on two free cores; a slow host takes ten times that)
def test_the_clean_sweep_of_drawn_drives_and_paths_has_no_false_fault() -> None:
    swept = list(clean_sweep.sweep(SWEEP_SEED, SWEEP_CASES, jobs=2, quick=True))
    faults = [(one.k, one.fault, one.outcome.case.describe()) for one in swept if one.fault is not None]
    assert not faults, faults
    ran = [one.outcome for one in swept if one.outcome.refused is None]
    # the rate check refuses the rates the drawn drives' latencies cannot hold (arm2 at 500 Hz, arm6 at 250 Hz):
    # that is its job, and the rest still covers every arm in both modes at each of its rates
    assert len(ran) >= SWEEP_CASES // 2
    covered = {(o.case.arm, o.case.mode, o.case.rate_hz) for o in ran if o.cycles > 0}
    expected = {(arm, ControlMode.POSITION, rate) for arm, rates in clean_sweep.ARMS.items() for rate in rates}
    assert expected <= covered, expected - covered
    assert {arm for arm, mode, _ in covered if mode is ControlMode.TORQUE} == set(clean_sweep.ARMS)
    worst = max(float(o.collision_ratio.max(initial=0.0)) for o in ran)
    assert 0.0 < worst < 1.0  # the check ran (a signal was seen) and stayed below the threshold in force
    fastest = max(float(o.speed_ratio.max(initial=0.0)) for o in ran)
    assert 0.5 < fastest < 1.0  # joints moved at speed, and none read beyond its overspeed limit


@pytest.mark.parametrize("k", FAULTED_BEFORE)
def test_a_clean_case_that_faulted_before_runs_clean(k: int) -> None:
    outcome = clean_sweep.run(clean_sweep.drawn(30, k))
    assert outcome.refused is None
    assert outcome.fault is None, (k, str(outcome.fault))
    assert outcome.cycles > 0


def test_a_drive_pinned_at_its_current_limit_by_each_step_is_no_collision() -> None:
    # seed 41's case 199: arm6_v3 in position mode at 62.5 Hz, elbow_pitch's drive tuned twice the factory's: each
    # 0xA4 step's push pins its current at the configured limit (10.8 N·m) when the drive samples it, the joint's speed
    # swings 0 to -18 deg/s between samples while it tracks within 0.13 deg; the mean current was anywhere in the
    # limit's span, and the check faulted "collision elbow_pitch +5.11 N·m (threshold 4.09)"
    case = clean_sweep.drawn(41, 199)
    assert case.arm == "arm6_v3.yaml" and case.mode is ControlMode.POSITION and case.rate_hz == 62.5
    config = clean_sweep.config_of(case)
    elbow = [j.name for j in config.joints].index("elbow_pitch")
    arm = clean_sweep._arm(case, config)
    pinned, limits = 0, 0.0
    with arm:
        controller, watchdog = arm.controller, arm.supervisor.watchdog  # type: ignore[union-attr]
        assert controller is not None
        pinned_a = (
            controller.transmission.transmissions[elbow].current_limit_a - controller.families[elbow].current_step_a
        )
        limit_nm = float(controller.tracking.torque_limit_nm[elbow])

        def count(*_: object) -> None:
            nonlocal pinned, limits
            if abs(controller.axes.iq_a[elbow]) >= pinned_a and watchdog.collision_armed:
                pinned += 1
                limits = max(limits, float(watchdog.collision_limit_nm[elbow]))

        controller.cycle_hooks.append(count)
        for step in case.steps:
            clean_sweep._step(arm, step).wait()
        assert arm.supervisor.fault is None  # type: ignore[union-attr]
    assert pinned > 20  # the drive sampled at its limit in many cycles ...
    assert limits > 2 * limit_nm  # ... and the threshold in force then took the limit's span, both ends


def test_a_collision_in_a_drawn_case_is_detected_within_five_cycles() -> None:
    # case 4 of the sweep: arm6, torque mode, drawn drives; 15 % of elbow_pitch's peak torque 0.385 s into its move
    trial = clean_sweep.detect(clean_sweep.drawn(30, 4))
    assert trial is not None and trial.isolated and trial.halted, trial
    assert trial.latency_cycles is not None and trial.latency_cycles <= clean_sweep.DETECTION_CYCLES, trial


def test_a_collision_after_the_moves_last_set_point_is_detected_within_five_cycles() -> None:
    # seed 41's case 197: arm6 in position mode at 250 Hz, 15 % of wrist_pitch's peak torque 1.16 s into a move that
    # has ended by then; the trial waited for the motion to end, so no cycle ran after the onset and the sweep counted
    # it undetected
    case = clean_sweep.drawn(41, 197)
    assert case.arm == "arm6.yaml" and case.mode is ControlMode.POSITION and case.collision is not None
    trial = clean_sweep.detect(case)
    assert trial is not None and trial.isolated and trial.halted, trial
    assert trial.latency_cycles is not None and trial.latency_cycles <= clean_sweep.DETECTION_CYCLES, trial
