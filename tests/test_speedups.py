"""The optional C extension ``motion._speedups`` (issue 12) against the Python code it doubles.

Its ``SlotBuilder`` (the C half of :func:`motion.protocol.compiled.frozen_builder`) builds the object the class's own
``__init__`` builds, for every message class of both families and the hot path's other frozen classes, refuses what it
cannot build and keeps reference counts and the garbage collector right. Its CAN codec gives the Python fast path's
bytes and messages on every CAN layout, or defers alike, and the public calls answer and raise as their Python paths.
Its tracking-model steps give the numpy steps' results to the bit, down to a whole emulated move. A stale build is
left aside, and the package without the extension (``RMD_MOTION_PURE_PYTHON``) passes the codec's tests."""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import subprocess
import sys
import weakref
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kinematics import dynamics as dynamics_module
from motion import transmission as transmission_module
from motion.config.schema import ControlMode
from motion.control import axes as axes_module
from motion.control import controller as controller_module
from motion.control import snapshot as snapshot_module
from motion.control import tracking
from motion.control.axes import AxisSpec, AxisStates
from motion.control.family import FAMILIES
from motion.control.tracking import chase, chase_work
from motion.errors import EncodeError
from motion.protocol import (
    Bare,
    CanFrame,
    Command,
    Direction,
    ErrorFlags,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    Status1,
    TorqueControl,
    WireProtocol,
    can_frame,
)
from motion.protocol import compiled as compiled_module
from motion.protocol.compiled import FALLBACK_ERRORS, PURE_PYTHON_ENV, CompiledLayout, compile_layout, frozen_builder
from motion.protocol.messages import Message
from motion.protocol.table import ProtocolFamily
from motion.protocol.v3 import messages as v3_messages  # noqa: F401  (the V3 family's message classes)
from motion.trajectory.planner import State
from motion.transmission import ArmTransmission, Transmission
from motion.transport.base import Reply, Request
from tests.motion_rig import arm_config, emulated_arm
from tests.test_codec_fastpath import CASES, ODD_VALUES, draw_message

ROOT = Path(__file__).resolve().parent.parent


def _subclasses(cls: type) -> list[type]:
    found: list[type] = []
    sub: type
    for sub in cls.__subclasses__():
        found.append(sub)
        found.extend(_subclasses(sub))
    return found


#: Every frozen slotted dataclass the builders serve: the messages of both families and the hot path's others.
CLASSES = sorted(
    {
        cls
        for cls in [*_subclasses(Message), CanFrame, Request, State]
        # (dataclass(slots=True) replaces a class: the one a module names is the slotted one)
        if getattr(sys.modules[cls.__module__], cls.__qualname__, None) is cls
        and dataclasses.is_dataclass(cls)
        and "__slots__" in cls.__dict__
        and not hasattr(cls, "__post_init__")
    },
    key=lambda c: f"{c.__module__}.{c.__qualname__}",
)


def test_the_extension_is_built_here() -> None:
    # The development install builds it (the project's own files, a C compiler): a silent fallback to the pure-Python
    # builders would make every speed figure of bench/ a different program's.
    assert compiled_module.SlotBuilder is not None
    turned_off = os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0")
    assert compiled_module.ACCELERATED is not turned_off


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__qualname__)
@pytest.mark.parametrize("accelerated", [True, False], ids=["C", "python"])
def test_a_built_object_is_the_one_init_builds(cls: Any, accelerated: bool) -> None:
    fields = dataclasses.fields(cls)
    values = [object() for _ in fields]  # neither builder nor __init__ looks at the values
    build = frozen_builder(cls, accelerated=accelerated)
    built = build(*values)
    made = cls(*values)
    assert type(built) is cls
    assert built == made
    assert hash(built) == hash(made)
    assert repr(built) == repr(made)
    assert [getattr(built, f.name) for f in fields] == values
    if fields:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(built, fields[0].name, 1)
        assert dataclasses.replace(built, **{fields[0].name: 1}) == cls(1, *values[1:])


def test_a_stale_build_of_the_extension_is_not_used(tmp_path: Path) -> None:
    # An editable install's module built from an older source (no or another ABI) is left aside, whole, and said so.
    from motion import _speedups

    stale = tmp_path / "motion"
    stale.mkdir()
    (stale / "__init__.py").write_text("")
    (stale / "_speedups.py").write_text("ABI = 0\n")
    code = (
        "import importlib.util, sys\n"
        f"spec = importlib.util.spec_from_file_location('motion._speedups', {str(stale / '_speedups.py')!r})\n"
        "module = importlib.util.module_from_spec(spec); spec.loader.exec_module(module)\n"
        "sys.modules['motion._speedups'] = module\n"
        "import motion; motion._speedups = module\n"
        "from motion.protocol import compiled, can_frame\n"
        "from motion.cli.app import version_text\n"
        "print(compiled.ACCELERATED, can_frame.encode_request is can_frame._encode_request)\n"
        "print(version_text())\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == "False True"
    assert lines[1].endswith("(pure Python: the C accelerator is out of date: reinstall (pip install -e .))")
    assert _speedups.ABI == compiled_module.SPEEDUPS_ABI  # (the build in use here is current)


def test_the_c_builder_is_used_and_checks_its_arguments() -> None:
    build: Any = frozen_builder(CanFrame, accelerated=True)
    assert type(build).__name__ == "SlotBuilder"
    assert build.cls is CanFrame and build.names == ("arbitration_id", "data")
    assert "CanFrame" in repr(build)
    with pytest.raises(TypeError, match=r"the builder of .*CanFrame takes 2 positional values, got 1"):
        build(0x141)
    with pytest.raises(TypeError, match=r"takes 2 positional values, got 3"):
        build(0x141, b"", 3)
    with pytest.raises(TypeError, match=r"got 1 and keywords"):
        build(0x141, data=b"")


def test_the_c_builder_refuses_what_it_cannot_build() -> None:
    slot_builder: Any = compiled_module.SlotBuilder

    class Plain:  # instances with a __dict__: no slots to fill
        pass

    class WithSlots:
        __slots__ = ("a",)

    class Other:
        __slots__ = ("b",)

    class Short(tuple[int, ...]):  # a variable-size instance
        __slots__ = ()

    with pytest.raises(TypeError, match=r"Plain has no slot 'a'"):
        slot_builder(Plain, ("a",))
    with pytest.raises(TypeError, match=r"WithSlots.__init__ is not a slot"):
        slot_builder(WithSlots, ("__init__",))
    WithSlots.b = Other.__dict__["b"]  # type: ignore[attr-defined]  # a slot of an unrelated class
    with pytest.raises(TypeError, match=r"WithSlots.b is a slot of another class"):
        slot_builder(WithSlots, ("b",))
    with pytest.raises(TypeError, match=r"variable size"):
        slot_builder(Short, ())
    with pytest.raises(TypeError, match=r"slot names must be str"):
        slot_builder(WithSlots, (1,))
    with pytest.raises(TypeError):
        slot_builder(WithSlots, ["a"])  # names: a tuple
    with pytest.raises(TypeError, match=r"not a writable object slot"):
        slot_builder(complex, ("real",))  # a read-only member of a C type


def test_the_c_builder_keeps_reference_counts_and_the_collector_right() -> None:
    build = frozen_builder(CanFrame, accelerated=True)
    value = object()
    before = sys.getrefcount(value)
    frames = [build(value, value) for _ in range(1000)]
    assert sys.getrefcount(value) == before + 2000
    del frames
    assert sys.getrefcount(value) == before
    frame = build([], b"")
    assert gc.is_tracked(frame)
    # A cycle through a built object is collected.
    marker = object()
    holder: list[Any] = []
    looped = build(holder, marker)
    holder.append(looped)
    assert any(type(o) is CanFrame and o.data is marker for o in gc.get_objects())
    del looped, holder
    gc.collect()
    assert not any(type(o) is CanFrame and o.data is marker for o in gc.get_objects())
    # The builder itself: a builder of a class that refers back to it is collected too.
    count = sum(1 for o in gc.get_objects() if type(o).__name__ == "SlotBuilder")

    @dataclasses.dataclass(frozen=True, slots=True)
    class Local:
        x: int

    Local.builder = frozen_builder(Local, accelerated=True)  # type: ignore[attr-defined]
    assert Local.builder(3) == Local(3)  # type: ignore[attr-defined]
    del Local
    gc.collect()
    assert sum(1 for o in gc.get_objects() if type(o).__name__ == "SlotBuilder") == count


@pytest.mark.timeout(1800)  # (about 50 s here; one CPU shared with three busy loops took more than 300 s)
def test_without_the_extension_the_codec_tests_pass_on_the_pure_python_builders() -> None:
    env = dict(os.environ, **{PURE_PYTHON_ENV: "1"})
    check = subprocess.run(
        [sys.executable, "-c", "from motion.protocol import compiled; print(compiled.ACCELERATED)"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert check.stdout.strip() == "False"
    tests = ["tests/test_codec_fastpath.py", "tests/test_protocol_golden.py", "tests/test_protocol_properties.py"]
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=1500,
        check=False,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert " passed" in run.stdout


# ---------------------------------------------------------------------------------------------------------- chase


def _chase_both(x: np.ndarray, v: np.ndarray, dt: float, **arrays: Any) -> tuple[tuple[Any, Any], tuple[Any, Any]]:
    results = []
    for accelerated in (True, False):
        xs, vs = x.copy(), v.copy()
        chase(xs, vs, dt, **arrays, work=chase_work(len(x)), accelerated=accelerated)
        results.append((xs, vs))
    return results[0], results[1]


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("seed", range(8))
def test_chase_in_c_gives_the_numpy_steps_results_to_the_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for trial in range(400):
        n = int(rng.integers(1, 13))
        x, v, target = rng.normal(0, 100, n), rng.normal(0, 300, n), rng.normal(0, 100, n)
        cap, gain, accel = np.abs(rng.normal(0, 500, n)), np.abs(rng.normal(0, 60, n)), np.abs(rng.normal(0, 5e3, n))
        if trial % 5 == 0:
            accel[:] = 1e12  # the model's "no limit"
        if trial % 7 == 0:
            cap[rng.integers(0, n)] = np.inf
        if trial % 11 == 0:
            target[rng.integers(0, n)] = np.nan  # propagates as numpy's minimum / maximum propagate it
        if trial % 13 == 0:
            x[:] = target  # at the target: zero errors, signed zeros
        dt = float(rng.choice([0.0, 0.0005, 0.001, 0.002, 0.004, 0.0123, 0.25]))
        (xc, vc), (xp, vp) = _chase_both(x, v, dt, target=target, cap=cap, gain=gain, accel=accel)
        assert _same_bits(xc, xp) and _same_bits(vc, vp), (seed, trial)
        assert not np.array_equal(xc, x, equal_nan=True) or dt == 0.0 or trial % 13 == 0 or np.isnan(target).any()


def test_the_tracking_model_steps_with_chase_in_c() -> None:
    assert tracking._C_CHASE is (None if compiled_module.SPEEDUPS is None else compiled_module.SPEEDUPS.chase)
    from motion import _speedups

    c_chase: Any = _speedups.chase
    x, v = np.zeros(3), np.zeros(3)
    ones = np.ones(3)
    c_chase(x, v, 0.004, ones * 10.0, ones * 100.0, ones * 50.0, ones * 1e4, tracking.MAX_STEP_S)
    assert (x > 0).all() and (v > 0).all()


def test_chase_in_c_refuses_what_it_cannot_take_and_changes_nothing_then() -> None:
    from motion import _speedups

    c_chase: Any = _speedups.chase
    three, ints = np.ones(3), np.ones(3, dtype=np.int64)
    x, v = np.full(3, 7.0), np.full(3, 3.0)
    with pytest.raises(TypeError, match=r"chase: accel must be a one-dimensional float64 array"):
        c_chase(x, v, 0.001, three, three, three, ints, 0.001)  # refused after x and v were taken
    with pytest.raises(ValueError, match=r"chase: gain has 2 entries, the first array 3"):
        c_chase(x, v, 0.001, three, three, np.ones(2), three, 0.001)
    with pytest.raises(TypeError, match=r"chase: x must be a C-contiguous, writable float64 array"):
        c_chase(np.zeros(6)[::2], v, 0.001, three, three, three, three, 0.001)
    with pytest.raises(TypeError, match=r"chase: v must be a C-contiguous, writable float64 array"):
        c_chase(x, three.copy()[None, :].repeat(2, 0)[:, 0], 0.001, three, three, three, three, 0.001)
    with pytest.raises(TypeError, match=r"takes 8 positional arguments"):
        c_chase(x, v, 0.001)
    with pytest.raises(ValueError, match=r"max_step must be > 0 and dt finite"):
        c_chase(x, v, math.inf, three, three, three, three, 0.001)
    assert (x == 7.0).all() and (v == 3.0).all()


def test_the_torque_mode_steps_in_c_refuse_a_wrong_call_and_change_nothing_then() -> None:
    from motion import _speedups

    c: Any = _speedups
    three = np.full(3, 2.0)
    x = np.full(3, 7.0)
    for call, arguments, expected in (
        (c.torque_pd, (x, three, three, three, three, three), 7),
        (c.moved_beyond, (x, three), 3),
        (c.torque_advance, (x, *[three.copy() for _ in range(7)], 0.001), 10),
        (c.torque_law, (x, *[three.copy() for _ in range(13)], np.eye(3), None, 1.0), 18),
        (c.torque_currents, (x, three.copy(), three, three, np.zeros(3, bool), None, 1.0, 1.0), 9),
        (c.gather_scaled, (x, three, np.arange(3)), 4),
    ):
        with pytest.raises(TypeError, match=rf"takes {expected} positional arguments, got {expected - 1}"):
            call(*arguments)
    with pytest.raises(TypeError, match=r"must be real number"):
        c.torque_advance(x, *[three.copy() for _ in range(8)], "0.001")  # after the arrays were taken (and released)
    with pytest.raises(TypeError, match=r"torque_law: mass_inv must be a 3 x 3 float64 matrix"):
        c.torque_law(x, *[three.copy() for _ in range(13)], np.eye(2), None, 1.0, 1.0)
    with pytest.raises(TypeError, match=r"torque_law: mass must be a C-contiguous float64 matrix"):
        c.torque_law(x, *[three.copy() for _ in range(13)], np.eye(3), "M", 1.0, 1.0)
    with pytest.raises(TypeError, match=r"torque_law: kd must be a one-dimensional float64 array"):
        c.torque_law(
            x, *[three.copy() for _ in range(9)], np.ones(3, np.int64), three, three, three, np.eye(3), None, 1, 1
        )
    with pytest.raises(ValueError, match=r"torque_currents: limited has 2 entries, the first array 3"):
        c.torque_currents(x, three.copy(), three, three, np.zeros(2, bool), None, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"torque_currents: addend has 2 entries, the first array 3"):
        c.torque_currents(x, three.copy(), three, three, np.zeros(3, bool), np.ones(2), 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"gather_scaled: order\[1\] = 3 is not an index of src"):
        c.gather_scaled(x, three, np.array([0, 3, 1]), 1.0)
    with pytest.raises(TypeError, match=r"torque_currents: limited must be a one-dimensional bool array"):
        c.torque_currents(x, three.copy(), three, three, np.zeros(3), None, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match=r"gather_scaled: order has 2 entries, the first array 3"):
        c.gather_scaled(x, three, np.arange(2), 1.0)
    with pytest.raises(TypeError, match=r"gather_scaled: order must be a one-dimensional int64 array"):
        c.gather_scaled(x, three, np.array([0, 1, 2], dtype=np.int32), 1.0)
    with pytest.raises(ValueError, match=r"gather_scaled: out must not be src"):
        c.gather_scaled(x, x, np.arange(3), 1.0)
    assert (x == 7.0).all()
    assert c.moved_beyond(np.array([0.0, 6.0]), np.zeros(2), 5.0) is True
    assert c.moved_beyond(np.array([np.nan, 6.0]), np.zeros(2), 5.0) is False  # as numpy's max: NaN > 5 is False


def _joint(**fields: Any) -> Transmission:
    values: dict[str, Any] = {
        "gear_ratio": 6.0,
        "direction": 1,
        "zero_offset_deg": 0.0,
        "torque_constant_nm_per_a": 0.1,
    }
    return Transmission(**(values | fields))


def _torque_model(rng: np.random.Generator, n: int, fed_forward: bool) -> tracking.ExpectedTracking:
    """A torque-mode tracking model of ``n`` joints with a random symmetric positive mass matrix, commanded once."""
    transmission = ArmTransmission([_joint(gear_ratio=float(rng.uniform(1, 50))) for _ in range(n)])
    kp, kd = np.abs(rng.normal(0, 2, n)), np.abs(rng.normal(0, 0.05, n))
    model = tracking.ExpectedTracking(
        ControlMode.TORQUE, transmission, kp, kd, list(range(1, n + 1)), read_drives=False
    )
    root = rng.normal(0, 0.3, (n, n))
    model.set_inertia(root @ root.T + np.eye(n) * 0.05, fed_forward=fed_forward)
    model.reset(rng.normal(0, 30, n), rng.normal(0, 50, n))
    return model


def _model_state(model: tracking.ExpectedTracking) -> list[bytes]:
    names = ("_x", "_v", "_x_law", "_v_law", "expected_deg", "expected_dps", "lag_deg", "_target", "_ref_v", "_ref_a")
    return [getattr(model, name).tobytes() for name in (*names, "_tau", "_accel_dps2")]


def _sequential_dot(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """Matrix . vector with each row summed in index order (Python floats, no fused multiply-add)."""
    rows = []
    for row in matrix.tolist():
        total = row[0] * vector[0]
        for m, x in zip(row[1:], vector.tolist()[1:], strict=True):
            total += m * x
        rows.append(total)
    return np.array(rows)


@pytest.mark.parametrize("seed", range(4))
def test_the_torque_model_in_c_steps_as_numpy_does(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # advance and command, in C and in numpy, from the same state: every array alike to the bit but for the two
    # matrix products (C sums in index order, np.dot as its BLAS does): those are checked against a sequential sum to
    # the bit, and against numpy's within rounding.
    rng = np.random.default_rng(seed)
    for trial in range(150):
        n = int(rng.integers(1, 13))
        fed_forward = trial % 2 == 0
        models = [_torque_model(np.random.default_rng([seed, trial]), n, fed_forward) for _ in range(2)]
        reference = [rng.normal(0, 40, n), rng.normal(0, 80, n), rng.normal(0, 500, n)]
        if trial % 9 == 0:
            reference[0][rng.integers(0, n)] = np.nan
        t_s = 0.0
        for step in range(3):
            dt = float(rng.choice([0.0, 0.001, 0.002, 0.0123]))
            measured = (rng.normal(0, 30, n), rng.normal(0, 50, n))
            for accelerated, model in zip((True, False), models, strict=True):
                if not accelerated:
                    monkeypatch.setattr(tracking, "_C", None)
                model.advance(t_s + dt, *measured)
                model.command(t_s + dt, reference[0], reference[1], reference[2], None)
                monkeypatch.undo()
            t_s += dt
            c_state, numpy_state = _model_state(models[0]), _model_state(models[1])
            assert c_state[:10] == numpy_state[:10], (seed, trial, step)
            c_model = models[0]
            mass = c_model.inertia_kgm2
            assert mass is not None
            tau = c_model._tau
            expected_tau = (
                c_model.kp * (c_model._target - c_model._x_law) + (c_model._ref_v - c_model._v_law) * c_model.kd
            )
            if fed_forward:
                expected_tau = expected_tau + _sequential_dot(mass, c_model._ref_a * (math.pi / 180.0))
            expected_tau = np.maximum(np.minimum(expected_tau, c_model.torque_limit_nm), -c_model.torque_limit_nm)
            assert _same_bits(tau, expected_tau), (seed, trial, step)
            accel = _sequential_dot(c_model._mass_inv, tau) * (180.0 / math.pi)
            assert _same_bits(c_model._accel_dps2, accel), (seed, trial, step)
            np.testing.assert_allclose(tau, models[1]._tau, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(c_model._accel_dps2, models[1]._accel_dps2, rtol=1e-9, atol=1e-9)
            for name in ("_tau", "_accel_dps2"):  # the next step starts both from the same state
                np.copyto(getattr(models[1], name), getattr(c_model, name))


@pytest.mark.parametrize("seed", range(4))
def test_the_torque_currents_in_c_are_the_python_ones_to_the_bit(seed: int) -> None:
    from motion import _speedups

    rng = np.random.default_rng(seed)
    seen_limited = seen_ties = 0
    for trial in range(300):
        n = int(rng.integers(1, 13))
        arm = ArmTransmission(
            [
                _joint(
                    gear_ratio=float(rng.choice([1.0, 6.0, 9.0, 36.0])),
                    direction=int(rng.choice([1, -1])),
                    torque_constant_nm_per_a=float(rng.uniform(0.05, 2.0)),
                    current_limit_a=float(rng.uniform(0.5, 32.0)),
                )
                for _ in range(n)
            ]
        )
        torque = rng.normal(0, 40, n)
        if trial % 3 == 0:  # exactly half-way between two raw values: rounded half to even, as Python's round()
            half = (np.floor(rng.normal(0, 200, n)) + 0.5) / 62.5
            torque = half * np.array([t.nm_per_a for t in arm.transmissions])
        addend = rng.normal(0, 5, n) if trial % 2 else None
        expected_torque = torque + addend if addend is not None else torque.copy()
        raw, limited = arm.iq_raw_limited_list(expected_torque.tolist())
        amps, flags, c_torque = np.full(n, np.nan), np.zeros(n, bool), torque.copy()
        assert (
            _speedups.torque_currents(amps, c_torque, arm._nm_per_a, arm._raw_limit, flags, addend, 62.5, 32, 2000)
            is None
        )
        assert _same_bits(c_torque, expected_torque)
        assert _same_bits(amps, np.array([raw_value * 32 / 2000 for raw_value in raw]))
        assert flags.tolist() == limited
        seen_limited += int(flags.any())
        seen_ties += sum(
            abs(t / k * 62.5 % 1.0 - 0.5) < 1e-9 for t, k in zip(expected_torque, arm._nm_per_a, strict=True)
        )
    assert seen_limited > 20 and seen_ties > 20  # the limits and the half-way rounding were exercised
    tiny = ArmTransmission([_joint(current_limit_a=0.01)] * 2)  # a raw limit of 0: the limited current is 0.0, not -0.0
    amps, flags = np.full(2, 5.0), np.zeros(2, bool)
    terms = (tiny._nm_per_a, tiny._raw_limit)
    assert _speedups.torque_currents(amps, np.array([-1.0, 1.0]), *terms, flags, None, 62.5, 32, 2000) is None
    assert amps.tobytes() == np.zeros(2).tobytes() and flags.all()
    arm = ArmTransmission([_joint(), _joint()])
    amps, flags = np.full(2, 5.0), np.zeros(2, bool)
    assert (
        _speedups.torque_currents(
            amps, np.array([1.0, np.inf]), arm._nm_per_a, arm._raw_limit, flags, None, 62.5, 32, 2000
        )
        == 1
    )
    assert (amps == 5.0).all() and not flags.any()  # nothing written: the caller raises


def test_the_cycles_current_limit_raises_for_a_torque_not_finite_with_c_and_without(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    arm = ArmTransmission([_joint(), _joint()], names=("shoulder", "elbow"))
    for accelerated in (True, False):
        if not accelerated:
            monkeypatch.setattr(transmission_module, "_C", None)
        amps, flags = np.zeros(2), np.zeros(2, bool)
        with pytest.raises(EncodeError, match=r"elbow") as raised:
            arm.iq_amps_limited_into(np.array([1.0, 0.0]), amps, flags, np.array([0.0, np.nan]))
        assert (amps == 0.0).all()
        assert "finite" in str(raised.value) or "nan" in str(raised.value).lower()


def test_gather_scaled_is_numpys_index_and_deg2rad_to_the_bit() -> None:
    from motion import _speedups

    rng = np.random.default_rng(5)
    for _ in range(200):
        n = int(rng.integers(1, 13))
        src, order = rng.normal(0, 400, n), rng.permutation(n)
        out = np.zeros(n)
        _speedups.gather_scaled(out, src, order, math.pi / 180.0)
        assert _same_bits(out, np.deg2rad(src[order]))


def test_chase_takes_what_the_c_one_refuses_through_numpy() -> None:
    x, v = np.zeros(3), np.zeros(3)
    cap: Any = np.inf  # a scalar, broadcast by numpy
    chase(
        x, v, 0.002, target=np.full(3, 5.0), cap=cap, gain=np.full(3, 50.0), accel=np.full(3, 1e4), work=chase_work(3)
    )
    xp, vp = np.zeros(3), np.zeros(3)
    chase(
        xp,
        vp,
        0.002,
        target=np.full(3, 5.0),
        cap=np.full(3, np.inf),
        gain=np.full(3, 50.0),
        accel=np.full(3, 1e4),
        work=chase_work(3),
        accelerated=False,
    )
    assert (x > 0).all() and _same_bits(x, xp) and _same_bits(v, vp)


# ---------------------------------------------------------------------------------------------------------- codec

#: Every CAN layout the C extension takes: (command, direction, the compiled layout with its ``native`` twin).
NATIVE_CASES = [
    (code, direction, compiled)
    for code, transport, direction, layout in CASES
    if transport is WireProtocol.CAN
    and (compiled := compile_layout(layout, code, transport, direction)) is not None
    and compiled.native is not None
]
NATIVE_IDS = [f"{'280' if c is None else f'{c:02X}'}-{d.value}" for c, d, _ in NATIVE_CASES]


def test_the_c_codec_takes_every_can_layout_of_the_hot_path() -> None:
    assert len(NATIVE_CASES) >= 40
    assert can_frame.encode_request is not can_frame._encode_request
    assert type(can_frame.encode_request).__name__ == "CanRequestEncoder"
    assert type(can_frame.decode_reply).__name__ == "CanReplyDecoder"
    assert can_frame.encode_request.fallback is can_frame._encode_request  # type: ignore[attr-defined]


def test_the_c_calls_take_the_control_cycles_frames_themselves() -> None:
    # With fallbacks that fail, the cycle's requests and replies still go through: the C objects do not defer them.
    def no_python(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError(f"deferred to Python: {args}")

    codecs = can_frame._native_codecs(no_python, no_python)
    assert codecs is not None
    encode, decode = codecs
    requests = [
        MultiTurnPositionSpeed(123.45, 270.0),
        TorqueControl(-1.25),
        MultiMotorTorque(1.0, -2.0, 0.5, 0.0),
        Bare(Command.READ_STATUS_1),
        Bare(Command.READ_STATUS_2),
        Bare(Command.READ_MULTI_TURN_ANGLE),
    ]
    for message in requests:
        assert encode(message, 3) == can_frame._encode_request(message, 3)
    replies = [
        MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, 0.416, -12, 1234),
        MotorState(Command.TORQUE, -5, -2.496, 300, 16383),  # (a current the 1/62.5 A steps carry)
        Status1(Command.READ_STATUS_1, 35, 24.1, ErrorFlags.NONE),
    ]
    for message in replies:
        frame = can_frame.encode_reply(message, 7)
        assert decode(frame.arbitration_id, frame.data) == (7, message)
    with pytest.raises(AssertionError, match="deferred to Python"):
        decode(0x280, bytes(8))  # the odd ones still go there


def _python_fast_encode(compiled: CompiledLayout, message: Any) -> bytes | None:
    try:
        return compiled.encode(message)
    except FALLBACK_ERRORS:
        return None


def _fields(message: Any) -> list[tuple[type, Any]]:
    return [(type(v), v) for v in (getattr(message, f.name) for f in dataclasses.fields(message))]


@pytest.mark.parametrize(("code", "direction", "compiled"), NATIVE_CASES, ids=NATIVE_IDS)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_c_encode_gives_the_python_fast_paths_bytes_or_defers_alike(
    code: Command | None, direction: Direction, compiled: CompiledLayout, data: st.DataObject
) -> None:
    message = draw_message(compiled, data, edges=True)
    assert compiled.native.encode(message) == _python_fast_encode(compiled, message), message


@pytest.mark.parametrize(("code", "direction", "compiled"), NATIVE_CASES, ids=NATIVE_IDS)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_c_decode_gives_the_python_fast_paths_message_or_defers_alike(
    code: Command | None, direction: Direction, compiled: CompiledLayout, data: st.DataObject
) -> None:
    payload = bytearray(data.draw(st.binary(min_size=compiled.size, max_size=compiled.size)))
    if data.draw(st.booleans()):
        payload = bytearray(b if data.draw(st.booleans()) else 0 for b in payload)
    if code is not None:
        payload[0] = code
    native, python = compiled.native.decode(bytes(payload)), compiled.decode(bytes(payload))
    if direction is Direction.REQUEST:
        assert native is None  # a request's reserved bytes are the Python path's to check
        return
    assert (native is None) == (python is None)
    if native is not None:
        assert type(native) is type(python)
        assert native == python
        assert _fields(native) == _fields(python)


def _outcome(call: Any, *args: Any, **kwargs: Any) -> Any:
    try:
        result = call(*args, **kwargs)
    except Exception as exc:  # the error's type and text are part of what must agree
        return (type(exc), str(exc))
    if isinstance(result, tuple):
        return result[0], result[1], _fields(result[1])
    return result


@settings(max_examples=300, deadline=None)
@given(
    arbitration_id=st.one_of(st.integers(0x13E, 0x163), st.sampled_from([0x280, -1, 1 << 70, True, 321.0])),
    payload=st.one_of(
        st.binary(min_size=8, max_size=8).map(lambda b: bytes([0x9C]) + b[1:]),
        st.binary(min_size=8, max_size=8),
        st.binary(min_size=0, max_size=10),
        st.binary(min_size=8, max_size=8).map(bytearray),
    ),
)
def test_decode_reply_in_c_answers_and_raises_as_the_python_one(arbitration_id: Any, payload: Any) -> None:
    assert _outcome(can_frame.decode_reply, arbitration_id, payload) == _outcome(
        can_frame._decode_reply, arbitration_id, payload
    )


@settings(max_examples=300, deadline=None)
@given(
    message=st.one_of(
        st.builds(MultiTurnPositionSpeed, ODD_VALUES, ODD_VALUES),
        st.builds(MultiTurnPositionSpeed, st.floats(-1e6, 1e6), st.floats(0, 70000)),
        st.builds(TorqueControl, st.one_of(st.floats(-40, 40), ODD_VALUES)),
        st.builds(MultiMotorTorque, st.floats(-33, 33), st.floats(-33, 33), st.floats(-33, 33), st.floats(-33, 33)),
        st.sampled_from(
            [
                Bare(Command.READ_STATUS_1),
                Bare(Command.MOTOR_STOP),
                Status1(Command.READ_STATUS_1, 30, 24.0, ErrorFlags(0)),
            ]
        ),
    ),
    motor_id=st.one_of(st.integers(-1, 34), st.sampled_from([True, 1.0, None, 1 << 70])),
    keyword=st.booleans(),
)
def test_encode_request_in_c_answers_and_raises_as_the_python_one(message: Any, motor_id: Any, keyword: bool) -> None:
    if keyword:
        assert _outcome(can_frame.encode_request, message, motor_id=motor_id) == _outcome(
            can_frame._encode_request, message, motor_id=motor_id
        )
    else:
        assert _outcome(can_frame.encode_request, message, motor_id) == _outcome(
            can_frame._encode_request, message, motor_id
        )
    assert _outcome(can_frame.encode_request, message) == _outcome(can_frame._encode_request, message)


def test_the_c_codec_keeps_reference_counts() -> None:
    angle = 12.5
    message = MultiTurnPositionSpeed(angle, 90.0)
    before = (sys.getrefcount(message), sys.getrefcount(angle))
    for _ in range(1000):
        can_frame.encode_request(message, 2)
    assert (sys.getrefcount(message), sys.getrefcount(angle)) == before
    data = can_frame.encode_reply(MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, 0.5, -5, 1000), 3).data
    member = Command.MULTI_TURN_POSITION_SPEED
    count = sys.getrefcount(member)
    replies = [can_frame.decode_reply(0x143, data) for _ in range(1000)]
    assert sys.getrefcount(member) == count + 1000
    del replies
    assert sys.getrefcount(member) == count


def test_the_c_codec_refuses_tables_it_cannot_take() -> None:
    from motion import _speedups

    layout: Any = _speedups.CLayout
    field = ("x", 0, 1, 1, 0, 255, 1, 1, False, None, None)
    assert layout(0xA4, 8, (field,), (), None, (), ()).encode(Bare(Command.READ_STATUS_1)) is None
    with pytest.raises(ValueError, match=r"field x: width 3 is not 1, 2 or 4"):
        layout(0xA4, 8, ((*field[:7], 3, *field[8:]),), (), None, (), ())
    with pytest.raises(ValueError, match=r"field x: offset, range or scale out of bounds"):
        layout(0xA4, 8, ((*field[:6], 8, *field[7:]),), (), None, (), ())  # beyond the payload
    with pytest.raises(ValueError, match=r"field x: offset, range or scale out of bounds"):
        layout(0xA4, 8, ((*field[:5], 256, *field[6:]),), (), None, (), ())  # beyond uint8
    with pytest.raises(ValueError, match=r"field x: kind 7 is not 0..3"):
        layout(0xA4, 8, ((*field[:1], 7, *field[2:]),), (), None, (), ())
    with pytest.raises(TypeError, match=r"an enum field needs its class"):
        layout(0xA4, 8, ((*field[:1], 2, *field[2:]),), (), None, (), ())
    with pytest.raises(ValueError, match=r"source 0 is neither -1 nor a field index"):
        layout(0xA4, 8, (field,), (), CanFrame, (1,), (None,))
    with pytest.raises(TypeError, match=r"256 layouts"):
        _speedups.CanReplyDecoder((None,) * 255, 0x140, 1, 32, can_frame._decode_reply)
    with pytest.raises(TypeError, match=r"layouts maps classes to CLayout"):
        not_layouts: Any = {Bare: 1}
        _speedups.CanRequestEncoder(not_layouts, {}, CanFrame, MultiMotorTorque, 0x280, 0x140, 1, 32, print)


def _axes_pair(rng: np.random.Generator, n: int) -> tuple[AxisStates, AxisStates]:
    """Two alike axis sets of ``n`` joints (random encoders, gears, directions, offsets): with the C loop, without."""
    specs = [AxisSpec(f"j{i}", i + 1, encoder_bits=int(rng.choice([12, 14, 16, 18]))) for i in range(n)]
    joints = [
        _joint(
            gear_ratio=float(rng.choice([1.0, 6.0, 9.0, 36.0, 101.0])),
            direction=int(rng.choice([1, -1])),
            zero_offset_deg=float(rng.normal(0, 50)),
        )
        for _ in range(n)
    ]
    pair = AxisStates(specs, ArmTransmission(joints)), AxisStates(specs, ArmTransmission(joints))
    pair[1]._absorb_c = None
    assert pair[0]._absorb_c is not None
    start = rng.normal(0, 1000, n)
    for axes in pair:
        for i in range(n):
            axes.initialise(i, float(start[i]), int(rng.integers(0, 65536)) if axes is pair[0] else 0)
    for i in range(n):  # the same encoders in both
        pair[1].initialise(i, float(start[i]), int(pair[0].encoder[i]))
    return pair


def _axes_arrays(axes: AxisStates) -> list[bytes]:
    names = ("encoder", "motor_deg", "motor_speed_dps", "iq_a", "temperature_c", "last_reply_s", "q_deg", "qd_dps")
    return [getattr(axes, name).tobytes() for name in (*names, "fresh")]


@pytest.mark.parametrize("seed", range(4))
def test_absorb_in_c_gives_the_python_loops_arrays_to_the_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    other = Status1(Command.READ_STATUS_1, 30, 24.0, ErrorFlags.NONE)
    for trial in range(120):
        n = int(rng.integers(1, 13))
        pair = _axes_pair(rng, n)
        for _cycle in range(6):
            replies: list[Reply] = []
            for _ in range(int(rng.integers(0, 2 * n + 3))):
                motor_id = int(rng.integers(1, n + 3))  # some of no axis
                state = MotorState(
                    Command.TORQUE,
                    int(rng.integers(-20, 120)),
                    float(rng.normal(0, 10)),
                    int(rng.integers(-30000, 30000)),
                    int(rng.integers(0, 65536)),  # any jump: wraps both ways
                )
                message = other if rng.random() < 0.1 else state
                received = None if rng.random() < 0.1 else float(rng.uniform(0, 100))
                replies.append(Reply(motor_id, state, message, received))
            keep_fresh = bool(rng.random() < 0.3)
            for axes in pair:
                axes.absorb(replies, keep_fresh=keep_fresh)
            assert _axes_arrays(pair[0]) == _axes_arrays(pair[1]), (seed, trial)


def test_absorb_in_c_leaves_what_it_cannot_take_to_the_python_loop() -> None:
    # Replies of odd types go to the Python loop, one by one, in their place among the others: the arrays end alike,
    # and what the Python loop refuses (memoryview: an encoder not an int64) it refuses with C too, having taken the
    # replies before it alike.
    rng = np.random.default_rng(9)
    axes, python = _axes_pair(rng, 3)
    plain = MotorState(Command.TORQUE, 30, 1.5, 100, 123)
    odd: Any = (31.5, 101.0)  # float temperature and speed, and an int current
    numbers = MotorState(Command.TORQUE, odd[0], 2, odd[1], 200)
    flag = MotorState(Command.TORQUE, True, 1.0, 10, 400)  # a bool: the Python loop's
    replies = [Reply(1, plain, plain, 1.0), Reply(2, numbers, numbers, 2), Reply(3, numbers, numbers, 3.0)]
    replies += [Reply(1, flag, flag, 5.0), Reply(3, plain, plain, 6.0)]
    for states in (axes, python):
        states.absorb(tuple(replies))
        states.absorb(iter(replies[::-1]))
    assert _axes_arrays(axes) == _axes_arrays(python)
    float_encoder = MotorState(Command.TORQUE, 32, 1.0, 10, cast(Any, 300.0))
    huge_encoder = MotorState(Command.TORQUE, 33, 1.0, 10, 2**70)
    for refused, error in (
        ([Reply(2, plain, plain, 7.0), Reply(1, float_encoder, float_encoder, 8.0)], TypeError),
        ([Reply(3, plain, plain, 9.0), Reply(1, huge_encoder, huge_encoder, 10.0)], ValueError),
        ([Reply(1, plain, plain, 11.0), (1, plain, 12.0)], ValueError),  # not a 4-tuple
    ):
        for states in (axes, python):
            with pytest.raises(error):
                states.absorb(refused)  # type: ignore[arg-type]
        assert _axes_arrays(axes) == _axes_arrays(python)


def test_the_c_absorber_is_used_only_for_what_it_doubles() -> None:
    class Geared(Transmission):  # its own conversions: the Python loop calls them
        pass

    specs = [AxisSpec("a", 1)]
    assert AxisStates(specs, ArmTransmission([_joint()]))._absorb_c is not None
    assert AxisStates(specs, ArmTransmission([Geared(6.0, 1, 0.0, 0.1)]))._absorb_c is None
    v3 = FAMILIES[ProtocolFamily.V3]
    assert AxisStates(specs, ArmTransmission([_joint()]), v3)._absorb_c is None


def test_the_c_absorber_refuses_arrays_it_cannot_hold_and_is_collected() -> None:
    from motion import _speedups

    n = 3
    floats = [np.zeros(n) for _ in range(7)]
    good = [np.zeros(n, np.int64), *floats, np.zeros(n, bool), *[np.ones(n) for _ in range(4)]]
    _speedups.StateAbsorber({1: 0}, MotorState, *good)
    for k, bad, message in (
        (0, np.zeros(n), r"encoder must be a one-dimensional int64 array"),
        (8, np.zeros(n), r"fresh must be a one-dimensional bool array"),
        (3, np.zeros(n + 1), r"iq_a has 4 entries, the first array 3"),
        (6, np.zeros(n)[::-1], r"q_deg must be a C-contiguous, writable float64 array"),
        (12, np.zeros(n, np.int64), r"offset must be a one-dimensional float64 array"),
    ):
        arrays = list(good)
        arrays[k] = bad
        with pytest.raises((TypeError, ValueError), match=message):
            _speedups.StateAbsorber({1: 0}, MotorState, *arrays)
    with pytest.raises(TypeError, match=r"takes 15 arguments"):
        _speedups.StateAbsorber({1: 0}, MotorState, *good[:-1])
    absorber = _speedups.StateAbsorber({1: 7}, MotorState, *good)
    state = MotorState(Command.TORQUE, 30, 1.5, 100, 123)
    with pytest.raises(ValueError, match=r"axis index 7 out of range"):
        absorber([Reply(1, state, state, 1.0)], 0, False)
    with pytest.raises(TypeError, match=r"replies must be a list or a tuple"):
        absorber(cast(Any, iter([])), 0, False)
    # The arrays are held for the absorber's life: an axis set and its absorber are collected together.
    axes = AxisStates([AxisSpec("a", 1)], ArmTransmission([_joint()]))
    watched = weakref.ref(axes.q_deg)
    del axes
    gc.collect()
    assert watched() is None


def test_a_snapshots_rows_are_stacked_in_c_as_numpy_stacks_them(monkeypatch: pytest.MonkeyPatch) -> None:
    from motion import _speedups

    rng = np.random.default_rng(3)
    rows = (rng.normal(0, 1, 5), np.array([True, False, True, True, False]), np.full(5, np.nan), -np.zeros(5))
    for given_rows in (rows, list(rows), (*rows[:3], np.arange(5)), (np.zeros(0),) * 2):
        stacked = snapshot_module.frozen(given_rows)
        monkeypatch.setattr(snapshot_module, "_C", None)
        expected = snapshot_module.frozen(given_rows)
        monkeypatch.undo()
        assert stacked.tobytes() == expected.tobytes() and stacked.shape == expected.shape
        assert stacked.dtype == np.float64 and not stacked.flags.writeable
    out = np.zeros((2, 3))
    with pytest.raises(TypeError, match=r"row 1 must be a one-dimensional float64 or bool array of 3 entries"):
        _speedups.stack_rows(out, (np.ones(3), np.ones(3, np.int64)))
    with pytest.raises(TypeError, match=r"rows must be a tuple of 2 arrays"):
        _speedups.stack_rows(out, (np.ones(3),))
    with pytest.raises(TypeError, match=r"out must be a C-contiguous, writable float64 matrix"):
        _speedups.stack_rows(np.zeros((3, 2)).T, (np.ones(3), np.ones(3)))
    assert out.tolist() == [[1.0] * 3, [0.0] * 3]  # the copy stopped at the refused row (frozen then asks numpy)
    with pytest.raises(ValueError, match=r"inhomogeneous"):
        snapshot_module.frozen((np.ones(3), np.ones(2)))  # numpy's own refusal, as without the extension


def _without_c(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every hot-path module on its Python path (as without the extension)."""
    for module in (tracking, controller_module, transmission_module, dynamics_module, axes_module, snapshot_module):
        assert module._C is compiled_module.SPEEDUPS is not None
        monkeypatch.setattr(module, "_C", None)
    monkeypatch.setattr(tracking, "_C_CHASE", None)


@pytest.mark.parametrize("mode", [ControlMode.POSITION, ControlMode.TORQUE])
def test_an_emulated_move_is_the_same_with_the_c_steps_and_without(
    mode: ControlMode, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The C twins of the cycle's steps (the set-points: torque_pd, torque_currents, gather_scaled in the feed-forward;
    # the tracking model: chase, moved_beyond, torque_advance, torque_law) against the Python ones, on a whole arm6
    # move in simulated time: every request sent and every measurement alike to the bit, and the model's expected
    # angles, speeds and lags too, but in torque mode, where its two matrix products sum in another order than
    # numpy's BLAS: there within 1e-9.
    runs: list[list[tuple[Any, ...]]] = []
    for accelerated in (True, False):
        if not accelerated:
            _without_c(monkeypatch)
        cycles: list[tuple[Any, ...]] = []
        with emulated_arm(arm_config("arm6.yaml", mode=mode), "sim", tmp_path, supervised=True) as rig:

            def record(controller: Any, start_s: float, replies: Any, cycles: list[Any] = cycles) -> None:
                model, sent = controller.tracking, controller.setpoints
                cycles.append(
                    (
                        start_s,
                        tuple(repr(reply.request) for reply in replies),
                        controller.axes.q_deg.tobytes(),
                        sent.torque_nm.tobytes(),
                        sent.limited.tobytes(),
                        sent.motor_angle_deg.tobytes(),
                        np.stack([model.expected_deg, model.expected_dps, model.lag_deg]),
                    )
                )

            rig.controller.cycle_hooks.append(record)
            if mode is ControlMode.TORQUE:
                assert rig.controller.feedforward is not None and rig.controller.tracking.inertia_kgm2 is not None
            supervisor = rig.supervisor
            assert supervisor is not None
            for target in ([40.0, -30.0, 45.0, 20.0, -25.0, 30.0], [0.0] * 6):
                supervisor.move_to(target, speed_scale=1.0)
                assert supervisor.wait(30.0)
        runs.append(cycles)
    assert len(runs[0]) > 300
    assert [cycle[:-1] for cycle in runs[0]] == [cycle[:-1] for cycle in runs[1]]
    with_c, without = np.array([cycle[-1] for cycle in runs[0]]), np.array([cycle[-1] for cycle in runs[1]])
    if mode is ControlMode.POSITION:
        assert with_c.tobytes() == without.tobytes()
    else:
        np.testing.assert_allclose(with_c, without, rtol=0.0, atol=1e-9)
        assert np.abs(with_c[:, 2]).max() > 0.01  # (the model expects a lag: it is not the reference itself)
