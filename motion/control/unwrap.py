"""The encoder's unwrapping envelope: how fast a joint may turn at the control rate for its turns to be counted.

Between two replies the controller takes the encoder's change the shortest way round (:mod:`motion.control.axes`):
the motor shaft must turn less than half a turn (:data:`~motion.control.axes.UNWRAP_BOUND_MOTOR_DEG`) from one sample
to the next. At the joint's velocity limit it turns ``velocity_limit_dps × |gear_ratio| / rate_hz`` motor degrees per
sample: a joint at or beyond the bound would lose whole turns at speed (and a 0x92 read would then show a jump no
motion explains), so it is refused at ``check --offline``, ``check`` and connect (:func:`check_unwrapping`), naming
its figures and the lowest rate that unwraps it. Drives whose motion replies carry no encoder (the V3 family) are read
with 0x92 in every cycle: their angle is never unwrapped, and no bound applies.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from motion.config.schema import ArmConfig, ProtocolSetting
from motion.control.axes import UNWRAP_BOUND_MOTOR_DEG
from motion.errors import ConfigError


@dataclass(frozen=True, slots=True)
class UnwrapHeadroom:
    """One joint's unwrapping figures at the control rate.

    Attributes:
        name: the joint.
        index: its place in ``joints:``.
        velocity_limit_dps: its velocity limit, joint deg/s.
        gear_ratio: its reduction (motor degrees per joint degree, in magnitude).
        motor_deg_per_sample: how far its motor turns between two samples at the joint's velocity limit, motor deg.
        bound_motor_deg: how far it may turn: half a turn, motor deg.
        lowest_rate_hz: the rate above which it unwraps at its velocity limit, Hz.
        highest_velocity_dps: the joint speed below which it unwraps at the configured rate, deg/s.
        reads_angle: its drive's angle is read (0x92) in every cycle: nothing is unwrapped, no bound applies.
    """

    name: str
    index: int
    velocity_limit_dps: float
    gear_ratio: float
    motor_deg_per_sample: float
    bound_motor_deg: float
    lowest_rate_hz: float
    highest_velocity_dps: float
    reads_angle: bool = False

    @property
    def holds(self) -> bool:
        """Whether the joint's turns are counted at its velocity limit (strictly under the bound: at half a turn the
        two ways round are the same length)."""
        return self.reads_angle or self.motor_deg_per_sample < self.bound_motor_deg

    @property
    def share(self) -> float:
        """The share of the bound one sample takes at the velocity limit (0 where nothing is unwrapped)."""
        return 0.0 if self.reads_angle else self.motor_deg_per_sample / self.bound_motor_deg

    def describe(self) -> str:
        """The figures in words (``check --offline``)."""
        if self.reads_angle:
            return f"{self.name}: its angle is read (0x92) in every cycle: nothing to unwrap"
        return (
            f"{self.name}: {self.motor_deg_per_sample:.1f} of {self.bound_motor_deg:g} motor deg per sample at its "
            f"velocity limit ({self.share:.0%}); unwraps above {self.lowest_rate_hz:.3g} Hz"
        )


def configured_reads_angle(config: ArmConfig) -> list[bool]:
    """Per joint, whether its drive's angle is read in every cycle as far as the configuration tells (offline): a
    joint on a bus whose ``protocol`` is ``v3``; ``auto`` counts as the older family (the stricter), as connect would
    find it unless the drives answer in V3."""
    return [config.buses[j.bus_index].protocol is ProtocolSetting.V3 for j in config.joints]


def unwrap_headroom(
    config: ArmConfig, reads_angle: Sequence[bool] | None = None, rate_hz: float | None = None
) -> list[UnwrapHeadroom]:
    """Every joint's :class:`UnwrapHeadroom` at ``rate_hz`` (None: ``control.rate_hz``); ``reads_angle``: per joint,
    whether its drive's angle is read in every cycle (its family, once connect knows it; None: as configured,
    :func:`configured_reads_angle`)."""
    rate = config.control.rate_hz if rate_hz is None else rate_hz
    reads = configured_reads_angle(config) if reads_angle is None else list(reads_angle)
    bound = UNWRAP_BOUND_MOTOR_DEG
    found = []
    for i, (joint, read) in enumerate(zip(config.joints, reads, strict=True)):
        gear = abs(joint.gear_ratio)
        motor_dps = joint.velocity_limit_dps * gear
        found.append(
            UnwrapHeadroom(
                joint.name,
                i,
                joint.velocity_limit_dps,
                gear,
                motor_deg_per_sample=motor_dps / rate,
                bound_motor_deg=bound,
                lowest_rate_hz=motor_dps / bound,
                highest_velocity_dps=bound * rate / gear,
                reads_angle=read,
            )
        )
    return found


def unwrap_problems(found: Sequence[UnwrapHeadroom], rate_hz: float) -> list[str]:
    """One line per joint whose turns are not counted at its velocity limit, naming its figures and what holds."""
    return [
        f"joint {h.name}: at its velocity_limit_dps {h.velocity_limit_dps:g} × gear_ratio {h.gear_ratio:g} / "
        f"control.rate_hz {rate_hz:g} its motor turns {h.motor_deg_per_sample:.1f} motor deg per sample, at or beyond "
        f"the {h.bound_motor_deg:g} motor deg (half a turn) within which the encoder's unwrapping tells its turns: "
        f"they would be lost at speed. Raise control.rate_hz above {h.lowest_rate_hz:.3g} Hz, or lower its "
        f"velocity_limit_dps below {h.highest_velocity_dps:.3g} deg/s"
        for h in found
        if not h.holds
    ]


def check_unwrapping(config: ArmConfig, reads_angle: Sequence[bool] | None = None) -> list[UnwrapHeadroom]:
    """Refuse a configuration whose velocity limits the encoder's unwrapping cannot follow at its rate (see
    :func:`unwrap_headroom` for ``reads_angle``); returns the figures.

    Raises:
        ConfigError: one or more joints beyond the bound (the first one's ``velocity_limit_dps`` as the key, a line
            per joint with its figures, the lowest rate that holds and the highest velocity limit that does).
    """
    found = unwrap_headroom(config, reads_angle)
    problems = unwrap_problems(found, config.control.rate_hz)
    if problems:
        first = next(h for h in found if not h.holds)
        raise ConfigError(config.source, f"joints[{first.index}].velocity_limit_dps", "\n".join(problems))
    return found
