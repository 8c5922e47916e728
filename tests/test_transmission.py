"""Joint <-> motor mapping: hand-computed examples, round trips, limiting, vectorised == scalar."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from motion.errors import ConfigError, EncodeError
from motion.protocol.scales import IQ_RAW_LIMIT
from motion.transmission import IQ_LIMIT_A, ArmTransmission, Transmission

finite = st.floats(min_value=-1e5, max_value=1e5, allow_nan=False)
transmissions = st.builds(
    Transmission,
    gear_ratio=st.floats(min_value=0.1, max_value=200),
    direction=st.sampled_from([1, -1]),
    zero_offset_deg=st.floats(min_value=-360, max_value=360),
    torque_constant_nm_per_a=st.floats(min_value=0.01, max_value=5),
    current_limit_a=st.floats(min_value=0.1, max_value=IQ_LIMIT_A),
)

X8 = Transmission(gear_ratio=9, direction=1, zero_offset_deg=10.0, torque_constant_nm_per_a=0.1, current_limit_a=10)
MIRRORED = Transmission(gear_ratio=9, direction=-1, zero_offset_deg=10.0, torque_constant_nm_per_a=0.1)


def test_position_examples() -> None:
    assert X8.joint_deg(900.0) == pytest.approx(110.0)  # 900 / 9 + 10
    assert X8.motor_deg(110.0) == pytest.approx(900.0)
    assert MIRRORED.joint_deg(900.0) == pytest.approx(-90.0)  # -900 / 9 + 10
    assert MIRRORED.motor_deg(-90.0) == pytest.approx(900.0)
    assert MIRRORED.joint_deg(0.0) == 10.0  # the offset is the joint angle at motor zero


def test_rates_have_no_offset() -> None:
    assert X8.joint_rate(900.0) == pytest.approx(100.0)
    assert MIRRORED.joint_rate(900.0) == pytest.approx(-100.0)
    assert MIRRORED.motor_rate(-100.0) == pytest.approx(900.0)
    assert X8.joint_rate(0.0) == 0.0


def test_torque_examples() -> None:
    assert X8.joint_torque_nm(2.0) == pytest.approx(1.8)  # 9 * 0.1 * 2 A
    assert MIRRORED.joint_torque_nm(2.0) == pytest.approx(-1.8)
    assert MIRRORED.iq_a(-1.8) == pytest.approx(2.0)
    assert X8.iq_raw_checked(1.8) == 125  # 2 A * 2000 / 32
    assert MIRRORED.iq_raw_checked(1.8) == -125


def test_current_limit_in_raw_counts() -> None:
    assert X8.iq_raw_limit == 625  # 10 A exactly
    assert MIRRORED.iq_raw_limit == IQ_RAW_LIMIT  # default: the protocol's 32 A
    assert Transmission(9, 1, 0.0, 0.1, current_limit_a=0.1).iq_raw_limit == 6  # 6.25 counts, rounded down


def test_limiting_is_reported() -> None:
    assert X8.iq_raw_limited(9.0) == (625, False)  # exactly 10 A
    assert X8.iq_raw_limited(20.0) == (625, True)
    assert X8.iq_raw_limited(-20.0) == (-625, True)
    assert MIRRORED.iq_raw_limited(100.0) == (-IQ_RAW_LIMIT, True)


def test_checked_conversion_raises_beyond_the_limit() -> None:
    with pytest.raises(EncodeError, match=r"±10 A \(±625 raw\).*joint torque 20 N·m") as info:
        X8.iq_raw_checked(20.0)
    assert info.value.field == "iq_a"
    assert info.value.value == pytest.approx(20.0 / 0.9)


@pytest.mark.parametrize("torque", [float("nan"), float("inf")])
def test_non_finite_torque_raises(torque: float) -> None:
    with pytest.raises(EncodeError):
        X8.iq_raw_limited(torque)
    with pytest.raises(EncodeError):
        ArmTransmission([X8]).iq_raw_limited([torque])


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("gear_ratio", {"gear_ratio": 0.0}),
        ("direction", {"direction": 0}),
        ("torque_constant_nm_per_a", {"torque_constant_nm_per_a": -0.1}),
        ("current_limit_a", {"current_limit_a": 33.0}),
        ("zero_offset_deg", {"zero_offset_deg": float("nan")}),
    ],
)
def test_invalid_parameters_are_rejected(field: str, kwargs: dict[str, float]) -> None:
    params: dict[str, float] = {"gear_ratio": 9, "direction": 1, "zero_offset_deg": 0, "torque_constant_nm_per_a": 0.1}
    with pytest.raises(ConfigError) as info:
        Transmission(**(params | kwargs))  # type: ignore[arg-type]
    assert info.value.key_path == field


@given(transmissions, finite)
def test_position_round_trip(t: Transmission, joint_deg: float) -> None:
    assert t.joint_deg(t.motor_deg(joint_deg)) == pytest.approx(joint_deg, rel=1e-9, abs=1e-7)


@given(transmissions, finite)
def test_rate_round_trip(t: Transmission, rate: float) -> None:
    assert t.joint_rate(t.motor_rate(rate)) == pytest.approx(rate, rel=1e-9, abs=1e-9)


@given(transmissions, st.floats(min_value=-IQ_LIMIT_A, max_value=IQ_LIMIT_A))
def test_torque_round_trip(t: Transmission, iq_a: float) -> None:
    assert t.iq_a(t.joint_torque_nm(iq_a)) == pytest.approx(iq_a, rel=1e-9, abs=1e-12)


@given(transmissions, st.floats(min_value=-1e4, max_value=1e4))
def test_limited_raw_never_exceeds_the_limit(t: Transmission, torque_nm: float) -> None:
    raw, limited = t.iq_raw_limited(torque_nm)
    assert abs(raw) <= t.iq_raw_limit <= IQ_RAW_LIMIT
    assert limited == (abs(t.iq_a(torque_nm)) * IQ_RAW_LIMIT / IQ_LIMIT_A > t.iq_raw_limit + 0.5)
    if not limited:
        assert t.iq_raw_checked(torque_nm) == raw


@given(st.lists(st.tuples(transmissions, finite, finite), min_size=1, max_size=8))
def test_vectorised_matches_scalar(rows: list[tuple[Transmission, float, float]]) -> None:
    arm = ArmTransmission([t for t, _, _ in rows])
    motor = np.array([m for _, m, _ in rows])
    torque = np.array([tau for _, _, tau in rows])
    np.testing.assert_allclose(arm.joint_deg(motor), [t.joint_deg(m) for t, m, _ in rows], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(arm.motor_deg(motor), [t.motor_deg(m) for t, m, _ in rows], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(arm.joint_rate(motor), [t.joint_rate(m) for t, m, _ in rows], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(arm.motor_rate(motor), [t.motor_rate(m) for t, m, _ in rows], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(arm.iq_a(torque), [t.iq_a(tau) for t, _, tau in rows], rtol=1e-12)
    np.testing.assert_allclose(arm.joint_torque_nm(torque), [t.joint_torque_nm(x) for t, _, x in rows], rtol=1e-12)
    raw, limited = arm.iq_raw_limited(torque)
    assert raw.dtype == np.int64
    assert [(int(r), bool(flag)) for r, flag in zip(raw, limited, strict=True)] == [
        t.iq_raw_limited(tau) for t, _, tau in rows
    ]


def test_vectorised_writes_into_out_without_allocating() -> None:
    arm = ArmTransmission([X8, MIRRORED])
    buffer = np.array([900.0, 900.0])
    result = arm.joint_deg(buffer, out=buffer)
    assert result is buffer
    np.testing.assert_allclose(buffer, [110.0, -90.0])
    assert arm.motor_deg(buffer, out=buffer) is buffer
    np.testing.assert_allclose(buffer, [900.0, 900.0])


def test_vectorised_checked_names_the_joint() -> None:
    arm = ArmTransmission([MIRRORED, X8], names=["shoulder", "elbow"])
    np.testing.assert_array_equal(arm.iq_raw_checked([1.8, 1.8]), [-125, 125])
    raw, limited = arm.iq_raw_limited([1.8, -20.0])
    np.testing.assert_array_equal(raw, [-125, -625])
    np.testing.assert_array_equal(limited, [False, True])
    with pytest.raises(EncodeError, match="joint elbow: joint torque -20 N·m"):
        arm.iq_raw_checked([1.8, -20.0])


def test_vectorised_factors_are_read_only() -> None:
    arm = ArmTransmission([X8])
    with pytest.raises(ValueError, match="read-only"):
        arm._offset_deg[0] = 0.0
    assert len(arm) == 1
    with pytest.raises(ValueError, match="names"):
        ArmTransmission([X8], names=["a", "b"])
