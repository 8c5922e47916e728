"""One emulated RMD drive: the behaviour of every command of both documents and the drive's control loops.

States (:class:`RunState`): a drive powers up OFF (no current, the motor coasts). A control command (0xA0..0xA8, or
the 0x280 multi-motor frame) makes it RUNNING in that command's mode. 0x81 stops it: it brakes to zero speed at its
acceleration limit, then holds that position, keeping the command; 0x88 resumes the command. 0x80 turns it OFF and
forgets the command (0x88 then has nothing to resume). A new control command while STOPPED runs at once. While an
error flag is set (under-voltage, over-temperature) the drive is OFF and ignores control commands; 0x9B clears a flag
only once its cause is gone, after which a new control command is needed.

Loops (motor side, run every integration step): position (P with braking curve ``v <= sqrt(2 a |e|)``, capped at the
max speed, plus a small integral near the target) -> speed reference slewed at the acceleration limit -> speed PI ->
iq reference capped at the current limit (not in torque mode, per 0xA1's memo) and at what the supply voltage can
drive against the back-EMF -> current loop as a first-order lag -> torque ``kt × iq``. Gain scales: see
:mod:`motion.emulator.model`.

Angles: the shaft's mechanical angle counts encoder counts continuously. At power-on the multi-turn angle starts at the
single-turn angle (0..360 deg, encoder minus offset), as on a drive without a multi-turn battery. 0x91 / 0x19 write the
ROM offset, used from the next power cycle (per the documents); 0x95 zeroes the angles at once until power-off.
Position targets are kept as shaft angles, so zeroing does not move the motor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum
from typing import Final

from motion.emulator.model import (
    ANGLE_KI_PER_S2,
    ANGLE_KP_PER_S,
    HARDWARE_CURRENT_LIMIT_A,
    IQ_KP_RAD_S,
    SPEED_KI_RAD_S,
    SPEED_KP_RAD_S,
    DriveModel,
)
from motion.protocol.messages import (
    Acceleration,
    Bare,
    Command,
    EncoderOffset,
    EncoderReading,
    ErrorFlags,
    IncrementalPosition,
    IncrementalPositionSpeed,
    Message,
    MotorState,
    MultiTurnAngle,
    MultiTurnPosition,
    MultiTurnPositionSpeed,
    OpenLoopControl,
    OpenLoopState,
    PhaseCurrents,
    PidGains,
    ProductInfo,
    SingleTurnAngle,
    SingleTurnPosition,
    SingleTurnPositionSpeed,
    SpeedControl,
    SpinDirection,
    Status1,
    TorqueControl,
)
from motion.protocol.scales import CENTIDEGREE
from motion.protocol.table import COMMANDS, Direction, WireProtocol, command_of, field_range

_RAD_PER_DEG: Final = math.pi / 180.0
_DEG_PER_RAD: Final = 180.0 / math.pi
#: Copper losses of a three-phase winding with amplitude-invariant dq currents: P = 3/2 R iq².
_COPPER_LOSS_FACTOR: Final = 1.5
#: The position loop integrates only within this distance of the target, deg: outside it the speed loop's own
#: integral already removes steady errors, and an outer integral would wind up during a move and overshoot.
_ANGLE_INTEGRAL_BAND_DEG: Final = 1.0
#: The position loop's integral term may add at most this fraction of the max speed.
_ANGLE_INTEGRAL_SHARE: Final = 0.1
_THIRD_TURN_RAD: Final = 2.0 * math.pi / 3.0


def _field_limits(command: Command, direction: Direction, name: str) -> tuple[float, float]:
    """Smallest and largest physical value of a field (the CAN layout: both transports carry the same values)."""
    return field_range(command, direction, WireProtocol.CAN, name)


#: Reply values saturate at what their fields carry (a drive cannot report more), instead of failing to encode.
_IQ_REPLY_MAX_A: Final = _field_limits(Command.READ_STATUS_2, Direction.REPLY, "iq_a")[1]
_SPEED_REPLY_MAX_DPS: Final = _field_limits(Command.READ_STATUS_2, Direction.REPLY, "speed_dps")[1]
_PHASE_REPLY_MAX_A: Final = _field_limits(Command.READ_STATUS_3, Direction.REPLY, "ia_a")[1]
_VOLTAGE_REPLY_MAX_V: Final = _field_limits(Command.READ_STATUS_1, Direction.REPLY, "voltage_v")[1]
_TEMPERATURE_REPLY_C: Final = _field_limits(Command.READ_STATUS_1, Direction.REPLY, "temperature_c")
#: Open-loop power of 0xA0 at the full supply voltage (the request field's largest value).
_OPEN_LOOP_FULL_SCALE: Final = _field_limits(Command.OPEN_LOOP, Direction.REQUEST, "power")[1]
#: Single-turn angles are carried in 0.01 deg.
_CENTIDEGREES_PER_DEG: Final = CENTIDEGREE[1] // CENTIDEGREE[0]


class RunState(Enum):
    """Whether the drive drives."""

    OFF = "off"  #: no current; the motor coasts (power-on, 0x80, or while an error flag is set)
    STOPPED = "stopped"  #: 0x81: brakes to zero speed and holds position; the command is kept for 0x88
    RUNNING = "running"  #: executing the last control command


class DriveLoop(Enum):
    """Which loop the last control command closes."""

    OPEN_LOOP = "open_loop"  #: 0xA0: a fraction of the supply voltage
    TORQUE = "torque"  #: 0xA1 and the 0x280 multi-motor frame: torque current
    SPEED = "speed"  #: 0xA2
    POSITION = "position"  #: 0xA3..0xA8
    MOTION = "motion"  #: V3 family's motion frame (0x400 + id): the drive's own PD on position and speed


@dataclass(frozen=True, slots=True)
class Setpoint:
    """The last control command as the drive keeps it (for 0x88).

    Attributes:
        command: the command that set it.
        mode: the loop it closes.
        value: power -1000..1000 (open loop), iq in A (torque), speed in motor dps (speed), or the target as a
            shaft angle in degrees (position).
        max_speed_dps: speed cap of the position modes, motor dps.
    """

    command: Command
    mode: DriveLoop
    value: float
    max_speed_dps: float = 0.0


def _clamp(x: float, limit: float) -> float:
    return -limit if x < -limit else (limit if x > limit else x)


class EmulatedDrive:
    """One drive on the bus: answers requests and, every integration step, turns plant state into torque.

    Args:
        motor_id: bus id 1..32.
        model: motor, power stage and ROM parameters.
        tuned_inertia_kgm2: motor-side inertia the speed loop is scaled for when ``model.tuned_inertia_kgm2`` is
            None, kg·m².
    """

    def __init__(self, motor_id: int, model: DriveModel, tuned_inertia_kgm2: float) -> None:
        self.motor_id = motor_id
        self.model = model
        self._counts_per_rev = 1 << model.encoder_bits
        self._field_shift = max(0, model.encoder_bits - 16)
        self._deg_per_count = 360.0 / self._counts_per_rev
        self._shaft_deg_per_rad = model.gear_ratio * _DEG_PER_RAD
        self._torque_per_a = model.gear_ratio * model.torque_constant_nm_per_a
        self._tuned_inertia = model.tuned_inertia_kgm2 or tuned_inertia_kgm2
        self._thermal_capacity = model.thermal_time_constant_s / model.thermal_resistance_k_per_w
        #: ROM: survives power cycles.
        self.pid_rom = replace(model.pid, command=Command.READ_PID)
        self._offset_rom = (model.encoder_offset << self._field_shift) % self._counts_per_rev
        #: Physical state: kept across power cycles.
        self._shaft_deg = model.shaft_zero_deg
        self._speed_dps = 0.0
        self.temperature_c = model.ambient_c
        #: Fault overrides set by the emulator's fault schedule (None: no fault).
        self.voltage_override_v: float | None = None
        self.temperature_floor_c: float | None = None
        self.iq_a = 0.0
        self._iq_dt_s = math.nan
        self._iq_alpha = 0.0
        #: RAM and loop state, (re)set by power_cycle() and the commands.
        self.pid = self.pid_rom
        self.acceleration_dps2 = model.acceleration_dps2
        self.errors = ErrorFlags.NONE
        self.state = RunState.OFF
        self.setpoint: Setpoint | None = None
        self._offset_ram = self._offset_rom
        self._ref_counts = 0
        self._hold_deg: float | None = None
        self._speed_ref = 0.0
        self._speed_integral = 0.0
        self._angle_integral = 0.0
        self.power_cycle()

    # --- power and RAM --------------------------------------------------------------------------------------------

    def power_cycle(self) -> None:
        """Switch the drive off and on: RAM gets ROM values (PID, acceleration, encoder offset), angles restart."""
        self.pid = self.pid_rom
        self._apply_gains()
        self.acceleration_dps2 = self.model.acceleration_dps2
        self._offset_ram = self._offset_rom
        self._ref_counts = self._frame_at_power_up(self._counts())
        self.errors = ErrorFlags.NONE
        self._turn_off()

    def _frame_at_power_up(self, counts: int) -> int:
        """The encoder count where the drive's multi-turn angle is 0 after a power-up at ``counts``: the angle starts
        at the single-turn reading, 0..360 motor degrees (no multi-turn battery)."""
        return counts - (counts - self._offset_ram) % self._counts_per_rev

    def _gain_units(self) -> tuple[float, float, float, float, float]:
        """The loop gains in the documents' units: angle kp, angle ki, speed kp, speed ki, current kp."""
        g = self.pid
        return g.angle_kp, g.angle_ki, g.speed_kp, g.speed_ki, g.iq_kp

    def _apply_gains(self) -> None:
        angle_kp, angle_ki, speed_kp, speed_ki, iq_kp = self._gain_units()
        self._kp_angle = angle_kp * ANGLE_KP_PER_S
        self._ki_angle = angle_ki * ANGLE_KI_PER_S2
        # Speed loop: a gain unit is a bandwidth at the tuned inertia; convert N·m per rad/s to A per dps.
        speed_nm_s_per_rad = self._tuned_inertia * speed_kp * SPEED_KP_RAD_S
        self._kp_speed = speed_nm_s_per_rad / self.model.torque_constant_nm_per_a * _RAD_PER_DEG
        self._ki_speed = self._kp_speed * speed_ki * SPEED_KI_RAD_S
        self._iq_bandwidth = iq_kp * IQ_KP_RAD_S
        self._iq_dt_s = math.nan

    def _turn_off(self) -> None:
        self.state = RunState.OFF
        self.setpoint = None
        self.iq_a = 0.0
        self._hold_deg = None

    # --- what the drive measures ----------------------------------------------------------------------------------

    def observe(self, joint_rad: float, joint_velocity_rad_s: float) -> None:
        """Read the plant's joint state (rad, rad/s) through the gear."""
        self._shaft_deg = self.model.shaft_zero_deg + joint_rad * self._shaft_deg_per_rad
        self._speed_dps = joint_velocity_rad_s * self._shaft_deg_per_rad

    def _counts(self) -> int:
        """Shaft angle in whole encoder counts since the mechanical zero (multi-turn)."""
        return math.floor(self._shaft_deg / self._deg_per_count)

    @property
    def angle_deg(self) -> float:
        """Multi-turn angle in the drive's frame (not quantised), motor degrees."""
        return self._shaft_deg - self._ref_counts * self._deg_per_count

    @property
    def speed_dps(self) -> float:
        """Shaft speed, motor deg/s."""
        return self._speed_dps

    @property
    def voltage_v(self) -> float:
        """Supply voltage, V."""
        return self.model.supply_voltage_v if self.voltage_override_v is None else self.voltage_override_v

    @property
    def encoder_raw(self) -> int:
        """Raw single-turn encoder position, counts (0 .. 2^bits - 1)."""
        return self._counts() % self._counts_per_rev

    @property
    def encoder(self) -> int:
        """Encoder position minus the active offset, counts (0 .. 2^bits - 1)."""
        return (self._counts() - self._offset_ram) % self._counts_per_rev

    @property
    def encoder_offset(self) -> int:
        """Active (RAM) encoder offset, counts."""
        return self._offset_ram

    def _field(self, counts: int) -> int:
        """Encoder counts as carried in a uint16 reply field (top 16 bits of encoders above 16 bits)."""
        return counts >> self._field_shift

    # --- control loops --------------------------------------------------------------------------------------------

    def control(self, dt_s: float, joint_rad: float, joint_velocity_rad_s: float) -> float:
        """Run the drive for one integration step of ``dt_s`` seconds; return the joint torque in N·m."""
        self.observe(joint_rad, joint_velocity_rad_s)
        self._latch_errors()
        if self.state is RunState.OFF:
            self.iq_a = 0.0
        else:
            volts = self.voltage_v
            back_emf_v = self.model.torque_constant_nm_per_a * self._speed_dps * _RAD_PER_DEG
            target = self._iq_target(dt_s, volts, back_emf_v)
            # The power stage drives at most its hardware current and what the supply can push past the back-EMF.
            resistance = self.model.winding_resistance_ohm
            highest = min(HARDWARE_CURRENT_LIMIT_A, (volts - back_emf_v) / resistance)
            lowest = max(-HARDWARE_CURRENT_LIMIT_A, (-volts - back_emf_v) / resistance)
            target = max(min(target, highest), lowest)
            if dt_s != self._iq_dt_s:
                self._iq_dt_s = dt_s
                self._iq_alpha = 1.0 - math.exp(-dt_s * self._iq_bandwidth)
            self.iq_a += self._iq_alpha * (target - self.iq_a)
        model = self.model
        loss_w = _COPPER_LOSS_FACTOR * model.winding_resistance_ohm * self.iq_a * self.iq_a
        cooling_w = (self.temperature_c - model.ambient_c) / model.thermal_resistance_k_per_w
        self.temperature_c += dt_s * (loss_w - cooling_w) / self._thermal_capacity
        if self.temperature_floor_c is not None and self.temperature_c < self.temperature_floor_c:
            self.temperature_c = self.temperature_floor_c
        return self._torque_per_a * self.iq_a

    def _latch_errors(self) -> None:
        if self.voltage_v < self.model.low_voltage_v and not self.errors & ErrorFlags.LOW_VOLTAGE:
            self.errors |= ErrorFlags.LOW_VOLTAGE
        if self.temperature_c > self.model.over_temperature_c and not self.errors & ErrorFlags.OVER_TEMPERATURE:
            self.errors |= ErrorFlags.OVER_TEMPERATURE
        if self.errors and self.state is not RunState.OFF:
            self._turn_off()  # protection: the power stage is disabled while a flag is set

    def _iq_target(self, dt_s: float, volts: float, back_emf_v: float) -> float:
        """The current the active mode asks for, A (before the power stage's limits)."""
        if self.state is RunState.STOPPED:
            if self._hold_deg is None:
                reference = self._slew(0.0, dt_s)
                if reference == 0.0:
                    self._hold_deg = self._shaft_deg
                return self._speed_pi(reference, dt_s)
            return self._position(self._hold_deg, self.model.max_speed_dps, dt_s)
        setpoint = self.setpoint
        assert setpoint is not None  # RUNNING always has one
        mode = setpoint.mode
        if mode is DriveLoop.POSITION:
            return self._position(setpoint.value, setpoint.max_speed_dps, dt_s)
        if mode is DriveLoop.SPEED:
            return self._speed_pi(self._slew(_clamp(setpoint.value, self.model.max_speed_dps), dt_s), dt_s)
        if mode is DriveLoop.TORQUE:
            return setpoint.value
        return (setpoint.value / _OPEN_LOOP_FULL_SCALE * volts - back_emf_v) / self.model.winding_resistance_ohm

    def _slew(self, target_dps: float, dt_s: float) -> float:
        """Move the speed reference toward ``target_dps`` at the acceleration limit (0: at once)."""
        if self.acceleration_dps2 == 0:
            self._speed_ref = target_dps
        else:
            self._speed_ref += _clamp(target_dps - self._speed_ref, self.acceleration_dps2 * dt_s)
        return self._speed_ref

    def _speed_pi(self, reference_dps: float, dt_s: float) -> float:
        """Speed PI with conditional integration (no wind-up while the current limit clips)."""
        limit = self.model.current_limit_a
        error = reference_dps - self._speed_dps
        integral = _clamp(self._speed_integral + self._ki_speed * error * dt_s, limit)
        out = self._kp_speed * error + integral
        if abs(out) <= limit or (out > 0) != (error > 0):
            self._speed_integral = integral
        return _clamp(out, limit)

    def _position(self, target_deg: float, max_speed_dps: float, dt_s: float) -> float:
        error = target_deg - self._shaft_deg
        distance = abs(error)
        speed = self._kp_angle * distance
        linear = speed <= max_speed_dps
        if not linear:
            speed = max_speed_dps
        if self.acceleration_dps2:
            braking = math.sqrt(2.0 * self.acceleration_dps2 * distance)
            if braking < speed:
                speed, linear = braking, False
        if linear and distance < _ANGLE_INTEGRAL_BAND_DEG:
            integral = self._angle_integral + self._ki_angle * error * dt_s
            self._angle_integral = _clamp(integral, _ANGLE_INTEGRAL_SHARE * max_speed_dps)
        else:
            self._angle_integral = 0.0
        wanted = _clamp(math.copysign(speed, error) + self._angle_integral, max_speed_dps)
        return self._speed_pi(self._slew(wanted, dt_s), dt_s)

    def _run(self, setpoint: Setpoint) -> None:
        """Start executing a control command (bumpless when a speed-loop mode takes over)."""
        if self.errors:
            return  # protection keeps the power stage off; the reply still reports the state
        closed = (DriveLoop.SPEED, DriveLoop.POSITION)
        was_closed = self.state is RunState.STOPPED or (
            self.state is RunState.RUNNING and self.setpoint is not None and self.setpoint.mode in closed
        )
        if setpoint.mode in closed and not was_closed:
            self._speed_ref = self._speed_dps
            self._speed_integral = _clamp(self.iq_a, self.model.current_limit_a)
            self._angle_integral = 0.0
        self.setpoint = setpoint
        self.state = RunState.RUNNING
        self._hold_deg = None

    # --- requests -------------------------------------------------------------------------------------------------

    def respond(self, message: Message, now_s: float, transport: WireProtocol) -> Message | None:
        """Execute one request of the drive's family at ``now_s`` (simulation time), come over ``transport``; the
        reply, or None where the command has none (see :meth:`handle`)."""
        return self.handle(message, transport)

    def hold_here(self, speed_dps: float) -> None:
        """Hold the present position by its own loop (0xA4 to where it is, at up to ``speed_dps`` motor deg/s): an
        emulated arm's start, straight to the drive (no link faults at power-on)."""
        self.handle(MultiTurnPositionSpeed(self.angle_deg, speed_dps), WireProtocol.CAN)

    def handle(self, message: Message, transport: WireProtocol) -> Message:
        """Execute one request and return the reply (of the class the command table gives for ``transport``).

        Raises:
            ValueError: the message is not a request of ``transport`` (the emulator decodes requests with the
                codec first, so this does not happen for frames from the bus).
        """
        command = command_of(message)
        spec = COMMANDS.get(command) if command is not None else None
        layout = spec.layout(transport, Direction.REPLY) if spec is not None else None
        if command is None or layout is None:
            raise ValueError(f"{message!r} is not a request of the {transport.value} protocol")
        self._latch_errors()
        self._execute(command, message)
        if layout.echo:
            return message
        return self._reply(command, layout.cls, transport)

    def _execute(self, command: Command, message: Message) -> None:
        if isinstance(message, PidGains) and command in (Command.WRITE_PID_RAM, Command.WRITE_PID_ROM):
            self.pid = replace(message, command=Command.READ_PID)
            if command is Command.WRITE_PID_ROM:
                self.pid_rom = self.pid
            self._apply_gains()
        elif isinstance(message, Acceleration) and command is Command.WRITE_ACCELERATION_RAM:
            self.acceleration_dps2 = message.acceleration_dps2
        elif isinstance(message, EncoderOffset):
            self._offset_rom = (message.encoder_offset << self._field_shift) % self._counts_per_rev
        elif command is Command.WRITE_ZERO_ROM:
            self._offset_rom = self.encoder_raw
        elif command is Command.SET_ZERO_RAM:
            self._offset_ram = self.encoder_raw
            self._ref_counts = self._counts()
        elif command is Command.CLEAR_ERRORS:
            if self.voltage_v >= self.model.low_voltage_v:
                self.errors &= ~ErrorFlags.LOW_VOLTAGE
            if self.temperature_c <= self.model.over_temperature_c:
                self.errors &= ~ErrorFlags.OVER_TEMPERATURE
        elif command is Command.MOTOR_OFF:
            self._turn_off()
        elif command is Command.MOTOR_STOP:
            self._stop()
        elif command is Command.MOTOR_RUN:
            if self.state is RunState.STOPPED and self.setpoint is not None:
                self.state = RunState.RUNNING
        else:
            setpoint = self._setpoint_of(command, message)
            if setpoint is not None:
                self._run(setpoint)

    def _stop(self) -> None:
        """0x81: a running drive brakes to a standstill and holds there, its closed loop kept."""
        if self.state is RunState.RUNNING:
            self.state = RunState.STOPPED
            self._hold_deg = None
            if self.setpoint is not None and self.setpoint.mode not in (DriveLoop.SPEED, DriveLoop.POSITION):
                self._speed_ref = self._speed_dps
                self._speed_integral = _clamp(self.iq_a, self.model.current_limit_a)

    def _setpoint_of(self, command: Command, message: Message) -> Setpoint | None:
        """The setpoint of a control command, targets converted to shaft angles; None for other requests."""
        here = self._shaft_deg
        frame_zero = self._ref_counts * self._deg_per_count  # shaft angle where the drive's angle is 0
        position = DriveLoop.POSITION
        top = self.model.max_speed_dps
        if isinstance(message, OpenLoopControl):
            return Setpoint(command, DriveLoop.OPEN_LOOP, message.power)
        if isinstance(message, TorqueControl):
            return Setpoint(command, DriveLoop.TORQUE, message.iq_a)
        if isinstance(message, SpeedControl):
            return Setpoint(command, DriveLoop.SPEED, message.speed_dps)
        if isinstance(message, MultiTurnPosition):
            return Setpoint(command, position, frame_zero + message.angle_deg, top)
        if isinstance(message, MultiTurnPositionSpeed):
            return Setpoint(command, position, frame_zero + message.angle_deg, message.max_speed_dps)
        if isinstance(message, (SingleTurnPosition, SingleTurnPositionSpeed)):
            # Clockwise is the positive direction of the documents' angles: go forward (or back) to the target.
            forward = (message.angle_deg - (here - frame_zero)) % 360.0
            step = forward
            if message.direction is SpinDirection.COUNTERCLOCKWISE and forward:
                step = forward - 360.0
            speed = message.max_speed_dps if isinstance(message, SingleTurnPositionSpeed) else top
            return Setpoint(command, position, here + step, speed)
        if isinstance(message, IncrementalPosition):
            return Setpoint(command, position, here + message.angle_deg, top)
        if isinstance(message, IncrementalPositionSpeed):
            return Setpoint(command, position, here + message.angle_deg, message.max_speed_dps)
        return None

    # --- replies --------------------------------------------------------------------------------------------------

    def _reply(self, command: Command, cls: type[Message], transport: WireProtocol) -> Message:
        """Build the reply of class ``cls`` from the drive's state."""
        coldest, hottest = _TEMPERATURE_REPLY_C
        temperature = int(max(coldest, min(hottest, round(self.temperature_c))))
        if cls is MotorState:
            return MotorState(command, temperature, self._iq_reply(), self._speed_reply(), self._field(self.encoder))
        if cls is Status1:
            return Status1(command, temperature, min(self.voltage_v, _VOLTAGE_REPLY_MAX_V), self.errors)
        if cls is PidGains:
            return replace(self.pid, command=command)
        if cls is Acceleration:
            return Acceleration(command, self.acceleration_dps2)
        if cls is EncoderOffset:
            return EncoderOffset(command, self._field(self._offset_rom))
        if cls is EncoderReading:
            return EncoderReading(
                self._field(self.encoder), self._field(self.encoder_raw), self._field(self._offset_ram)
            )
        if cls is MultiTurnAngle:
            return MultiTurnAngle((self._counts() - self._ref_counts) * self._deg_per_count)
        if cls is SingleTurnAngle:
            # Floor to 0.01 deg: rounding could reach 360.00, which the field cannot carry.
            centi = _CENTIDEGREES_PER_DEG
            return SingleTurnAngle(self.encoder * 360 * centi // self._counts_per_rev / centi)
        if cls is PhaseCurrents:
            return self._phase_currents(temperature if transport is WireProtocol.RS485 else None)
        if cls is OpenLoopState:
            setpoint = self.setpoint if self.state is RunState.RUNNING else None
            power = int(setpoint.value) if setpoint is not None and setpoint.mode is DriveLoop.OPEN_LOOP else 0
            return OpenLoopState(temperature, power, self._speed_reply(), self._field(self.encoder))
        if cls is ProductInfo:
            m = self.model
            return ProductInfo(m.driver_name, m.motor_name, m.hardware_version, m.firmware_version)
        if cls is Bare:
            return Bare(command)
        raise AssertionError(f"no reply builder for {cls.__name__}")  # a new table class needs one here

    def _iq_reply(self) -> float:
        return _clamp(self.iq_a, _IQ_REPLY_MAX_A)

    def _speed_reply(self) -> int:
        return round(_clamp(self._speed_dps, _SPEED_REPLY_MAX_DPS))

    def _phase_currents(self, temperature_c: int | None) -> PhaseCurrents:
        # Inverse Park transform with id = 0 at the rotor's electrical angle (amplitude invariant).
        electrical = self.model.pole_pairs * self._shaft_deg * _RAD_PER_DEG
        iq = self.iq_a
        return PhaseCurrents(
            _clamp(-iq * math.sin(electrical), _PHASE_REPLY_MAX_A),
            _clamp(-iq * math.sin(electrical - _THIRD_TURN_RAD), _PHASE_REPLY_MAX_A),
            _clamp(-iq * math.sin(electrical + _THIRD_TURN_RAD), _PHASE_REPLY_MAX_A),
            temperature_c,
        )
