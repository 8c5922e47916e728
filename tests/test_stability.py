"""Torque mode's PD against the loop it runs in: the discrete-time gain margin (motion.control.stability), checked by
``check --offline``, at connect and by the rate check, and gains from a bandwidth."""

from __future__ import annotations

import dataclasses
import json
import math
import random
from pathlib import Path

import numpy as np
import pytest

from motion import Arm, MotionFault
from motion.cli import main
from motion.compose import torque_loops, torque_stability, with_bandwidth_gains
from motion.config import ArmConfig, load_config, load_config_or_example
from motion.config.schema import ControlMode
from motion.control.ratecheck import RateCheck, RateError, stable_floor_hz
from motion.control.stability import (
    MASS_LOW,
    REQUIRED_MARGIN,
    ROTOR_INERTIA_LOW,
    LoopBounds,
    StabilityError,
    gain_margin,
    lowest_rate_hz,
)
from motion.errors import ConfigError
from tests.drive_models import DriveDraw, JointDraw, draw_drives, with_drives
from tests.motion_rig import CONFIGS

ARM2 = load_config_or_example("arm2.yaml")


def at_rate(config: ArmConfig, rate_hz: float, mode: ControlMode = ControlMode.TORQUE) -> ArmConfig:
    return dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=rate_hz, mode=mode))


def _simulated_growth(kp_nm_per_deg: float, kd_nm_per_dps: float, inertia: float, rate_hz: float) -> float:
    """An independent oracle: the sampled loop integrated in small steps (semi-implicit Euler, the current loop as a
    first-order lag, the torque of each sample applied one period plus the latency later and held), from a 1 rad
    offset; the amplitude of the last second over the first's."""
    bounds = LoopBounds()
    period = 1.0 / rate_hz
    dt = period / 200.0
    kp, kd = math.degrees(kp_nm_per_deg), math.degrees(kd_nm_per_dps)
    q, v, tau = 1.0, 0.0, 0.0
    pending: list[tuple[float, float]] = []  # (time it takes effect, command)
    command, next_sample, t = 0.0, 0.0, 0.0
    early, late = 0.0, 0.0
    horizon = max(4.0, 400 * period)
    while t < horizon:
        if t >= next_sample - 1e-12:
            pending.append((next_sample + period + bounds.latency_s, -bounds.torque_constant_high * (kp * q + kd * v)))
            next_sample += period
        while pending and pending[0][0] <= t + 1e-12:
            command = pending.pop(0)[1]
        tau += (command - tau) * (1.0 - math.exp(-dt / bounds.current_loop_s))
        v += tau / inertia * dt
        q += v * dt
        t += dt
        if t < 1.0:
            early = max(early, abs(q))
        elif t > horizon - 1.0:
            late = max(late, abs(q))
    return late / early


@pytest.mark.parametrize(("kp", "kd", "inertia", "rate"), [(0.3, 0.01, 0.0067, 200.0), (0.5, 0.02, 0.068, 60.0)])
def test_the_margin_is_where_an_independently_integrated_loop_turns_from_decaying_to_growing(
    kp: float, kd: float, inertia: float, rate: float
) -> None:
    margin = gain_margin(kp, kd, inertia, rate)
    assert 0.5 < margin < 20.0
    assert _simulated_growth(0.9 * margin * kp, 0.9 * margin * kd, inertia, rate) < 1.0
    assert _simulated_growth(1.1 * margin * kp, 1.1 * margin * kd, inertia, rate) > 1.0


def test_the_margin_falls_with_the_rate_and_the_lowest_rate_is_where_it_meets_the_requirement() -> None:
    margins = [gain_margin(0.3, 0.01, 0.0067, r) for r in (60.0, 125.0, 250.0, 500.0)]
    assert margins == sorted(margins)
    (elbow,) = [loop for loop in torque_loops(ARM2) if loop.name == "elbow"]
    lowest = lowest_rate_hz(elbow)
    m = elbow.kp_nm_per_deg, elbow.kd_nm_per_dps, elbow.inertia_low_kgm2
    assert gain_margin(*m, lowest) >= REQUIRED_MARGIN > gain_margin(*m, lowest * 0.98)
    assert gain_margin(0.0, 0.0, 0.01, 10.0) == math.inf  # no feedback: nothing to make unstable
    with pytest.raises(ValueError, match="inertia"):
        gain_margin(0.3, 0.01, 0.0, 100.0)


def test_the_inertia_envelope_takes_the_coupling_and_the_stated_bounds() -> None:
    shoulder, elbow = torque_loops(ARM2)
    # the elbow's diagonal is the same at every pose (forearm about its joint + rotor); with the shoulder free to move
    # it sees far less, and the bounds take the masses and the rotor lower still
    rotor = ARM2.joints[1].rotor_inertia_kgm2 * 81
    diagonal = 0.0052083 + 1.0 * 0.125**2
    assert elbow.inertia_high_kgm2 == pytest.approx(diagonal + rotor, rel=1e-6)
    assert elbow.inertia_low_kgm2 < MASS_LOW * diagonal + ROTOR_INERTIA_LOW * rotor
    assert 0.0 < elbow.inertia_low_kgm2 < 0.5 * elbow.inertia_high_kgm2
    assert shoulder.inertia_low_kgm2 < shoulder.inertia_high_kgm2


def test_a_torque_arm_at_a_rate_its_gains_do_not_hold_is_refused_before_anything_opens() -> None:
    # arm2 at 40 Hz in torque mode drove the elbow to six times its velocity limit and 200 deg past its limit
    with pytest.raises(StabilityError) as refused:
        Arm(at_rate(ARM2, 40.0), emulate=True).connect()
    text = str(refused.value)
    assert "elbow: gain margin 0.00 at 40 Hz" in text and "shoulder: gain margin" in text
    assert "the lowest rate at which every joint's gains hold is 143 Hz" in text
    assert isinstance(refused.value, ConfigError) and refused.value.key_path == "control.rate_hz"
    # position mode at the same rate: the drives close the loop, the host's gains are not used
    with Arm(at_rate(ARM2, 40.0, ControlMode.POSITION), emulate=True) as arm:
        assert arm.status().state == "ready"


@pytest.mark.parametrize("corner", [1.2, 0.8])
def test_an_accepted_rate_holds_the_arm_on_drives_at_the_bounds(corner: float) -> None:
    # at the lowest rate the check accepts, drives at the stated bounds' corner (torque constant and rotor inertia)
    # with a latency of 1 ms: the example move ends without a fault and the arm comes to rest near its target (a
    # torque constant 20 % off leaves the PD 20 % of the gravity feed-forward to carry: a steady error, not a swing)
    report = torque_stability(ARM2)
    rate = stable_floor_hz(report.lowest_rate_hz)
    draw = DriveDraw(tuple(JointDraw(torque_constant=corner, inertia=0.7) for _ in ARM2.joints), latency_s=0.001)
    config = with_drives(at_rate(ARM2, rate), draw)
    with Arm(config, emulate=True) as arm:
        arm.move_to({"shoulder": 30.0, "elbow": -45.0}, speed_scale=1.0)
        arm.sleep(0.5)
        status = arm.status()
        assert status.state == "ready" and status.fault is None
        assert np.allclose([j.position_deg for j in status.joints], [30.0, -45.0], atol=3.0)
        assert all(abs(j.velocity_dps) < 1.0 for j in status.joints)


def test_the_rate_check_never_recommends_a_rate_below_the_loops_floor() -> None:
    check = RateCheck(
        rate_hz=200.0, reply_budget=0.8, margin=1.5, round_trip_p99_s=0.004, host_p99_s=0.0005, samples=100,
        simulated=False, stable_from_hz=180.0,
    )  # fmt: skip
    assert check.highest_rate_hz == 130.0 and check.recommended_rate_hz == 0.0 and not check.holds
    text = str(RateError("arm.yaml", check))
    assert "200 Hz cannot be held, and no rate this host and bus hold keeps torque mode's PD loop stable" in text
    assert "hold up to 130 Hz" in text and "at least 180.0 Hz" in text
    fast = dataclasses.replace(check, round_trip_p99_s=0.001, host_p99_s=0.0001, rate_hz=150.0)
    assert fast.recommended_rate_hz >= 180.0 and not fast.holds
    assert "150 Hz is below the rate torque mode's PD loop needs" in str(RateError("arm.yaml", fast))
    assert dataclasses.replace(fast, rate_hz=200.0).holds
    assert stable_floor_hz(174.2) == 175.0 and stable_floor_hz(math.nan) == math.inf


def test_the_simulated_connect_reports_the_floor() -> None:
    with Arm(at_rate(ARM2, 250.0), emulate=True) as arm:
        assert arm.rate_check is not None
        lowest = torque_stability(ARM2).lowest_rate_hz
        assert arm.rate_check.stable_from_hz == lowest and 142.0 < lowest < 144.0
        assert f"the torque loop's gains need at least {lowest:.1f} Hz" in arm.rate_check.summary()


def test_check_offline_prints_each_joints_margin_and_refuses_a_torque_arm_without_one(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code = main(["check", "--config", "arm2.yaml", "--offline"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "torque mode's PD loop at 500 Hz" in out and "rates its gains allow: 143 Hz and up" in out
    assert "elbow     3.02    143 Hz" in out
    slow = tmp_path / "arm2.yaml"
    slow.write_text((CONFIGS / "arm2.yaml").read_text().replace("rate_hz: 500", "rate_hz: 60"))
    code = main(["check", "--config", str(slow), "--offline", "--json"])
    out, err = capsys.readouterr()
    assert code == 2
    report = json.loads(out)
    assert report["stability"]["in_use"] and report["stability"]["lowest_rate_hz"] == pytest.approx(143, abs=1)
    assert report["stability"]["joints"]["elbow"]["margin"] < 1.0
    assert any("elbow: gain margin" in e for e in report["errors"])
    # position mode: the same figures, for information only
    code = main(["check", "--config", "arm6.yaml", "--offline"])
    out, err = capsys.readouterr()
    assert code == 0 and "torque mode's PD loop (not in use: position mode) at 250 Hz" in out


def test_every_example_in_torque_mode_holds_its_margin_at_its_own_rate() -> None:
    for name in ("arm2.yaml", "arm2_rs485.yaml", "arm6.yaml", "arm6_v3.yaml", "bimanual.yaml"):
        report = torque_stability(load_config_or_example(name))
        assert not report.failing, f"{name}: {report.describe_failing()}"


def _with_bandwidth(tmp_path: Path, extra: str) -> Path:
    text = (CONFIGS / "arm2.yaml").read_text()
    text = text.replace("    kp_nm_per_deg: 0.3\n    kd_nm_per_dps: 0.01\n", extra)
    path = tmp_path / "arm2.yaml"
    path.write_text(text)
    (tmp_path / "arm6.urdf").write_text("")  # (arm2's model is a chain: nothing else to copy)
    return path


def test_gains_from_a_bandwidth_are_critically_damped_at_the_heaviest_pose_and_checked_like_any(
    tmp_path: Path,
) -> None:
    config = with_bandwidth_gains(load_config(_with_bandwidth(tmp_path, "    bandwidth_hz: 3.0\n")))
    elbow = config.joints[1]
    heaviest = torque_loops(config)[1].inertia_high_kgm2
    omega = 2 * math.pi * 3.0
    assert math.degrees(elbow.kp_nm_per_deg) == pytest.approx(heaviest * omega**2)
    assert math.degrees(elbow.kd_nm_per_dps) == pytest.approx(2 * heaviest * omega)
    assert not torque_stability(config).failing
    fast = with_bandwidth_gains(load_config(_with_bandwidth(tmp_path, "    bandwidth_hz: 40.0\n")))
    with pytest.raises(StabilityError, match="elbow: gain margin"):
        Arm(fast, emulate=True).connect()
    with pytest.raises(ConfigError, match="give either bandwidth_hz or both gains"):
        load_config(_with_bandwidth(tmp_path, "    bandwidth_hz: 3.0\n    kp_nm_per_deg: 0.3\n"))
    with pytest.raises(ConfigError, match="bandwidth_hz"):
        load_config(_with_bandwidth(tmp_path, "    bandwidth_hz: -1\n"))


@pytest.mark.parametrize("seed", range(6))
def test_no_accepted_rate_diverges_on_drawn_drives(seed: int) -> None:
    # drawn drives (tuning, torque constant, rotor inertia, friction, latency) at a drawn rate from 10 Hz up: a rate
    # the check accepts moves the arm without a joint ever reaching 1.5 times its velocity limit; one it refuses is
    # refused before anything opens
    rng = random.Random(5000 + seed)
    name, highest_hz = rng.choice((("arm2.yaml", 500.0), ("arm6_v3.yaml", 160.0)))  # (what the simulated bus holds)
    base = load_config_or_example(name)
    rate = float(round(10 ** rng.uniform(1.0, math.log10(highest_hz))))
    config = with_drives(at_rate(base, rate), draw_drives(rng, len(base.joints)))
    if torque_stability(config).failing:
        with pytest.raises(StabilityError):
            Arm(config, emulate=True).connect()
        return
    limits = np.array([j.velocity_limit_dps for j in config.joints])
    peak = np.zeros(len(limits))

    def watch(controller, _now, _replies) -> None:
        np.maximum(peak, np.abs(controller.axes.qd_dps) / limits, out=peak)

    with Arm(config, emulate=True) as arm:
        assert arm.controller is not None
        arm.controller.cycle_hooks.append(watch)
        target = {j.name: 0.3 * rng.uniform(j.position_min_deg, j.position_max_deg) for j in config.joints}
        try:
            arm.move_to(target, speed_scale=rng.uniform(0.3, 1.0))
            arm.sleep(0.5)
        except MotionFault:  # (a fault halts the arm: what matters here is that nothing diverged first)
            pass
    assert peak.max() < 1.5, f"{config.name} at {rate:g} Hz: peak speed {peak.max():.2f} x the velocity limit"
