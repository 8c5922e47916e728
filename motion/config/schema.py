"""Arm configuration as frozen dataclasses.

The field names are the YAML keys and the field defaults are the YAML defaults: the loader (its reader,
:class:`motion.config.nodes.Node`) derives both from here, so a key without a default below is required in the
file. Units are in the names.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import ClassVar, Final, NamedTuple, TypeAlias

from motion.errors import ConfigError
from motion.protocol import WireProtocol
from motion.protocol.table import ADDRESS_STRIDE
from motion.transmission import ArmTransmission, Transmission

Vec3: TypeAlias = tuple[float, float, float]


class ModeTraits(NamedTuple):
    """What a control mode is, for every layer that behaves by it: each asks these instead of naming a mode (a new
    mode is its member and its traits here, and its set-point builder in :mod:`motion.control.setpoints`; see
    docs/architecture.md).

    Attributes:
        drive_position_loop: the drives close the position loop on streamed set-points (0xA4 with a speed cap): the
            expected tracking runs the drive's loop, the planner leaves the drive room to catch up below the cap,
            the loops can be identified, the collision bound counts the set-points' steps.
        host_torque: the host closes the loop and sends torque (0xA1, 0x280): per-joint gains (``kp_nm_per_deg``,
            ``kd_nm_per_dps``), gravity and inertia feed-forward, the set-points' current limiting, ``comply``.
    """

    drive_position_loop: bool
    host_torque: bool


class ControlMode(StrEnum):
    """How the controller drives the motors (:attr:`traits`: what that means to the layers above)."""

    #: Stream position setpoints (0xA4) with a speed cap; the drive closes the position loop.
    POSITION = "position"
    #: Stream torque-current setpoints (0xA1); the controller closes a PD loop plus feed-forward.
    TORQUE = "torque"

    @property
    def traits(self) -> ModeTraits:
        """This mode's :class:`ModeTraits`."""
        return _MODE_TRAITS[self]


_MODE_TRAITS: dict[ControlMode, ModeTraits] = {
    ControlMode.POSITION: ModeTraits(drive_position_loop=True, host_torque=False),
    ControlMode.TORQUE: ModeTraits(drive_position_loop=False, host_torque=True),
}


class HaltPolicy(StrEnum):
    """What every axis does on a fault (and an E-stop, Ctrl-C, the end of a program)."""

    #: 0x81: the drives brake and hold (keeping their mode).
    STOP = "stop"
    #: 0x80: torque off (an arm under gravity falls unless it has brakes).
    OFF = "off"
    #: A jerk-limited stop of the reference, then hold; only while communication is healthy (else 0x81).
    HOLD = "hold"
    #: Torque mode, collisions only (``safety.collision_reaction``): gravity compensation with zero gains, so that a
    #: person can push the arm away; only while communication is healthy (else 0x81).
    COMPLY = "comply"


class ProtocolSetting(StrEnum):
    """``bus.protocol``: the drives' protocol generation, or ``auto`` to tell it from their replies at connect."""

    AUTO = "auto"  #: told at connect (CAN: by the reply ids; RS485: by the framing the drives answer)
    V2 = "v2"  #: the older family (CAN v2.3 / RS485 v1.62 documents)
    V3 = "v3"  #: the V3-driver family (V4.2 document)


@dataclass(frozen=True, slots=True)
class CanBusConfig:
    """CAN bus via python-can.

    Attributes:
        interface: python-can interface name (``virtual``, ``socketcan``, ``slcan``, ``pcan``, ``kvaser``, ...).
        channel: interface channel (``can0``, ``/dev/ttyACM0``, ``PCAN_USBBUS1``, ...).
        bitrate: bit rate in bit/s (500000 or 1000000, the rates the RMD drives support).
        protocol: the drives' protocol generation (see :class:`ProtocolSetting`).
        name: its name under ``buses:`` (the one ``bus:`` section has none: "").
    """

    transport: ClassVar[WireProtocol] = WireProtocol.CAN
    #: The settings a command line may override (``--interface``, ``--channel``).
    overridable: ClassVar[tuple[str, ...]] = ("interface", "channel")
    interface: str
    channel: str
    bitrate: int = 1_000_000
    protocol: ProtocolSetting = ProtocolSetting.AUTO
    name: str = field(default="", metadata={"derived": True})

    @property
    def link(self) -> str:
        """What the bus is reached through (the channel)."""
        return self.channel

    def settings(self) -> dict[str, object]:
        """The transport's arguments (its registry entry is :attr:`transport`)."""
        return {"interface": self.interface, "channel": self.channel, "bitrate": self.bitrate}


@dataclass(frozen=True, slots=True)
class Rs485BusConfig:
    """RS485 serial port via pyserial.

    Attributes:
        port: serial device (``/dev/ttyUSB0``, ``COM3``).
        baudrate: baud rate in bit/s (the older drives: 9600, 19200, 57600 or 115200; V3-driver drives: 115200, 500000,
            1000000, 1500000 or 2500000).
        protocol: the drives' protocol generation (see :class:`ProtocolSetting`).
        name: its name under ``buses:`` (the one ``bus:`` section has none: "").
    """

    transport: ClassVar[WireProtocol] = WireProtocol.RS485
    #: The settings a command line may override (``--port``).
    overridable: ClassVar[tuple[str, ...]] = ("port",)
    port: str
    baudrate: int = 115_200
    protocol: ProtocolSetting = ProtocolSetting.AUTO
    name: str = field(default="", metadata={"derived": True})

    @property
    def link(self) -> str:
        """What the bus is reached through (the serial port)."""
        return self.port

    def settings(self) -> dict[str, object]:
        """The transport's arguments (its registry entry is :attr:`transport`)."""
        return {"port": self.port, "baudrate": self.baudrate}


BusConfig: TypeAlias = CanBusConfig | Rs485BusConfig


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """Control loop settings.

    Attributes:
        halt_policy: what the axes do on halt (required: the safe choice depends on the arm).
        mode: position or torque control.
        rate_hz: control cycle rate in Hz (1..1000: a long RS485 line holds a few tens of Hz; the rate check says).
        gravity_feedforward: add the model's gravity torque g(q).
        inertia_feedforward: add the inertial and Coriolis torques of the planned motion (RNEA).
        rate_margin: the margin the rate check at connect requires (1..10, default 1.5): the measured bus round trip
            and host work times this must fit the period. Below the default a warning says the margin is thin.
        goal_tolerance_deg: a move (or path) ends when every joint is within this of its target, degrees (0: when its
            reference ends, not waiting for the arm).
        goal_settle_s: ... and has stayed within it for this long, s.
        goal_time_s: how long after the reference ends the joints have to arrive, s; a joint that has not is
            reported (``MotionHandle.arrival``, a warning), not a fault.
    """

    halt_policy: HaltPolicy
    mode: ControlMode = ControlMode.POSITION
    rate_hz: float = 200.0
    gravity_feedforward: bool = False
    inertia_feedforward: bool = False
    rate_margin: float = 1.5
    goal_tolerance_deg: float = 0.1
    goal_settle_s: float = 0.1
    goal_time_s: float = 2.0

    @property
    def period_s(self) -> float:
        """Control cycle period in seconds."""
        return 1.0 / self.rate_hz


@dataclass(frozen=True, slots=True)
class InertiaConfig:
    """Rotational inertia about the centre of mass, in the link frame, in kg·m²."""

    ixx: float
    ixy: float
    ixz: float
    iyy: float
    iyz: float
    izz: float

    def matrix(self) -> tuple[Vec3, Vec3, Vec3]:
        """The symmetric 3x3 inertia matrix in kg·m², row by row."""
        return (
            (self.ixx, self.ixy, self.ixz),
            (self.ixy, self.iyy, self.iyz),
            (self.ixz, self.iyz, self.izz),
        )


@dataclass(frozen=True, slots=True)
class ChainJointConfig:
    """One revolute joint of a serial chain written in YAML, and the link it moves (URDF conventions).

    Attributes:
        joint: joint name (must match a configured joint).
        axis: rotation axis in the joint frame (normalised on load).
        mass_kg: link mass in kg.
        com_xyz_m: link centre of mass in the joint frame, in metres.
        inertia_kgm2: link inertia about its centre of mass, in the joint frame axes.
        origin_xyz_m: joint frame position in the previous joint frame (the world for the first), in metres.
        origin_rpy_rad: joint frame orientation (roll, pitch, yaw; R = Rz(y)·Ry(p)·Rx(r)) in radians.
        link: name of the link frame (default ``<joint>_link``).
    """

    joint: str
    axis: Vec3
    mass_kg: float
    com_xyz_m: Vec3
    inertia_kgm2: InertiaConfig
    origin_xyz_m: Vec3 = (0.0, 0.0, 0.0)
    origin_rpy_rad: Vec3 = (0.0, 0.0, 0.0)
    link: str = ""

    @property
    def link_name(self) -> str:
        """Name of the link frame: ``link``, or ``<joint>_link`` when not given."""
        return self.link or f"{self.joint}_link"


@dataclass(frozen=True, slots=True)
class ModelConfig:
    """Arm dynamic model: exactly one of ``urdf`` and ``chain``.

    Attributes:
        urdf: absolute path of the URDF file (written relative to the configuration file).
        chain: serial chain of revolute joints, base first.
        gravity_m_s2: gravity vector in the base frame, in m/s².
        tip_xyz_m: with ``chain`` only: a frame named ``tip`` at this offset in the last joint frame, in metres.
    """

    urdf: Path | None = None
    chain: tuple[ChainJointConfig, ...] = ()
    gravity_m_s2: Vec3 = (0.0, 0.0, -9.81)
    tip_xyz_m: Vec3 | None = None


@dataclass(frozen=True, slots=True)
class HomingConfig:
    """How ``rmd-motion home`` finds a joint's turn count against its hard stop.

    The stop lies outside the joint's limits (below ``position_min_deg`` or above ``position_max_deg``); homing
    moves toward it, so the side it lies on gives the direction.

    Attributes:
        stop_deg: the joint angle at the hard stop, in degrees.
        speed_dps: joint speed toward the stop, in deg/s.
        current_limit_a: torque-current limit while seeking, in A: what the joint may push against the stop with.
        back_off_deg: how far the joint moves back off the stop once it is found, in degrees.
        max_travel_deg: the farthest homing moves looking for the stop, in degrees (None: from the far joint limit
            to the stop, plus the back-off).
        timeout_s: the longest homing may take, in seconds.
    """

    stop_deg: float
    speed_dps: float = 5.0
    current_limit_a: float = 2.0
    back_off_deg: float = 2.0
    max_travel_deg: float | None = None
    timeout_s: float = 60.0


@dataclass(frozen=True, slots=True)
class EmulatedPidConfig:
    """The PI gains (0x30 units, 0..255) an emulated drive has in ROM at first power-on; None: the factory value.

    Attributes:
        angle_kp: position loop proportional gain.
        angle_ki: position loop integral gain.
        speed_kp: speed loop proportional gain.
        speed_ki: speed loop integral gain.
        iq_kp: current loop proportional gain.
        iq_ki: current loop integral gain.
    """

    angle_kp: int | None = None
    angle_ki: int | None = None
    speed_kp: int | None = None
    speed_ki: int | None = None
    iq_kp: int | None = None
    iq_ki: int | None = None


@dataclass(frozen=True, slots=True)
class EmulationConfig:
    """Plant parameters for the emulated drive of a joint (used only by the emulator). In a file, the first three
    default to the joint's own model values (``rotor_inertia_kgm2``, ``viscous_friction_nm_per_dps``,
    ``coulomb_friction_nm`` beside the joint): the emulated joint is as modelled unless this block says otherwise
    (e.g. to test the collision observer against a model mismatch).

    Attributes:
        rotor_inertia_kgm2: motor rotor inertia, motor side, in kg·m² (reflected: gear_ratio² times this).
        viscous_friction_nm_per_dps: joint-side viscous friction in N·m per deg/s.
        coulomb_friction_nm: joint-side Coulomb friction in N·m.
        torque_constant_nm_per_a: the emulated motor's true torque constant, N·m/A (None: the joint's
            ``torque_constant_nm_per_a``).
        pid: the drive's tuning (softer or stiffer loops than the factory's).
        acceleration_dps2: the drive's acceleration limit at power-on, motor side, in deg/s² (0: none; None: the
            factory value).
    """

    rotor_inertia_kgm2: float = 3.0e-5
    viscous_friction_nm_per_dps: float = 2.0e-4
    coulomb_friction_nm: float = 0.05
    torque_constant_nm_per_a: float | None = None
    pid: EmulatedPidConfig = field(default_factory=EmulatedPidConfig)
    acceleration_dps2: int | None = None


@dataclass(frozen=True, slots=True)
class JointConfig:
    """One joint and its drive. Angles, rates and limits are joint-side unless the name says motor.

    Attributes:
        name: joint name (as in the model).
        motor_id: drive id on its bus (1..32; unique per bus).
        gear_ratio: motor-shaft degrees per joint degree (9 for a 1:9 drive).
        direction: +1 or -1.
        zero_offset_deg: joint angle when the motor reads 0, in degrees.
        torque_constant_nm_per_a: motor-side torque constant in N·m/A.
        current_limit_a: largest torque current commanded, in A (0 < x <= 32).
        position_min_deg: lower joint limit in degrees.
        position_max_deg: upper joint limit in degrees.
        velocity_limit_dps: joint speed limit in deg/s.
        acceleration_limit_dps2: joint acceleration limit in deg/s².
        jerk_limit_dps3: joint jerk limit in deg/s³.
        encoder_bits: single-turn encoder resolution in bits (12..18).
        kp_nm_per_deg: torque-mode stiffness in N·m per degree (required when control.mode is torque).
        kd_nm_per_dps: torque-mode damping in N·m per deg/s (required when control.mode is torque, unless
            ``bandwidth_hz`` is given).
        bandwidth_hz: torque mode: the PD loop's bandwidth, Hz, instead of ``kp_nm_per_deg`` and
            ``kd_nm_per_dps``: the gains of a critically damped loop at the heaviest the joint is in the limits
            (:func:`motion.compose.with_bandwidth_gains` fills them in; None: the gains as given).
        temperature_limit_c: motor temperature that faults the arm, in °C.
        rotor_inertia_kgm2: motor rotor inertia, motor side, in kg·m² (the collision observer's model adds
            gear_ratio² times this to the joint's diagonal of M(q)).
        viscous_friction_nm_per_dps: the joint's viscous friction, joint side, in N·m per deg/s (observer model).
        coulomb_friction_nm: the joint's Coulomb friction, joint side, in N·m (observer model).
        collision_threshold_nm: the collision observer's residual beyond which the arm faults (``collision``) in
            position mode, N·m, where it is above the collision bound (None: the joint is not watched; 0: watched
            with the bound alone in force, ``bound`` in YAML; see ``rmd-motion collision-calibrate``). In YAML one
            value for both modes or ``{position: N, torque: N}``.
        collision_threshold_torque_nm: the same in torque mode (None: ``collision_threshold_nm``); set from
            ``collision_threshold_nm`` in YAML.
        power_on_window_deg: where the joint is guaranteed to be when the drives power up, ``(min, max)`` in degrees,
            narrower than ``360 / gear_ratio`` (None: no window; the drive's turn count is assumed, see
            :mod:`motion.control.turns`).
        homing: the joint's hard stop and how to home against it (None: the joint cannot be homed).
        brake: the joint has a holding brake its drive controls (V3-driver drives, 0x77 / 0x78): released when the
            loop starts, locked when the arm has halted and at the end.
        actuator: the model of :mod:`motion.config.actuators` whose published figures are the defaults of
            ``gear_ratio``, ``torque_constant_nm_per_a`` and ``current_limit_a`` (None: each given).
        emulation: emulator plant parameters.
        bus: the name of the bus the drive is on, one of ``buses:`` ("" with the one ``bus:`` section).
        bus_index: that bus's place in ``buses:`` (0 with one bus); set from ``bus``.
    """

    name: str
    motor_id: int
    gear_ratio: float
    direction: int
    zero_offset_deg: float
    torque_constant_nm_per_a: float
    current_limit_a: float
    position_min_deg: float
    position_max_deg: float
    velocity_limit_dps: float
    acceleration_limit_dps2: float
    jerk_limit_dps3: float
    encoder_bits: int = 14
    kp_nm_per_deg: float = 0.0
    kd_nm_per_dps: float = 0.0
    bandwidth_hz: float | None = None
    temperature_limit_c: float = 70.0
    rotor_inertia_kgm2: float = 3.0e-5
    viscous_friction_nm_per_dps: float = 2.0e-4
    coulomb_friction_nm: float = 0.05
    collision_threshold_nm: float | None = None
    collision_threshold_torque_nm: float | None = field(default=None, metadata={"derived": True})
    power_on_window_deg: tuple[float, float] | None = None
    homing: HomingConfig | None = None
    brake: bool = False
    actuator: str | None = None
    emulation: EmulationConfig = field(default_factory=EmulationConfig)
    bus: str = ""
    bus_index: int = field(default=0, metadata={"derived": True})

    @property
    def address(self) -> int:
        """The drive's address in the arm: its motor id on the first bus (and the only one), else
        ``bus_index × ADDRESS_STRIDE + motor_id`` (:data:`motion.protocol.table.ADDRESS_STRIDE`)."""
        return self.bus_index * ADDRESS_STRIDE + self.motor_id

    @property
    def drive_label(self) -> str:
        """``"motor 3"``, or ``"motor 3 on bus left"`` on an arm of several buses: how messages name the drive."""
        return f"motor {self.motor_id}" + (f" on bus {self.bus}" if self.bus else "")

    def collision_threshold_in(self, mode: ControlMode) -> float | None:
        """The collision threshold in force in ``mode`` (None: not watched), N·m."""
        if mode.traits.host_torque and self.collision_threshold_torque_nm is not None:
            return self.collision_threshold_torque_nm
        return self.collision_threshold_nm

    def without_collision_threshold(self) -> JointConfig:
        """This joint, not watched for collisions in either mode."""
        return replace(self, collision_threshold_nm=None, collision_threshold_torque_nm=None)

    @property
    def peak_torque_nm(self) -> float:
        """The largest joint torque the controller commands: torque constant × gear ratio × current limit, N·m."""
        return self.torque_constant_nm_per_a * self.gear_ratio * self.current_limit_a

    def transmission(self) -> Transmission:
        """The joint <-> motor mapping of this joint."""
        return Transmission(
            gear_ratio=self.gear_ratio,
            direction=self.direction,
            zero_offset_deg=self.zero_offset_deg,
            torque_constant_nm_per_a=self.torque_constant_nm_per_a,
            current_limit_a=self.current_limit_a,
        )


@dataclass(frozen=True, slots=True)
class SafetyConfig:
    """Arm-wide fault thresholds.

    Attributes:
        following_error_deg: largest |planned - measured| joint angle before a fault, in degrees.
        min_voltage_v: supply voltage below which the arm faults, in volts.
        reply_timeout_ms: time to wait for a drive's reply, in milliseconds.
        max_missed_replies: consecutive missed replies of one drive tolerated before a fault.
        collision_reaction: the reaction to a ``collision`` fault: a halt policy, or ``comply`` (torque mode only);
            None: ``control.halt_policy`` (``hold`` then means 0x81: a collision is not holdable).
        collision_observer_gain_per_s: the momentum observer's gain K_O, 1/s: its residual follows an external
            torque step as ``1 - exp(-K_O t)`` (per step ``K_O × dt``, at most 1: deadbeat); the noise the speed
            field's steps put in the residual grows with it (see :mod:`motion.safety.watchdog`).
        collision_window_s: the thresholds apply to the residual's change over this long, s (0..1; 0: to the
            residual itself), which cancels slowly varying model errors; a collision must be detected within it.
        link_timeout_ms: V3-driver drives: the communication-loss time set in each drive at start (0xB3), in
            milliseconds: a drive that gets no frame for this long cuts its output and locks its brake by itself
            (the host died, the cable dropped); 0 leaves the protection off; None: five control periods, at least
            20 ms (:mod:`motion.control.drivesetup`).
    """

    following_error_deg: float
    min_voltage_v: float
    reply_timeout_ms: float = 20.0
    max_missed_replies: int = 3
    collision_reaction: HaltPolicy | None = None
    collision_observer_gain_per_s: float = 125.0
    collision_window_s: float = 0.032
    link_timeout_ms: float | None = None


#: The shortest communication-loss time a loop of a given period may set, in periods: every cycle sends each drive
#: a frame, and a cycle that overruns is skipped, so two periods may pass between a drive's frames.
LINK_TIMEOUT_MIN_PERIODS: Final = 2


def link_timeout_problem(link_timeout_ms: float | None, rate_hz: float) -> str | None:
    """What is wrong with a configured communication-loss time at ``rate_hz`` (None: nothing; 0 and None are the
    protection off and the default). A time shorter than the gap between two of a drive's frames cuts every drive's
    output between cycles."""
    if not link_timeout_ms:
        return None
    shortest_ms = LINK_TIMEOUT_MIN_PERIODS * 1000.0 / rate_hz
    if link_timeout_ms >= shortest_ms - 1e-9:
        return None
    return (
        f"{link_timeout_ms:g} ms is shorter than a loop at {rate_hz:g} Hz leaves between a drive's frames: at least "
        f"{LINK_TIMEOUT_MIN_PERIODS} periods, {shortest_ms:g} ms (the drives would cut their output and lock their "
        "brakes between cycles): raise it, remove it (five periods by default) or raise control.rate_hz"
    )


@dataclass(frozen=True, slots=True)
class ArmConfig:
    """A whole arm: its bus (or buses), control loop, model, joints (in controller order) and safety thresholds.

    Attributes:
        source: the file it was read from (``"<string>"`` when parsed from a mapping), for error messages.
    """

    name: str
    buses: tuple[BusConfig, ...]
    control: ControlConfig
    model: ModelConfig
    safety: SafetyConfig
    joints: tuple[JointConfig, ...]
    source: str = "<string>"

    @property
    def bus(self) -> BusConfig:
        """The arm's one bus.

        Raises:
            ConfigError: the arm is on several buses (``buses:``) and the caller handles one only.
        """
        if len(self.buses) != 1:
            names = ", ".join(b.name for b in self.buses)
            raise ConfigError(self.source, "buses", f"this takes an arm on one bus; the arm is on {names}")
        return self.buses[0]

    def joints_on(self, bus_index: int) -> tuple[JointConfig, ...]:
        """The joints whose drives are on bus ``bus_index`` (configuration order)."""
        return tuple(j for j in self.joints if j.bus_index == bus_index)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names in configuration order."""
        return tuple(j.name for j in self.joints)

    @property
    def collision_watched(self) -> bool:
        """Whether any joint has a collision threshold (the observer then runs and its fault source is armed)."""
        return any(t is not None for t in self.collision_thresholds_nm)

    @property
    def collision_thresholds_nm(self) -> tuple[float | None, ...]:
        """Each joint's collision threshold in the configured control mode (None: not watched), N·m."""
        return tuple(j.collision_threshold_in(self.control.mode) for j in self.joints)

    @property
    def collision_reaction(self) -> HaltPolicy:
        """The reaction to a collision: ``safety.collision_reaction``, else ``control.halt_policy``."""
        reaction = self.safety.collision_reaction
        return self.control.halt_policy if reaction is None else reaction

    def transmission(self) -> ArmTransmission:
        """Vectorised joint <-> motor mapping of all joints, in configuration order."""
        return ArmTransmission([j.transmission() for j in self.joints], self.joint_names)
