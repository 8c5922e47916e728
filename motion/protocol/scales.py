"""Physical scales shared by the command table and by the joint transmission.

Each scale is an exact fraction ``(numerator, denominator)``: physical = raw * numerator / denominator.
"""

from __future__ import annotations

from typing import Final

#: Torque current: raw -2000..2000 <-> -32..32 A (both documents, command side), 0.016 A per LSB.
IQ_SCALE: Final = (32, 2000)
#: Largest torque-current command in raw units (0xA1 and the 0x280 multi-motor frame).
IQ_RAW_LIMIT: Final = 2000
#: Angles on the wire: 0.01 degree per LSB.
CENTIDEGREE: Final = (1, 100)


def iq_amps(raw: int) -> float:
    """Convert a raw torque-current value to amperes."""
    return raw * IQ_SCALE[0] / IQ_SCALE[1]


def iq_raw(amps: float) -> int:
    """Convert amperes to the nearest raw torque-current value (no range check; the encoder checks)."""
    return round(amps * IQ_SCALE[1] / IQ_SCALE[0])
