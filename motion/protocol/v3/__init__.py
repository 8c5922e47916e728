"""The V3-driver protocol family (MyActuator "Servo Motor Control Protocol" V4.2): messages, table and framing.

The drives sold since about 2022 speak it: replies on ``0x240 + id``, float32 PID parameters by index, a 16-bit error
word, RS485 frames ``3E id 08 <the CAN bytes> CRC16``. The older family (CAN v2.3, RS485 v1.62) is
:mod:`motion.protocol`.
"""

from __future__ import annotations

from motion.protocol.v3 import frames
from motion.protocol.v3.messages import CommandV3
from motion.protocol.v3.table import COMMANDS_V3, RS485_COMMANDS

__all__ = ["COMMANDS_V3", "RS485_COMMANDS", "CommandV3", "frames"]
