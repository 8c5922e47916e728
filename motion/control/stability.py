"""Whether a joint's torque-mode PD is stable at the rate it runs at: a discrete-time gain margin of the sampled loop.

The host closes torque mode's loop: cycle *k* sends ``u = Kp (q_ref − q) + Kd (q̇_ref − q̇)`` computed from the state
the drives replied in cycle *k − 1*, and each drive holds that torque until the next cycle's frame. What decides the
loop's stability is therefore not the gains alone but the gains against the cycle: the state the torque acts on is a
period (plus the drive's own latency) old, the torque is held over the period (a zero-order hold), and the drive's
current loop lags the command. A PD that is stiff for a light joint at a low rate rings and then diverges (arm2's
example gains at 40 Hz: the elbow reached six times its velocity limit).

The model, per joint (the feed-forward cancels gravity; the reference's part is an input and does not change the
poles), in SI units::

    J q̈ = τ,    τc τ̇ = κ u − τ,    u(t) = −(Kp q + Kd q̇)(s_j)  for t ≥ s_j + D,

with ``J`` the inertia the joint sees, ``τc`` the current loop's time constant, ``κ`` the true torque constant over
the configured one, and ``D = T + L`` the time from the measurement at ``s_j`` to the torque it asks for taking
effect: one period ``T`` and the drive's latency ``L``. Integrated exactly over one period (the plant's transition
and input matrices in closed form, :func:`_transition`), the loop is a linear map on the last few samples; it is
stable while every eigenvalue of that map lies inside the unit circle. Friction only adds damping and is left out.

The **gain margin** is the factor by which ``Kp`` and ``Kd`` together (equivalently ``κ / J``) may grow before the
map's spectral radius reaches 1. It is computed at the stated bounds, where the loop is least stable:

- ``J``: the smallest inertia the joint sees anywhere in the joint limits, with the other joints free to move
  (``1 / (M⁻¹)ᵢᵢ`` of the arm's mass matrix, the coupling included, sampled over the limits by the caller), the
  model's masses at :data:`MASS_LOW` and the rotors' reflected inertia at :data:`ROTOR_INERTIA_LOW` of their figures;
- ``κ``: :data:`TORQUE_CONSTANT_HIGH` (the torque constant may be 20 % above the configured one);
- ``L``: :data:`LATENCY_S`, the drives' reply latency bound; ``τc``: :data:`CURRENT_LOOP_S`.

A configuration is accepted where every torque-mode joint keeps a margin of at least :data:`REQUIRED_MARGIN` there:
stable on every drive the stated bounds allow. The corner is itself the margin asked of the nominal drive: it bears
the torque constant 20 % up with the masses 20 % down (1.5 times the nominal loop gain) and five times the emulated
drives' latency, so that a configuration at the limit keeps about 1.65 (4.3 dB) on a drive as configured. Outside it
the check names the joint, its margin, the lowest rate at which its gains hold and the highest gains that hold at this
rate.

Gains from a bandwidth (:func:`gains_for_bandwidth`): ``Kp = J ω²``, ``Kd = 2 ζ J ω`` with ``ω = 2π f`` and ``ζ = 1``
(critically damped), at the *largest* inertia the joint sees (so that the bandwidth is at least ``f`` and the loop at
least critically damped at every pose; the margin is then checked at the smallest).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from motion.errors import ConfigError

#: The margin every torque-mode joint must keep at the stated bounds' corner: stable there (see the module docstring).
REQUIRED_MARGIN: Final = 1.0
#: The true torque constant may be this factor of the configured one (the stated bound: ±20 %).
TORQUE_CONSTANT_HIGH: Final = 1.2
#: The rotor's inertia may be this factor of the configured one (the stated bound: ±30 %).
ROTOR_INERTIA_LOW: Final = 0.7
#: The model's masses may be this factor of their figures (the stated bound of the model's mass error: ±20 %).
MASS_LOW: Final = 0.8
#: The drives' reply latency bound, s: the time a drive's measurement may precede the new torque taking effect beyond
#: the period (the drawn drive models' range reaches 1 ms).
LATENCY_S: Final = 0.001
#: The drives' current loop, as a first-order lag, s: 1 ms, a bandwidth of 1000 rad/s (a field-oriented drive's
#: current loop is faster; a slower one would show as a lower margin, so the bound is taken long).
CURRENT_LOOP_S: Final = 0.001
#: Damping ratio of the gains made from a bandwidth.
BANDWIDTH_DAMPING: Final = 1.0
#: The rates searched for the lowest that holds, Hz (the schema's range).
RATE_RANGE_HZ: Final = (1.0, 1000.0)
_DEG: Final = 180.0 / math.pi
#: Gain factors searched for the margin: from this up, in steps of :data:`_SCAN_STEP`, then bisected.
_SCAN_LOW: Final = 1.0 / 4096.0
_SCAN_HIGH: Final = 4096.0
_SCAN_STEP: Final = 1.25
_BISECTIONS: Final = 30


@dataclass(frozen=True, slots=True)
class LoopBounds:
    """What the margin is computed at besides the gains and the rate (see the module docstring)."""

    latency_s: float = LATENCY_S
    current_loop_s: float = CURRENT_LOOP_S
    torque_constant_high: float = TORQUE_CONSTANT_HIGH
    required_margin: float = REQUIRED_MARGIN


@dataclass(frozen=True, slots=True)
class JointLoop:
    """One torque-mode joint as the stability check sees it.

    Attributes:
        name: the joint.
        kp_nm_per_deg: its PD stiffness, N·m/deg.
        kd_nm_per_dps: its PD damping, N·m/(deg/s).
        inertia_low_kgm2: the smallest inertia it sees within the limits, the rotor's at its low bound, kg·m².
        inertia_high_kgm2: the largest it sees (its diagonal of M(q), the rotor's at its configured figure), kg·m².
    """

    name: str
    kp_nm_per_deg: float
    kd_nm_per_dps: float
    inertia_low_kgm2: float
    inertia_high_kgm2: float


@dataclass(frozen=True, slots=True)
class JointMargin:
    """The check's figures for one joint at one rate.

    Attributes:
        joint: the joint's loop.
        rate_hz: the rate checked.
        margin: the gain margin at the bounds (``inf``: no gain makes the loop unstable, or there are no gains).
        lowest_rate_hz: the lowest rate at which these gains keep the required margin (``nan``: none up to 1 kHz).
        required_margin: the margin asked for.
    """

    joint: JointLoop
    rate_hz: float
    margin: float
    lowest_rate_hz: float
    required_margin: float

    @property
    def holds(self) -> bool:
        """The joint keeps the required margin at this rate."""
        return self.margin >= self.required_margin

    @property
    def gain_scale(self) -> float:
        """The factor on both gains that would leave exactly the required margin at this rate."""
        return self.margin / self.required_margin

    def describe(self) -> str:
        """The figures in words (one line)."""
        j = self.joint
        margin = "unbounded" if math.isinf(self.margin) else f"{self.margin:.2f}"
        lowest = "none up to 1000 Hz" if math.isnan(self.lowest_rate_hz) else f"{self.lowest_rate_hz:.0f} Hz"
        return (
            f"{j.name}: gain margin {margin} at {self.rate_hz:g} Hz (needed {self.required_margin:g}; kp "
            f"{j.kp_nm_per_deg:g} N·m/deg, kd {j.kd_nm_per_dps:g} N·m/(deg/s), inertia from "
            f"{j.inertia_low_kgm2:.4g} kg·m²); lowest rate for these gains {lowest}; highest gains at this rate kp "
            f"{j.kp_nm_per_deg * self.gain_scale:.3g}, kd {j.kd_nm_per_dps * self.gain_scale:.3g}"
        )


def _transition(h_s: float, inertia_kgm2: float, lag_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The plant ``[q, q̇, τ]`` over ``h_s`` seconds under a constant command: ``x(h) = Φ x(0) + Γ u`` (SI)."""
    e = math.exp(-h_s / lag_s) if lag_s > 0.0 else 0.0
    settled = lag_s * (1.0 - e)  # ∫ of the lag's step response's complement
    phi = np.array(
        [
            [1.0, h_s, lag_s * (h_s - settled) / inertia_kgm2],
            [0.0, 1.0, settled / inertia_kgm2],
            [0.0, 0.0, e],
        ]
    )
    gamma = np.array(
        [
            (h_s * h_s / 2.0 - lag_s * h_s + lag_s * settled) / inertia_kgm2,
            (h_s - settled) / inertia_kgm2,
            1.0 - e,
        ]
    )
    return phi, gamma


def loop_matrix(
    kp_nm_per_rad: float, kd_nm_s_per_rad: float, inertia_kgm2: float, period_s: float, bounds: LoopBounds
) -> np.ndarray:
    """The sampled loop's map on its last samples ``[x_k, x_{k−1}, …]`` (see the module docstring)."""
    delay = period_s + bounds.latency_s
    whole = math.floor(delay / period_s + 1e-12)  # (≥ 1)
    rest = delay - whole * period_s
    if rest < 1e-12 * period_s:
        rest = 0.0
    phi_t, _ = _transition(period_s, inertia_kgm2, bounds.current_loop_s)
    phi_late, gamma_late = _transition(period_s - rest, inertia_kgm2, bounds.current_loop_s)
    _, gamma_early = _transition(rest, inertia_kgm2, bounds.current_loop_s)
    gain = -bounds.torque_constant_high * np.array([kp_nm_per_rad, kd_nm_s_per_rad, 0.0])
    blocks = whole + 2
    a = np.zeros((3 * blocks, 3 * blocks))
    a[0:3, 0:3] = phi_t
    # over [s_k + rest, s_{k+1}) the torque of sample k − whole, before it that of the sample before
    a[0:3, 3 * whole : 3 * whole + 3] += np.outer(gamma_late, gain)
    a[0:3, 3 * (whole + 1) : 3 * (whole + 2)] += np.outer(phi_late @ gamma_early, gain)
    for b in range(1, blocks):
        a[3 * b : 3 * b + 3, 3 * (b - 1) : 3 * b] = np.eye(3)
    return a


def spectral_radius(
    kp_nm_per_deg: float, kd_nm_per_dps: float, inertia_kgm2: float, rate_hz: float, bounds: LoopBounds
) -> float:
    """The largest eigenvalue magnitude of the loop's map (stable below 1)."""
    a = loop_matrix(kp_nm_per_deg * _DEG, kd_nm_per_dps * _DEG, inertia_kgm2, 1.0 / rate_hz, bounds)
    return float(np.max(np.abs(np.linalg.eigvals(a))))


@functools.lru_cache(maxsize=4096)  # (an arm connects many times with the same gains: the search is the cost)
def gain_margin(
    kp_nm_per_deg: float, kd_nm_per_dps: float, inertia_kgm2: float, rate_hz: float, bounds: LoopBounds = LoopBounds()
) -> float:
    """The factor on both gains at which the loop's spectral radius first reaches 1 (``inf`` past 4096).

    Raises:
        ValueError: a gain below 0, an inertia or a rate not above 0.
    """
    if not (kp_nm_per_deg >= 0.0 and kd_nm_per_dps >= 0.0 and inertia_kgm2 > 0.0 and rate_hz > 0.0):
        raise ValueError(
            f"the stability margin needs gains >= 0 and an inertia and a rate > 0: kp {kp_nm_per_deg}, kd "
            f"{kd_nm_per_dps}, inertia {inertia_kgm2} kg·m², rate {rate_hz} Hz"
        )
    if kp_nm_per_deg == 0.0 and kd_nm_per_dps == 0.0:
        return math.inf  # no feedback: nothing to make unstable

    def stable(g: float) -> bool:
        return spectral_radius(g * kp_nm_per_deg, g * kd_nm_per_dps, inertia_kgm2, rate_hz, bounds) < 1.0

    low, high = 0.0, _SCAN_LOW
    while stable(high):
        low, high = high, high * _SCAN_STEP
        if high > _SCAN_HIGH:
            return math.inf
    if low == 0.0:
        return 0.0  # unstable at the smallest factor searched: no margin worth the name
    for _ in range(_BISECTIONS):
        middle = math.sqrt(low * high)
        low, high = (middle, high) if stable(middle) else (low, middle)
    return low


def lowest_rate_hz(loop: JointLoop, bounds: LoopBounds = LoopBounds()) -> float:
    """The lowest rate at which ``loop``'s gains keep the required margin, Hz (``nan``: none up to 1 kHz)."""
    low, high = RATE_RANGE_HZ

    def holds(rate: float) -> bool:
        return (
            gain_margin(loop.kp_nm_per_deg, loop.kd_nm_per_dps, loop.inertia_low_kgm2, rate, bounds)
            >= bounds.required_margin
        )

    if not holds(high):
        return math.nan
    if holds(low):
        return low
    for _ in range(24):  # (to well under 0.1 Hz)
        middle = math.sqrt(low * high)
        low, high = (low, middle) if holds(middle) else (middle, high)
    return high


def joint_margin(loop: JointLoop, rate_hz: float, bounds: LoopBounds = LoopBounds()) -> JointMargin:
    """``loop``'s margin at ``rate_hz`` and the lowest rate that holds."""
    margin = gain_margin(loop.kp_nm_per_deg, loop.kd_nm_per_dps, loop.inertia_low_kgm2, rate_hz, bounds)
    return JointMargin(loop, rate_hz, margin, lowest_rate_hz(loop, bounds), bounds.required_margin)


@dataclass(frozen=True, slots=True)
class StabilityReport:
    """Every torque-mode joint's margin at one rate."""

    rate_hz: float
    joints: tuple[JointMargin, ...]

    @property
    def failing(self) -> tuple[JointMargin, ...]:
        """The joints without the required margin."""
        return tuple(j for j in self.joints if not j.holds)

    @property
    def lowest_rate_hz(self) -> float:
        """The lowest rate at which every joint holds (``nan``: some joint holds at none up to 1 kHz)."""
        rates = [j.lowest_rate_hz for j in self.joints]
        return max(rates) if rates else RATE_RANGE_HZ[0]

    def describe_failing(self) -> str:
        """The joints without margin in words, one sentence each."""
        return "; ".join(j.describe() for j in self.failing)


def stability_report(loops: Sequence[JointLoop], rate_hz: float, bounds: LoopBounds = LoopBounds()) -> StabilityReport:
    """The margin of every loop in ``loops`` at ``rate_hz``."""
    return StabilityReport(rate_hz, tuple(joint_margin(loop, rate_hz, bounds) for loop in loops))


def gains_for_bandwidth(bandwidth_hz: float, inertia_kgm2: float) -> tuple[float, float]:
    """``(kp N·m/deg, kd N·m/(deg/s))`` that give a critically damped loop of ``bandwidth_hz`` on ``inertia_kgm2``
    (continuous time: the rate's margin is checked apart).

    Raises:
        ValueError: a bandwidth or inertia not above 0.
    """
    if not (bandwidth_hz > 0.0 and inertia_kgm2 > 0.0):
        raise ValueError(f"a bandwidth and an inertia > 0 are needed: {bandwidth_hz} Hz, {inertia_kgm2} kg·m²")
    omega = 2.0 * math.pi * bandwidth_hz
    return inertia_kgm2 * omega * omega / _DEG, 2.0 * BANDWIDTH_DAMPING * inertia_kgm2 * omega / _DEG


class StabilityError(ConfigError):
    """Torque mode's PD loop of some joint has no margin at the configured rate (a configuration error: nothing
    moved). ``report`` holds every joint's figures."""

    def __init__(self, source: str, report: StabilityReport) -> None:
        self.report = report
        lowest = report.lowest_rate_hz
        floor = (
            "no rate up to 1000 Hz holds these gains"
            if math.isnan(lowest)
            else f"the lowest rate at which every joint's gains hold is {lowest:.0f} Hz"
        )
        super().__init__(
            source,
            "control.rate_hz",
            f"torque mode's PD loop is not stable with margin at {report.rate_hz:g} Hz on drives within the stated "
            f"bounds (torque constant +{TORQUE_CONSTANT_HIGH - 1:.0%}, masses -{1 - MASS_LOW:.0%}, rotor inertia "
            f"-{1 - ROTOR_INERTIA_LOW:.0%}, the lightest pose in the limits, {LATENCY_S * 1e3:g} ms latency): "
            f"{report.describe_failing()}; {floor} (raise control.rate_hz, lower the joint's kp_nm_per_deg and "
            "kd_nm_per_dps, or give bandwidth_hz)",
        )
