"""What a drive's protocol family changes in control (issue 17), declared once per family.

The controller looks each joint's drive's family up once (``FAMILIES[bus.family_of(address)]``: its bus's; an arm's
buses may have drives of both families) and it, the axis states, the watchdog and the supervisor follow what each
joint's :class:`DriveFamily` says; no other control code asks which family a bus speaks.

The V3 family differs in what control needs in these ways (V4.2 document; decisions in ``docs/protocol.md``):

* its drives report and take the angles and speeds of their **output shaft** (their own reduction applied): the
  controller keeps working in motor degrees (the transmission's convention) and converts at the wire by each axis'
  ``drive_gear_ratio``;
* its motion replies carry the angle in **whole degrees** and no encoder, so the precise multi-turn angle (0x92,
  0.01 deg) is read in every cycle's batch: twice the frames of the older family (see ``bench/``);
* 0x280 broadcasts one command, so torque goes out as 0xA1 per joint;
* the drive plans its own trapezoid on 0xA4 unless its position-planning accelerations are 0 (set at connect, restored
  at close), it stops by itself when no frame comes for its communication-loss time (0xB3, set at connect), and it
  has holding brakes (0x77 / 0x78);
* its 0x9A carries a 16-bit error word (other bits than the older family's flags), there is no 0x9B to clear errors
  (level-2 errors clear themselves), and a drive that restarted shows in its runtime (0xB1), which starts again.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from motion.protocol import Bare, Command, ErrorFlags, Message, MotorState, Status1
from motion.protocol.generation import GENERATIONS
from motion.protocol.scales import IQ_SCALE
from motion.protocol.table import Direction, ProtocolFamily, WireProtocol, field_range, field_spec
from motion.protocol.v3.messages import (
    AccelerationIndex,
    BareV3,
    CommandV3,
    MotorStateV3,
    Status1V3,
    SystemErrorFlags,
)


@dataclass(frozen=True, slots=True)
class DriveFamily:
    """What control does differently for the drives of one protocol family.

    Attributes:
        family: the protocol family.
        output_shaft: the drives report and take output-shaft angles and speeds (their reduction applied).
        angle_every_cycle: the motion replies lack a fine angle: 0x92 is read in every cycle's batch.
        multi_torque_frame: 0x280 carries the torque currents of motors 1..4 (else torque goes as 0xA1 per joint).
        reads_loop_settings: the tracking model reads the drives' 0x30 gains and 0x33 acceleration (older shapes).
        clears_errors: the drives have 0x9B (clear error flags).
        restart_read: the read that shows a drive that restarted (0x92: its angle jumps while the tracked encoder
            does not; 0xB1: its runtime starts again).
        tells_runtime: the drives tell the time since their power-on (0xB1): a drive that has run since a record
            of it is known to have kept its counts (:mod:`motion.control.turns`, :mod:`motion.control.drivesetup`).
        link_protection: the drives have the communication-loss protection (0xB3).
        brakes: the drives have holding-brake commands (0x77 release, 0x78 lock).
        planning_accelerations: the 0x42 / 0x43 indexes set to 0 while streaming 0xA4 (empty: none).
        low_voltage: the error bit of an under-voltage.
        over_temperature: the error bit of an over-temperature.
        status_type: the 0x9A reply's message class.
        state_type: the motion replies' message class.
        speed_step_dps: the step of the motion replies' speed field, in the drive's units (deg/s).
        current_step_a: the step of the motion replies' torque-current field, A.
        max_speed_dps: the largest 0xA4 speed cap on CAN, in the drive's units (deg/s).
        rs485_max_speed_dps: the same on RS485.
        max_speed_step_dps: the step of the 0xA4 speed cap on CAN, in the drive's units (deg/s).
        rs485_max_speed_step_dps: the same on RS485.
    """

    family: ProtocolFamily
    output_shaft: bool
    angle_every_cycle: bool
    multi_torque_frame: bool
    reads_loop_settings: bool
    clears_errors: bool
    restart_read: int
    tells_runtime: bool
    link_protection: bool
    brakes: bool
    planning_accelerations: tuple[AccelerationIndex, ...]
    low_voltage: int
    over_temperature: int
    status_type: type[Message]
    state_type: type[Message]
    speed_step_dps: float
    current_step_a: float
    max_speed_dps: float
    rs485_max_speed_dps: float
    max_speed_step_dps: float
    rs485_max_speed_step_dps: float

    def bare(self, code: int) -> Message:
        """The family's request without data for ``code`` (0x80, 0x81, 0x92, 0x9A, 0x9C, ...)."""
        return GENERATIONS[self.family].bare(code)

    def speed_ceiling_dps(self, wire: WireProtocol) -> float:
        """The largest 0xA4 speed cap ``wire`` carries, in the drive's units."""
        return self.rs485_max_speed_dps if wire is WireProtocol.RS485 else self.max_speed_dps

    def speed_cap_step_dps(self, wire: WireProtocol) -> float:
        """The step of the 0xA4 speed cap ``wire`` carries, in the drive's units."""
        return self.rs485_max_speed_step_dps if wire is WireProtocol.RS485 else self.max_speed_step_dps


_A4_V2: Final = Command.MULTI_TURN_POSITION_SPEED
_A4_V3: Final = CommandV3.MULTI_TURN_POSITION_SPEED


def _step(command: Command | CommandV3, direction: Direction, wire: WireProtocol, field: str) -> float:
    """The step of a field, as its table declares it, in its physical unit."""
    spec = field_spec(command, direction, wire, field)
    return spec.num / spec.den


#: Each family's capabilities.
FAMILIES: Final[Mapping[ProtocolFamily, DriveFamily]] = {
    ProtocolFamily.V2: DriveFamily(
        family=ProtocolFamily.V2,
        output_shaft=False,
        angle_every_cycle=False,
        multi_torque_frame=True,
        reads_loop_settings=True,
        clears_errors=True,
        restart_read=Command.READ_MULTI_TURN_ANGLE,
        tells_runtime=False,
        link_protection=False,
        brakes=False,
        planning_accelerations=(),
        low_voltage=ErrorFlags.LOW_VOLTAGE,
        over_temperature=ErrorFlags.OVER_TEMPERATURE,
        status_type=Status1,
        state_type=MotorState,
        speed_step_dps=_step(Command.READ_STATUS_2, Direction.REPLY, WireProtocol.CAN, "speed_dps"),
        current_step_a=IQ_SCALE[0] / IQ_SCALE[1],
        max_speed_dps=field_range(_A4_V2, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps")[1],
        rs485_max_speed_dps=field_range(_A4_V2, Direction.REQUEST, WireProtocol.RS485, "max_speed_dps")[1],
        max_speed_step_dps=_step(_A4_V2, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps"),
        rs485_max_speed_step_dps=_step(_A4_V2, Direction.REQUEST, WireProtocol.RS485, "max_speed_dps"),
    ),
    ProtocolFamily.V3: DriveFamily(
        family=ProtocolFamily.V3,
        output_shaft=True,
        angle_every_cycle=True,
        multi_torque_frame=False,
        reads_loop_settings=False,
        clears_errors=False,
        restart_read=CommandV3.READ_RUNTIME,
        tells_runtime=True,
        link_protection=True,
        brakes=True,
        planning_accelerations=(AccelerationIndex.POSITION_ACCELERATION, AccelerationIndex.POSITION_DECELERATION),
        low_voltage=SystemErrorFlags.LOW_VOLTAGE,
        over_temperature=SystemErrorFlags.OVER_TEMPERATURE,
        status_type=Status1V3,
        state_type=MotorStateV3,
        speed_step_dps=_step(CommandV3.READ_STATUS_2, Direction.REPLY, WireProtocol.CAN, "speed_dps"),
        current_step_a=0.01,  # (the V3 table's iq: int16, 0.01 A)
        max_speed_dps=field_range(_A4_V3, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps")[1],
        rs485_max_speed_dps=field_range(_A4_V3, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps")[1],
        max_speed_step_dps=_step(_A4_V3, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps"),
        rs485_max_speed_step_dps=_step(_A4_V3, Direction.REQUEST, WireProtocol.CAN, "max_speed_dps"),
    ),
}

#: Every family's status and motion-reply classes (a watchdog accepts either: a bus only ever yields its own).
STATUS_TYPES: Final = (Status1, Status1V3)
STATE_TYPES: Final = (MotorState, MotorStateV3)
#: Every family's message of a command without data (the echo of 0x80, 0x81, 0x77, 0x78, ...).
BARE_TYPES: Final = (Bare, BareV3)
