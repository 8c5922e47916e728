"""Kinematics and dynamics against closed forms and against each other (gravity == rnea(q, 0, 0), URDF == chain)."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import kinematics as kin
from motion.config import ArmConfig, load_config, parse_config
from motion.errors import ConfigError

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ARM2_DATA: dict[str, Any] = yaml.safe_load((CONFIGS / "arm2.yaml").read_text())
ARM6_DATA: dict[str, Any] = yaml.safe_load((CONFIGS / "arm6.yaml").read_text())
ARM2_CONFIG = load_config(CONFIGS / "arm2.yaml")
ARM2 = kin.build_arm(ARM2_CONFIG)
ARM6 = kin.build_arm(load_config(CONFIGS / "arm6.yaml"))
#: arm6 with its joints configured in another order than the URDF's.
SHUFFLE = [5, 2, 0, 4, 1, 3]
ARM6_SHUFFLED = kin.build_arm(
    parse_config(dict(ARM6_DATA, joints=[ARM6_DATA["joints"][i] for i in SHUFFLE]), base_dir=CONFIGS)
)


Vector = np.ndarray[Any, np.dtype[np.float64]]


def joint_values(n: int) -> st.SearchStrategy[Vector]:
    """Joint angles (deg), speeds (deg/s) or accelerations (deg/s²) for n joints."""
    return arrays(np.float64, n, elements=st.floats(-400, 400, allow_nan=False))


def _arm2_parameters(config: ArmConfig) -> tuple[float, float, float, float, float, float, float, float]:
    """m1, m2 (kg), l1, l2, c1, c2 (m), I1, I2 (kg·m² about the centre of mass, about z) of the planar arm."""
    upper, forearm = config.model.chain
    assert config.model.tip_xyz_m is not None
    return (
        upper.mass_kg,
        forearm.mass_kg,
        forearm.origin_xyz_m[0],
        config.model.tip_xyz_m[0],
        upper.com_xyz_m[0],
        forearm.com_xyz_m[0],
        upper.inertia_kgm2.izz,
        forearm.inertia_kgm2.izz,
    )


M1, M2, L1, L2, C1, C2, I1, I2 = _arm2_parameters(ARM2_CONFIG)
G = -ARM2_CONFIG.model.gravity_m_s2[1]


def test_arm2_is_the_planar_arm_the_closed_forms_assume() -> None:
    assert (M1, M2, L1, L2, C1, C2) == (1.5, 1.0, 0.3, 0.25, 0.15, 0.125)
    assert ARM2_CONFIG.model.gravity_m_s2 == (0.0, -9.81, 0.0)
    assert all(c.axis == (0.0, 0.0, 1.0) and c.com_xyz_m[1:] == (0.0, 0.0) for c in ARM2_CONFIG.model.chain)


@pytest.mark.parametrize("q1", np.linspace(-180, 180, 13))
@pytest.mark.parametrize("q2", np.linspace(-180, 180, 13))
def test_arm2_gravity_matches_closed_form_on_a_grid(q1: float, q2: float) -> None:
    a1, a12 = math.radians(q1), math.radians(q1 + q2)
    expected = [(M1 * C1 + M2 * L1) * G * math.cos(a1) + M2 * C2 * G * math.cos(a12), M2 * C2 * G * math.cos(a12)]
    np.testing.assert_allclose(kin.gravity_torque(ARM2, [q1, q2]), expected, atol=1e-12)


@given(joint_values(2), joint_values(2))
def test_arm2_mass_matrix_and_rnea_match_closed_form(q_deg: Vector, qdd_dps2: Vector) -> None:
    c2 = math.cos(math.radians(q_deg[1]))
    m11 = I1 + I2 + M1 * C1**2 + M2 * (L1**2 + C2**2 + 2 * L1 * C2 * c2)
    m12 = I2 + M2 * (C2**2 + L1 * C2 * c2)
    m22 = I2 + M2 * C2**2
    expected_kgm2 = np.array([[m11, m12], [m12, m22]])
    mass = kin.mass_matrix(ARM2, q_deg)
    np.testing.assert_allclose(mass, expected_kgm2 * math.pi / 180, rtol=1e-6)  # izz is given to 5 digits
    inertial = kin.rnea(ARM2, q_deg, np.zeros(2), qdd_dps2) - kin.gravity_torque(ARM2, q_deg)
    np.testing.assert_allclose(inertial, mass @ qdd_dps2, rtol=1e-9, atol=1e-9)


@given(joint_values(2))
def test_arm2_tip_position_matches_closed_form(q_deg: Vector) -> None:
    a1, a12 = np.radians(q_deg[0]), np.radians(q_deg.sum())
    pose = kin.frame_pose(ARM2, "tip", q_deg)
    np.testing.assert_allclose(
        pose.position_m, [L1 * math.cos(a1) + L2 * math.cos(a12), L1 * math.sin(a1) + L2 * math.sin(a12), 0], atol=1e-12
    )
    rz = np.array([[math.cos(a12), -math.sin(a12), 0], [math.sin(a12), math.cos(a12), 0], [0, 0, 1]])
    np.testing.assert_allclose(pose.rotation, rz, atol=1e-12)


@given(joint_values(6))
def test_arm6_gravity_equals_rnea_at_rest(q_deg: Vector) -> None:
    tau = kin.gravity_torque(ARM6, q_deg)
    np.testing.assert_allclose(tau, kin.rnea(ARM6, q_deg, np.zeros(6), np.zeros(6)), rtol=1e-12, atol=1e-12)


def test_arm6_gravity_is_not_trivial() -> None:
    """The oracle above would also hold for a massless arm: check the shoulder really carries the arm."""
    tau = kin.gravity_torque(ARM6, [0, 90, 0, 0, 0, 0])  # upper arm and everything beyond it horizontal
    assert abs(tau[0]) < 1e-12  # the base yaw axis is vertical
    assert 15 < abs(tau[1]) < 25  # about 1.9 kg·m of arm at g


@given(joint_values(6), joint_values(6), joint_values(6))
def test_arm6_aba_inverts_rnea(q_deg: Vector, qd_dps: Vector, qdd_dps2: Vector) -> None:
    tau = kin.rnea(ARM6, q_deg, qd_dps, qdd_dps2)
    np.testing.assert_allclose(kin.aba(ARM6, q_deg, qd_dps, tau), qdd_dps2, rtol=1e-6, atol=1e-6)


def test_mass_matrix_is_symmetric_positive_definite() -> None:
    mass = kin.mass_matrix(ARM6, [10, 20, 30, 40, 50, 60])
    np.testing.assert_allclose(mass, mass.T)
    assert np.linalg.eigvalsh(mass).min() > 0


@given(joint_values(6), joint_values(6), joint_values(6))
@settings(max_examples=30)
def test_configuration_order_differs_from_urdf_order(q_deg: Vector, qd_dps: Vector, qdd_dps2: Vector) -> None:
    arm, s = ARM6_SHUFFLED, SHUFFLE
    q, qd, qdd = q_deg[s], qd_dps[s], qdd_dps2[s]
    assert arm.joint_names == tuple(ARM6.joint_names[i] for i in s)
    np.testing.assert_allclose(kin.gravity_torque(arm, q), kin.gravity_torque(ARM6, q_deg)[s], atol=1e-12)
    tau = kin.rnea(ARM6, q_deg, qd_dps, qdd_dps2)
    np.testing.assert_allclose(kin.rnea(arm, q, qd, qdd), tau[s], atol=1e-9)
    np.testing.assert_allclose(kin.aba(arm, q, qd, tau[s]), qdd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(kin.mass_matrix(arm, q), kin.mass_matrix(ARM6, q_deg)[np.ix_(s, s)], atol=1e-15)
    tool = kin.frame_pose(ARM6, "tool0", q_deg)
    np.testing.assert_allclose(kin.frame_pose(arm, "tool0", q).position_m, tool.position_m, atol=1e-12)


# ---- a YAML chain and the equivalent URDF build the same model ------------------------------------------

CHAIN: list[dict[str, Any]] = [
    {
        "joint": "j1",
        "origin_xyz_m": [0.01, 0.02, 0.1],
        "origin_rpy_rad": [0.1, -0.2, 0.3],
        "axis": [0, 0, 1],
        "mass_kg": 1.2,
        "com_xyz_m": [0.02, -0.01, 0.05],
        "inertia_kgm2": {"ixx": 0.004, "ixy": 0.0002, "ixz": -0.0001, "iyy": 0.005, "iyz": 0.0003, "izz": 0.003},
    },
    {
        "joint": "j2",
        "origin_xyz_m": [0.0, 0.05, 0.12],
        "origin_rpy_rad": [1.2, 0.0, -0.4],
        "axis": [0, 1, 0],
        "mass_kg": 0.9,
        "com_xyz_m": [0.1, 0.0, 0.01],
        "inertia_kgm2": {"ixx": 0.001, "ixy": 0.0, "ixz": 0.0001, "iyy": 0.006, "iyz": 0.0, "izz": 0.0062},
    },
    {
        "joint": "j3",
        "origin_xyz_m": [0.2, 0.0, 0.0],
        "origin_rpy_rad": [0.0, 0.7, 0.0],
        "axis": [0.6, 0.8, 0],
        "mass_kg": 0.4,
        "com_xyz_m": [0.05, 0.02, -0.03],
        "inertia_kgm2": {"ixx": 0.0004, "ixy": -0.00005, "ixz": 0.0, "iyy": 0.0005, "iyz": 0.00002, "izz": 0.0006},
    },
]


def _joints(names: list[str]) -> list[dict[str, Any]]:
    template = ARM6_DATA["joints"][0]
    return [dict(template, name=name, motor_id=i + 1) for i, name in enumerate(names)]


def _urdf(chain: list[dict[str, Any]]) -> str:
    def vector(values: list[float]) -> str:
        return " ".join(str(v) for v in values)

    parts = ['<robot name="chain">', '<link name="base"/>']
    parent = "base"
    for c in chain:
        link = f"{c['joint']}_link"
        inertia = " ".join(f'{k}="{v}"' for k, v in c["inertia_kgm2"].items())
        parts += [
            f'<link name="{link}"><inertial><origin xyz="{vector(c["com_xyz_m"])}" rpy="0 0 0"/>'
            f'<mass value="{c["mass_kg"]}"/><inertia {inertia}/></inertial></link>',
            f'<joint name="{c["joint"]}" type="revolute"><parent link="{parent}"/><child link="{link}"/>'
            f'<origin xyz="{vector(c["origin_xyz_m"])}" rpy="{vector(c["origin_rpy_rad"])}"/>'
            f'<axis xyz="{vector(c["axis"])}"/><limit lower="-3" upper="3" effort="10" velocity="5"/></joint>',
        ]
        parent = link
    return "\n".join([*parts, "</robot>"])


@pytest.fixture(scope="module")
def chain_and_urdf(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
    urdf = tmp_path_factory.mktemp("urdf") / "chain.urdf"
    urdf.write_text(_urdf(CHAIN))
    base = copy.deepcopy(ARM2_DATA)
    base["joints"] = _joints([c["joint"] for c in CHAIN])
    base["control"]["mode"] = "position"
    base["model"] = {"chain": CHAIN, "gravity_m_s2": [0.3, -1.0, -9.7]}
    from_chain = kin.build_arm(parse_config(base))
    base["model"] = {"urdf": str(urdf), "gravity_m_s2": [0.3, -1.0, -9.7]}
    return from_chain, kin.build_arm(parse_config(base))


@given(q_deg=joint_values(3), qd_dps=joint_values(3), qdd_dps2=joint_values(3))
@settings(max_examples=50)
def test_yaml_chain_and_urdf_agree(
    chain_and_urdf: tuple[Any, Any],
    q_deg: Vector,
    qd_dps: Vector,
    qdd_dps2: Vector,
) -> None:
    from_chain, from_urdf = chain_and_urdf
    np.testing.assert_allclose(kin.gravity_torque(from_chain, q_deg), kin.gravity_torque(from_urdf, q_deg), atol=1e-12)
    np.testing.assert_allclose(kin.mass_matrix(from_chain, q_deg), kin.mass_matrix(from_urdf, q_deg), atol=1e-14)
    tau = kin.rnea(from_chain, q_deg, qd_dps, qdd_dps2)
    np.testing.assert_allclose(tau, kin.rnea(from_urdf, q_deg, qd_dps, qdd_dps2), rtol=1e-9, atol=1e-9)
    for frame in ("j1_link", "j2_link", "j3_link"):
        chain_pose, urdf_pose = kin.frame_pose(from_chain, frame, q_deg), kin.frame_pose(from_urdf, frame, q_deg)
        np.testing.assert_allclose(chain_pose.position_m, urdf_pose.position_m, atol=1e-12)
        np.testing.assert_allclose(chain_pose.rotation, urdf_pose.rotation, atol=1e-12)


def test_gravity_vector_comes_from_the_configuration() -> None:
    data = copy.deepcopy(ARM2_DATA)
    data["model"]["gravity_m_s2"] = [0.0, 0.0, -9.81]  # now the joint axes are vertical: gravity does no work
    arm = kin.build_arm(parse_config(data))
    np.testing.assert_allclose(kin.gravity_torque(arm, [30, 60]), [0, 0], atol=1e-12)
    assert abs(kin.gravity_torque(ARM2, [30, 60])[0]) > 1


# ---- feed-forward callables and argument checks ----------------------------------------------------------

Q, QD, QDD = np.array([20.0, -40.0]), np.array([90.0, -30.0]), np.array([300.0, 500.0])


def test_feedforward_variants() -> None:
    gravity = kin.gravity_torque(ARM2, Q)
    full = kin.rnea(ARM2, Q, QD, QDD)
    assert not np.allclose(full, gravity)
    np.testing.assert_allclose(kin.feedforward(ARM2)(Q, QD, QDD), gravity)
    np.testing.assert_allclose(kin.feedforward(ARM2, inertia=True)(Q, QD, QDD), full)
    np.testing.assert_allclose(kin.feedforward(ARM2, gravity=False, inertia=True)(Q, QD, QDD), full - gravity)
    np.testing.assert_array_equal(kin.feedforward(ARM2, gravity=False)(Q, QD, QDD), [0.0, 0.0])


def test_the_feedforward_callables_give_the_functions_results_to_the_bit() -> None:
    # The callables take their arguments into arrays of their own: the results are the public functions' to the bit,
    # independent of each other, for arrays and lists alike.
    gravity, full = kin.gravity_torque(ARM2, Q), kin.rnea(ARM2, Q, QD, QDD)
    for args in ((Q, QD, QDD), (Q.tolist(), QD.tolist(), QDD.tolist()), (Q[::-1][::-1], QD, QDD.astype(np.float32))):
        first = kin.feedforward(ARM2, inertia=True)
        result = first(*args)
        expected = kin.rnea(ARM2, *[np.asarray(a, dtype=np.float64) for a in args])
        assert result.tobytes() == expected.tobytes()
        again = first(Q + 10.0, QD, QDD)
        assert result.tobytes() == expected.tobytes() and not np.array_equal(again, result)  # not a shared buffer
    assert kin.feedforward(ARM2)(Q, QD, QDD).tobytes() == gravity.tobytes()
    only_inertia = kin.feedforward(ARM2, gravity=False, inertia=True)(Q, QD, QDD)
    assert only_inertia.tobytes() == (full - gravity).tobytes()
    with pytest.raises(ValueError, match=r"qd_dps: expected shape \(2,\) \(one value per joint\), got \(3,\)"):
        kin.feedforward(ARM2, inertia=True)(Q, np.zeros(3), QDD)


def test_results_are_not_views_of_pinocchio_data() -> None:
    first = kin.gravity_torque(ARM2, [0, 0])
    kept = first.copy()
    kin.gravity_torque(ARM2, [90, 0])
    np.testing.assert_array_equal(first, kept)


def test_frame_names_and_unknown_frame() -> None:
    assert {"shoulder", "upper_arm", "elbow", "forearm", "tip"} <= set(kin.frame_names(ARM2))
    with pytest.raises(ConfigError, match="no frame 'hand'; frames: .*tip") as info:
        kin.frame_pose(ARM2, "hand", [0, 0])
    assert info.value.file == str(CONFIGS / "arm2.yaml")


def test_wrong_number_of_joint_values() -> None:
    with pytest.raises(ValueError, match=r"q_deg: expected shape \(2,\)"):
        kin.gravity_torque(ARM2, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="tau_nm"):
        kin.aba(ARM2, Q, QD, 1.0)


def test_urdf_that_pinocchio_rejects(tmp_path: Path) -> None:
    urdf = tmp_path / "broken.urdf"
    urdf.write_text((CONFIGS / "arm6.urdf").read_text().replace('<child link="tool0"/>', '<child link="nowhere"/>'))
    config = parse_config(dict(ARM6_DATA, model={"urdf": str(urdf)}), source="mem")  # joint names still match
    with pytest.raises(ConfigError, match="Pinocchio cannot build a model from it: .*broken.urdf") as info:
        kin.build_arm(config)
    assert (info.value.file, info.value.key_path) == ("mem", "model.urdf")


def test_figure_places_the_joints_and_draws_each_link_to_the_next_joint() -> None:
    from kinematics.figure import ArmFigure

    figure = ArmFigure(ARM2_CONFIG)
    # arm2: the elbow 0.30 m along the upper arm's x; the forearm, a tip, drawn toward its centre of mass
    assert len(figure.links) == 2
    assert figure.links[0][0] == pytest.approx([0.30, 0.0, 0.0])
    assert figure.reach == pytest.approx(0.30)
    positions, quaternions = figure.placements(np.array([90.0, 0.0]))
    assert positions[1] == pytest.approx([0.0, 0.30, 0.0], abs=1e-12)  # shoulder turned 90 deg about z
    assert quaternions[0] == pytest.approx([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    assert np.linalg.norm(figure.up) == pytest.approx(1.0)
