"""Published figures of MyActuator RMD actuators, for a joint's ``actuator:`` key (issue 33 §9): it fills the joint's
``gear_ratio``, ``torque_constant_nm_per_a`` (motor side) and ``current_limit_a`` (the peak current where published
and within what the torque command carries, else the key stays required); each stays overridable in the joint.

The torque constant is the published torque over the published current (the tables give both, rated), divided by the
reduction: torque per ampere of the drive's torque current at the motor, as the joint's key means it. The figures are
MyActuator's as the cited pages give them; a drive's own figures vary (the collision check bears ±20 % on the torque
constant: :mod:`motion.safety.collision_bound`). Not yet in the table, for want of a published source reachable here:
the L series other than the L-7015, and the peak currents of most X models (their ``current_limit_a`` is then
required). The MG rows take the stall current as the peak.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

#: MyActuator's X-series pages, as the ROS package myactuator_rmd (``actuator_constants.hpp``) cites them per model.
_PRODUCT_PAGES: Final = "https://www.myactuator.com/{page} (via docs.ros.org/en/humble/p/myactuator_rmd)"
#: Seeed Studio's table of the X series (rated and peak torque and current, module torque constant).
_SEEED: Final = "https://wiki.seeedstudio.com/myactuator_series (specification table)"
#: MyActuator's RMD-L-7015 specification table (direct drive, MC200 driver: 8 A rated, 15 A instant), as the
#: myactuator_rmd fork of github.com/whyscience transcribes it in ``actuator_constants.hpp``.
_L7015: Final = "MyActuator RMD-L-7015 specification (via github.com/whyscience/myactuator_rmd actuator_constants.hpp)"
#: A reseller's table of the MG series (nominal torque and current, stall current, the models' reductions).
_MG: Final = "https://shop.smc-powers.com/MG8016-6-DUO-RS485.html (MG series specification table)"


@dataclass(frozen=True, slots=True)
class Actuator:
    """One model's published figures.

    Attributes:
        model: the model's name as the ``actuator:`` key takes it (``X8-90``).
        gear_ratio: its reduction, motor turns per output turn.
        rated_torque_nm: rated output torque, N·m.
        rated_current_a: rated current, A.
        peak_current_a: peak current, A (None: not published in the source).
        source: where the figures come from.
    """

    model: str
    gear_ratio: float
    rated_torque_nm: float
    rated_current_a: float
    peak_current_a: float | None
    source: str

    @property
    def torque_constant_nm_per_a(self) -> float:
        """Motor-side torque constant, N·m/A: rated torque over rated current, over the reduction."""
        return self.rated_torque_nm / self.rated_current_a / self.gear_ratio


def _page(model: str, page: str, gear: float, torque: float, current: float) -> Actuator:
    return Actuator(model, gear, torque, current, None, _PRODUCT_PAGES.format(page=page))


def _seeed(model: str, gear: float, torque: float, current: float, peak: float) -> Actuator:
    return Actuator(model, gear, torque, current, peak, _SEEED)


def _mg(model: str, gear: float, torque: float, current: float, stall: float) -> Actuator:
    return Actuator(model, gear, torque, current, stall, _MG)


#: The models, by name.
ACTUATORS: Final[Mapping[str, Actuator]] = {
    a.model: a
    for a in (
        _page("X4-V2", "product-page/rmd-x4-1-10", 10.0, 1.0, 1.6),
        _page("X4-V3", "product-page/rmd-x4-1-6", 6.0, 1.2, 3.0),
        _page("X4-24", "x4-24-details", 36.0, 9.0, 3.5),
        _page("X6-40", "x6-40-details", 36.0, 18.0, 5.2),
        _page("X8-PRO-V2", "product-page/x8-pro-1-9", 9.0, 13.0, 5.0),
        _page("X8-90", "x8-90-details", 18.0, 25.0, 10.0),
        _page("X10-V3", "product-page/rmd-x10", 7.0, 12.0, 5.3),
        _page("X10-40", "x10-40-details", 7.0, 15.0, 6.5),
        _page("X10-100", "x10-100-details", 35.0, 50.0, 6.7),
        _page("X12-150", "x12-150-details", 12.0, 50.0, 15.0),
        _page("X15-400", "x15-400-details", 11.4, 130.0, 23.0),
        _seeed("X2-7", 28.17, 2.5, 3.0, 8.1),
        _seeed("X4-10", 12.6, 4.0, 7.8, 19.5),
        _seeed("X4-36", 36.0, 10.5, 6.1, 21.5),
        _seeed("X8-120", 19.61, 43.0, 17.6, 43.8),
        _seeed("X12-320", 20.0, 85.0, 30.0, 100.0),
        _seeed("X15-450", 20.25, 145.0, 25.0, 69.2),
        Actuator("L-7015", 1.0, 1.0, 3.62, 15.0, _L7015),
        _mg("MG4005-10", 10.0, 1.0, 1.6, 4.0),
        _mg("MG4010-10", 10.0, 2.5, 3.5, 6.97),
        _mg("MG4010-36", 36.0, 9.0, 3.5, 6.97),
        _mg("MG5010-10", 10.0, 4.0, 4.4, 6.7),
        _mg("MG6010-6", 6.0, 5.0, 3.8, 8.0),
        _mg("MG6012-8", 8.0, 5.0, 3.8, 8.0),
        _mg("MG6012-36", 36.0, 15.0, 3.8, 8.0),
        _mg("MG8008-9", 9.0, 10.0, 4.9, 10.0),
        _mg("MG8010-6", 6.0, 9.0, 4.9, 7.0),
        _mg("MG8010-36", 36.0, 35.0, 6.9, 9.0),
        _mg("MG8016-6", 6.0, 13.0, 6.5, 12.5),
        _mg("MG10015-10", 10.0, 30.0, 8.0, 13.0),
    )
}
