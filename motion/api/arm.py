"""The arm: :class:`Arm`, its lifecycle (connect, homing, close) and its motion commands (see :mod:`motion.api`)."""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import types
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from motion.api.arguments import emulation_of, joint_targets, seconds, start_pose_of, waypoint_rows
from motion.api.emulation import emulated_families, emulator_process, simulated_lines
from motion.api.status import ArmStatus, MotionHandle, arm_status
from motion.api.summary import RunSummary
from motion.compose import (
    arm_figure,
    build_controller,
    build_supervisor,
    check_envelope,
    check_rate,
    emulated_frames,
    feedforward_for,
    identify_position_loops,
    negotiate_family,
    open_bus,
    opening_families,
    resolve_frames,
    with_bandwidth_gains,
)
from motion.config import ArmConfig, load_config_or_example
from motion.control.clock import Clock
from motion.control.commands import MotionTicket
from motion.control.controller import Controller
from motion.control.ratecheck import RateCheck
from motion.control.tracking import PositionLoopFit
from motion.control.turns import JointTurns, Source, ambiguous_joints
from motion.emulator import Fault, FrameLog
from motion.emulator.simulated import SimulatedBus, SimulatedClock, Simulation
from motion.errors import EncodeError, FaultKind, MotionError, MotionFault, PlanningError
from motion.homing import (
    HomingResult,
    check_seeks,
    corrected_turns,
    finish_halt,
    homed_joints,
    homing_variant,
    quiet_ahead,
    seek_stop,
)
from motion.keep import load_turn_records, offer_stored_tracking, resting_angles, save_turn_records, store_tracking
from motion.protocol.table import ADDRESS_STRIDE, ProtocolFamily
from motion.protocol.v3.messages import MotionRanges
from motion.safety import ArmState, Supervisor
from motion.telemetry import TelemetryOptions, TelemetrySession
from motion.transmission import FloatArray
from motion.transport import Transport
from motion.view import LiveView, ViewOptions

logger = logging.getLogger("motion.api")

#: The fault's detail of :meth:`Arm.stop`.
_STOP_DETAIL = "E-stop requested"


class Arm:
    """An arm of RMD joints, built from a configuration (see :meth:`from_config`).

    Args:
        config: the validated configuration.
        emulate: run on emulated drives instead of hardware. ``True`` (or ``"simulated"``): in simulated time, in
            this process: the wire and the drives are modelled frame by frame, the control cycles run in the thread
            that waits (``handle.wait()``, :meth:`sleep`), and a run gives the same result on every host, faster than
            real time. ``"realtime"``: the drives run in real time in a process of their own (``rmd-motion emulate``
            on a slcan or RS485 pseudo-terminal, built from the configuration file), as hardware would.
        bus_overrides: replace configured bus settings (``channel=...``, ``port=...``; an arm on several buses: a
            mapping of bus names per setting, ``channel={"left": ..., "right": ...}``).
        initial_deg: emulated joint angles at start (emulation only).
        emulator_log: write every frame the emulated drives receive and send to this file (emulation only).
        telemetry: record the run: a per-cycle log and/or a bus trace, written when the arm closes (see
            :mod:`motion.telemetry`); the files are created at :meth:`connect`, before anything moves.
        observe_collisions: run the collision observer (and record its residuals) even where no joint has a
            ``collision_threshold_nm`` (it always runs where one has), e.g. to calibrate thresholds.
        faults: emulated faults to schedule (emulation only; e.g. ``Fault(InjectedFault.COLLISION, ...)``, an
            external torque on a joint).
        forget_turns: the drives have been powered up since the last session: leave its recorded turn offsets
            aside, and resolve every joint from its ``power_on_window_deg`` (see :mod:`motion.control.turns`).
        keep_turns: the drives have stayed powered since the last session: its recorded turn offsets hold, where a
            reading alone cannot tell (a joint left a whole motor turn from its window).
        home: joints to home against their hard stops at :meth:`connect`, before the arm is handed over (their
            power-on windows are not consulted; see :mod:`motion.homing`).
        start_pose: emulation only: the emulated drives power up with the named joints at these angles, degrees
            (the others at 0), so that they know each joint only modulo ``360 / gear_ratio``, as real drives do;
            connect then resolves the turns as on hardware (unlike ``initial_deg``: drives powered up at the zero
            pose, which has since moved there).
        bus: a transport the caller made (a :class:`~motion.transport.Transport`: a kind of link rmd-motion has no
            backend for, a python-can bus set up elsewhere) to use instead of opening the configured bus; the arm takes
            it over and closes it when it closes (not with ``emulate`` or ``bus_overrides``). A
            :class:`~motion.emulator.simulated.SimulatedBus` runs on its simulation's clock: emulated drives the arm
            treats as hardware (their turns resolved and recorded between sessions on the same simulation).
        view: show the arm live in the browser while connected (``True``: on 127.0.0.1:8080; or a
            :class:`ViewOptions`); see :mod:`motion.view` (the ``view`` extra). In simulated emulation the
            simulation is then paced to the wall clock, so that the page shows the motion at its speed.
    """

    def __init__(
        self,
        config: ArmConfig,
        *,
        emulate: bool | str = False,
        bus_overrides: Mapping[str, object] | None = None,
        initial_deg: Sequence[float] | None = None,
        emulator_log: str | os.PathLike[str] | None = None,
        telemetry: TelemetryOptions | None = None,
        observe_collisions: bool = False,
        faults: Sequence[Fault] = (),
        forget_turns: bool = False,
        keep_turns: bool = False,
        home: Sequence[str] = (),
        start_pose: Mapping[str, float] | None = None,
        view: bool | ViewOptions = False,
        emulated_protocol: ProtocolFamily | str | Sequence[ProtocolFamily | str] | None = None,
        bus: Transport | None = None,
    ) -> None:
        if bus is not None:
            if not isinstance(bus, Transport):
                raise TypeError(f"bus: expected a motion.transport.Transport, got {type(bus).__name__}")
            if emulate or bus_overrides:
                raise ValueError("bus: a transport of the caller's own takes the place of emulate= and bus_overrides=")
        self._given_bus = bus
        self.config = with_bandwidth_gains(config)  # (gains from a bandwidth: the arm's model decides them)
        self._view_options = ViewOptions() if view is True else (view or None)
        #: The live page while connected with ``view=`` (see :mod:`motion.view`; ``view.url`` says where).
        self.view: LiveView | None = None
        self._start_pose = start_pose_of(config, start_pose, emulate, initial_deg)
        #: The emulated drives' protocol generation on each bus (the controller tells it at connect as with real
        #: drives).
        self.emulated_families = emulated_families(config, emulated_protocol)
        if forget_turns and keep_turns:
            raise ValueError("forget_turns and keep_turns: the drives either were powered up since or stayed powered")
        self._forget_turns = forget_turns
        self._keep_turns_given = keep_turns
        self._home = tuple(home)
        if self._home:
            homed_joints(config, self._home)  # an unknown or unhomeable joint is refused before anything opens
        #: What the latest homing found, per joint (see :meth:`home`).
        self.homing: list[HomingResult] = []
        self._clock: Clock | None = None
        #: Each joint's turn offset between the controller's frame and its drive's, and how it was found (set at
        #: :meth:`connect`; see :mod:`motion.control.turns`).
        self.turns: tuple[JointTurns, ...] = ()
        self._observe = observe_collisions
        self._faults = tuple(faults)
        #: ``None`` (hardware), ``"simulated"`` or ``"realtime"``.
        self.emulation: str | None = emulation_of(config, emulate)
        self.emulate = self.emulation is not None
        self._overrides = dict(bus_overrides or {})
        self._initial = initial_deg
        self._emulator_log = emulator_log
        self._telemetry_options = telemetry
        #: Joints with a stored position-loop identification, used while their drives keep its settings (hardware
        #: only; ``controller.tracking.identified`` says which are in use).
        self.tracking_offered: list[str] = []
        #: The file :meth:`identify_tracking` stored the identification in.
        self.tracking_file: Path | None = None
        #: The recording of the current run (with ``telemetry=``); its ``result`` is the log once the arm closed.
        self.telemetry: TelemetrySession | None = None
        self._stack = ExitStack()
        self.bus: Transport | None = None
        self.controller: Controller | None = None
        self.supervisor: Supervisor | None = None
        #: What the run did so far (following errors, current limits, timing) and a fault's likely cause
        #: (:mod:`motion.api.summary`); set at :meth:`connect`.
        self.summary: RunSummary | None = None
        self.emulator: Any = None
        self.plant: Any = None
        self.frame_log: FrameLog | None = None
        #: What the rate check at connect measured (see :mod:`motion.control.ratecheck`).
        self.rate_check: RateCheck | None = None
        #: The simulation of ``emulate=True`` (its emulator, wire and clock), once connected.
        self.simulation: Simulation | None = None
        self.names = config.joint_names
        self._index = {name: i for i, name in enumerate(self.names)}
        # While connect() or home() runs, a stop (stop(), request_stop(): any thread, a signal handler) is latched
        # here (its detail) until the next connect() or home(), and sent on to the loop running then (homing's or the
        # arm's, once started). No lock: a signal handler must never wait on one. A request writes the latch, then
        # reads the loop; a loop is registered, then reads the latch: in every interleaving one of them sees the
        # other, so no loop that starts during connect() or home() misses a stop.
        self._connecting = False
        self._stop_latch: str | None = None
        self._running: Supervisor | None = None
        # One session at a time: set from the start of connect() until close() (or a connect that failed), under a
        # lock, so that a second connect (of this thread, `arm.connect()` and then `with arm:`, or another) is refused
        # before it opens or sends anything.
        self._session_lock = threading.Lock()
        self._in_session = False

    @classmethod
    def from_config(cls, path: str | os.PathLike[str], *, emulate: bool | str = False, **kwargs: Any) -> Arm:
        """Load and validate ``path`` (the arm is connected by ``with`` or :meth:`connect`); when no such file exists,
        an example's name (``arm6.yaml``, ``configs/arm6.yaml``) loads the packaged example
        (:func:`motion.config.resolve_config`).

        Raises:
            ConfigError: the file is missing or invalid.
        """
        return cls(load_config_or_example(path), emulate=emulate, **kwargs)

    # ------------------------------------------------------------------------------------------------ lifecycle

    def connect(self) -> Arm:
        """Open the bus (and the emulator), read every joint's position, start the guarded loop holding it.

        A :meth:`stop` (or :meth:`request_stop`) meanwhile, from another thread or a signal handler, interrupts homing
        within one control cycle (every axis halted; a MotionFault of kind ``stop`` is raised), and an arm that has
        not started its loop yet starts it halted (FAULTED, kind ``stop``: :meth:`clear` before moving).

        An arm holds one session: connecting an arm that is connected (or connecting) raises before anything is
        opened or sent, and the running session goes on. A port or channel another session holds (another ``Arm``,
        in this process or another) is refused likewise (:class:`~motion.errors.PortHeld`).

        Raises:
            MotionError: the arm is connected already (``arm.connect()`` and then ``with arm:`` connects twice).
            PortHeld: another rmd-motion session holds the bus or port (nothing was sent).
            TransportError: the bus cannot be opened or a drive does not answer.
            RateError: the configured rate cannot be held on this host and bus (a ConfigError; nothing moved).
            StabilityError: torque mode's PD of some joint has no stability margin at the configured rate (a
                ConfigError, raised before the bus is opened; so is a ``safety.link_timeout_ms`` shorter than the
                loop leaves between a drive's frames).
            HomingError: a joint of ``home`` could not be homed (every axis halted).
            MotionFault: a fault or a stop halted every axis during homing.
        """
        check_envelope(self.config)  # before anything is opened: nothing to undo
        with self._session_lock:
            if self._in_session:
                raise MotionError(
                    f"arm {self.config.name!r} is connected already: an Arm holds one session (connect() and then "
                    "`with arm:` connects twice; use one of them, or close() first); the running session goes on"
                )
            self._in_session = True
        self._begin_connecting()
        try:
            if self._telemetry_options is not None:
                # Entered first, so closed last: the files are written once the loop and the bus have ended.
                robot = None
                if self._telemetry_options.log is not None:
                    from kinematics.frames import LinkFrames  # noqa: PLC0415 - (Pinocchio: only for a recording)

                    robot = LinkFrames(self.config)
                self.telemetry = self._stack.enter_context(
                    TelemetrySession(self._telemetry_options, self.config, emulated=self.emulate, robot=robot)
                )
            clock = None
            if self.emulation == "simulated":
                self.bus, clock = self._start_simulation()
                self._stack.callback(self.bus.close)
            elif self._given_bus is not None:  # the caller's transport: the arm takes it over (closed with the arm)
                self.bus = self._stack.enter_context(self._given_bus)
                if isinstance(self.bus, SimulatedBus):  # its drives' time is the simulation's
                    clock = SimulatedClock(self.bus.simulation)
            else:
                if self.emulation == "realtime":
                    self._start_emulator_process()
                self.bus = self._stack.enter_context(open_bus(self.config, **self._overrides))
            self.bus = self._negotiate(self.bus)
            self._clock = clock
            if self.telemetry is not None:
                self.telemetry.tap(self.bus)
            self.controller = self._new_controller()
            self.turns = self._resolve_turns(self.controller)
            self.controller.read_positions()
            if self._home:
                self.homing = self._home_joints(self._home)
            self._keep_turns()
            if self._view_options is not None:  # before the rate check and the loop: its start takes a CPU a while
                self._open_view(self._view_options)
            self.rate_check = check_rate(self.controller, self.config)
            if not self.emulate:  # an identification belongs to the drives it was made on
                self.tracking_offered = offer_stored_tracking(self.config, self.controller)
            self._start_supervisor()
            if self.view is not None and isinstance(self._clock, SimulatedClock):
                self._clock.pace(1.0)  # a simulated arm on view moves at the wall clock's speed
        except BaseException:
            try:
                self._stack.close()
            finally:
                self._in_session = False
            raise
        finally:
            self._connecting = False
        return self

    def _begin_connecting(self) -> None:
        """From here until :meth:`connect` or :meth:`home` returns, a stop is latched for the loops it starts."""
        self._stop_latch = None
        self._connecting = True

    def _register_loop(self, supervisor: Supervisor) -> None:
        """``supervisor`` (its loop not started yet) is where a stop goes from now on; a stop latched while connecting
        halts it in its first cycle."""
        self._running = supervisor
        latched = self._stop_latch
        if latched is not None:
            supervisor.request_estop(FaultKind.STOP, self._stop_detail(supervisor, latched))

    def _negotiate(self, bus: Transport) -> Transport:
        """The bus in the drives' protocol generation (:func:`motion.compose.negotiate_family`)."""
        spoken = negotiate_family(bus, self.config)
        if spoken is not bus:
            self._stack.enter_context(spoken)
        return spoken

    def _open_view(self, options: ViewOptions) -> None:
        controller = self.controller
        assert controller is not None

        def stop() -> None:  # before the loop runs nothing moves: there is nothing to stop
            if self.supervisor is not None:
                self.supervisor.request_estop(FaultKind.ESTOP, "STOP pressed in the view")

        self.view = LiveView(self.config, arm_figure, stop, host=options.host, port=options.port)
        self._stack.callback(self._close_view)
        controller.publisher.tap = self.view.publish

    def _close_view(self) -> None:
        if self.view is not None:
            if self.controller is not None:
                self.controller.publisher.tap = None
            self.view.close()
            self.view = None

    def _new_controller(self) -> Controller:
        assert self.bus is not None
        return build_controller(self.config, self.bus, feedforward=feedforward_for(self.config), clock=self._clock)

    def _start_supervisor(self) -> None:
        assert self.controller is not None
        self.supervisor = supervisor = build_supervisor(self.config, self.controller, observe=self._observe)
        self.summary = RunSummary(self.config, supervisor)
        self.controller.cycle_hooks.append(self.summary)
        if self.telemetry is not None:
            self.telemetry.attach(self.controller, supervisor)
        self._register_loop(supervisor)
        supervisor.start()

    def home(self, joints: Sequence[str]) -> list[HomingResult]:
        """Home ``joints`` against their hard stops (see :mod:`motion.homing`): the guarded loop ends (every axis
        halted with 0x81: the drives hold), the joints seek their stops one at a time under a homing loop of their
        own, and the arm's loop starts again in the corrected frame, holding where homing left it.

        A :meth:`stop` (or :meth:`request_stop`) meanwhile interrupts homing within one control cycle, as at
        :meth:`connect`.

        Raises:
            HomingError: a joint cannot be homed, or no stop was found (the arm is left halted and closed to motion
                until connected again).
            MotionFault: a fault or a stop halted the arm during homing (closed to motion as above).
            MotionError: the arm is not connected, not READY, or recording telemetry (home at connect instead:
                ``Arm(..., home=[...])``).
        """
        supervisor = self._guard()
        homed_joints(self.config, joints)
        if supervisor.state is not ArmState.READY:
            raise MotionError(f"homing needs the arm READY; it is {supervisor.state.value}")
        if self.telemetry is not None:
            raise MotionError("homing a recording arm: home at connect instead (Arm(..., home=[...]))")
        self._begin_connecting()
        try:
            quiet_ahead(supervisor)
            supervisor.close()
            fault = supervisor.fault
            if fault is not None and fault.kind is not FaultKind.CLOSE:
                raise fault  # a stop (or a fault) came before homing began: it does not begin
            self.supervisor = None
            self.controller = self._new_controller()
            self.controller.set_turns([j.turns for j in self.turns])
            self.controller.read_positions()
            self.homing = self._home_joints(joints)
            self._keep_turns()
            self._start_supervisor()
        finally:
            self._connecting = False
        return self.homing

    def _home_joints(self, names: Sequence[str]) -> list[HomingResult]:
        """Run the homing loop (the homing variant of the configuration on the same bus), then put the arm's
        controller (loop not running) in the corrected frame."""
        controller = self.controller
        assert controller is not None and self.bus is not None
        joints = homed_joints(self.config, names)
        variant = homing_variant(self.config, names)
        seeker = build_controller(variant, self.bus, clock=self._clock)
        seeker.set_turns(controller.turns)
        seeker.read_positions()
        supervisor = build_supervisor(variant, seeker)
        self._register_loop(supervisor)
        try:
            supervisor.start()
            check_seeks(supervisor, [(self._index[j.name], j) for j in joints], seeker.pause)
            results = [seek_stop(supervisor, self._index[j.name], j, seeker.pause) for j in joints]
        finally:
            self._running = None  # a stop from now on is latched for the arm's loop
            finish_halt(supervisor)
            quiet_ahead(supervisor)
            supervisor.close()
        controller.set_turns(corrected_turns(controller.turns, self._index.__getitem__, results))
        q = controller.read_positions()
        homed = {r.name for r in results}
        self.turns = tuple(
            dataclasses.replace(t, turns=k, source=Source.HOMED, joint_deg=float(q[i])) if t.name in homed else t
            for i, (t, k) in enumerate(zip(self.turns, controller.turns, strict=True))
        )
        return results

    def _keep_turns(self, angles_deg: Mapping[str, float] | None = None) -> None:
        """Record the turn offsets for the next session (on hardware; a file that cannot be written is a warning):
        every joint's where the controller reads it, or only those of ``angles_deg``, at those angles."""
        if not self._remembers or self.controller is None or self.bus is None or not self.turns:
            return
        try:
            save_turn_records(
                self.config,
                self.bus.describe(),
                self.controller,
                (j.source for j in self.turns),
                [j.power_on for j in self.turns],
                angles_deg=angles_deg,
            )
        except OSError as exc:
            logger.warning("turn offsets not kept for the next session: %s", exc)

    def _warn_ambiguous_pose(self, q_deg: FloatArray | None = None) -> None:
        """Warn of a joint left (or, with ``q_deg``, a motion planned to end) where the next session cannot tell its
        turns from its reading (a whole motor turn from its power-on window): it will ask whether the drives stayed
        powered (``--keep-turns``). (A V3 drive's reading is absolute: never.)"""
        controller = self.controller
        assert controller is not None
        absolute = {s.name for s, f in zip(controller.specs, controller.families, strict=True) if f.output_shaft}
        if len(absolute) == len(controller.specs):
            return
        q = controller.snapshot.position_deg if q_deg is None else q_deg
        for name, angle, window in ambiguous_joints(controller.base_transmission.transmissions, self.turns, q):
            if name in absolute:
                continue
            logger.warning(
                "joint %s %s %.2f deg, a whole number of motor turns from its power_on_window_deg [%g, %g]: after a "
                "power cycle there a session cannot tell from its reading whether the drives were powered up meanwhile "
                "and will ask (--keep-turns if they stayed powered); move it elsewhere, or home it after a power cycle",
                name,
                "is left at" if q_deg is None else "is planned to end at",
                angle,
                *window,
            )

    @property
    def _remembers(self) -> bool:
        """Whether the turn offsets are kept between sessions: on hardware (emulated drives are new every run)."""
        return not self.emulate

    def _resolve_turns(self, controller: Controller) -> tuple[JointTurns, ...]:
        if self.emulation == "simulated" and self._start_pose is None:
            return emulated_frames(controller, self.config)
        records = None
        if self._remembers and not self._forget_turns:
            records = load_turn_records(self.config, controller.bus.describe())
        return resolve_frames(
            controller, self.config, records=records, provisional=self._home, stayed_powered=self._keep_turns_given
        )

    def _remember_turns(self) -> None:
        """At close: keep the turn offsets for the next session of the joints its end saw at rest, where they came to
        rest (:func:`motion.keep.resting_angles`): a joint whose drive restarted, or that still coasted, has none (the
        next session resolves it afresh)."""
        if not self._remembers or self.supervisor is None:
            return
        self._keep_turns(resting_angles(self.supervisor))
        if self.controller is not None and self.turns:
            self._warn_ambiguous_pose()

    def _start_simulation(self) -> tuple[Transport, SimulatedClock]:
        from motion.emulator.arm import arm_emulator  # noqa: PLC0415 - as above

        initial = self._start_pose if self._start_pose is not None else self._initial
        self.emulator, self.plant = arm_emulator(
            self.config, initial_deg=initial, faults=self._faults, family=self.emulated_families
        )
        if self._start_pose is not None:
            self.emulator.power_cycle()  # powered up there: each drive counts its turns from this pose
        simulation = Simulation(self.emulator, lines=simulated_lines(self.config))
        if self._emulator_log is not None:
            self.frame_log = self._stack.enter_context(FrameLog(self._emulator_log, clock=simulation.now))
            simulation.frame_log = self.frame_log
        self.simulation = simulation
        # the bus opens in the configured generation (auto: the older) and is told the drives' at connect
        names = [bus.name for bus in self.config.buses]
        return SimulatedBus(simulation, opening_families(self.config), names=names), SimulatedClock(simulation)

    def _start_emulator_process(self) -> None:
        if self._initial is not None:
            raise MotionError("initial_deg applies to simulated emulation only (emulate=True)")
        pose = None if self._start_pose is None else dict(zip(self.config.joint_names, self._start_pose, strict=True))
        self._overrides = self._stack.enter_context(
            emulator_process(
                self.config,
                log=self._emulator_log,
                faults=self._faults,
                start_pose=pose,
                protocol=self.emulated_families,
            )
        )

    def close(self) -> None:
        """Halt every axis (0x81), end the loop, release the bus and write the telemetry; safe to call twice."""
        try:
            if self.supervisor is not None:
                fault, summary = self.supervisor.fault, self.summary
                if fault is not None and fault.cause is None and summary is not None:
                    fault.cause = summary.cause(fault)  # (the raised fault is this one: its handler reads the cause)
                self.supervisor.close()
                self._remember_turns()
        finally:
            self._running = None  # (a stop during a later connect goes to that connect's loops, not to this one)
            try:
                self._stack.close()
            finally:
                self._in_session = False

    def __enter__(self) -> Arm:
        return self.connect()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: types.TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ motion

    def _guard(self) -> Supervisor:
        if self.supervisor is None:
            raise MotionError("the arm is not connected: use `with Arm.from_config(...) as arm` or arm.connect()")
        return self.supervisor

    def positions(self) -> dict[str, float]:
        """Measured joint angles, degrees (of the latest cycle's published snapshot)."""
        q = self._guard().controller.snapshot.position_deg
        return {name: float(q[i]) for i, name in enumerate(self.names)}

    def motion_ranges(self, joint: str) -> MotionRanges:
        """The ranges of ``joint``'s V3 drive for the motion frame (0x400: a ``MotionCommand`` needs them), from the
        firmware date and model the drive told at connect (see :mod:`motion.protocol.v3.motion_frame`).

        Raises:
            MotionError: the arm is not connected.
            PlanningError: no joint of that name.
            EncodeError: the drive told no firmware date at connect (the older family has no motion frame), or its
                firmware's ranges are not known for its model.
        """
        supervisor = self._guard()
        ids = {j.name: j.address for j in self.config.joints}
        if joint not in ids:
            raise PlanningError(f"motion_ranges: unknown joint {joint!r}; joints: {', '.join(ids)}")
        motor_id = ids[joint]
        identity = supervisor.controller.bus.identities.get(motor_id)
        if identity is None:
            raise EncodeError(
                "firmware_date", "the drive's firmware date and model, told at connect (V3 drives)", None,
                f"the motion frame of joint {joint} (motor {motor_id % ADDRESS_STRIDE})",
            )  # fmt: skip
        return identity.motion_ranges()

    def move_to(self, targets: Mapping[str, float], *, speed_scale: float = 1.0, wait: bool = True) -> MotionHandle:
        """Move the named joints to their targets (degrees); the others keep their reference.

        A move (or :meth:`follow`) given while another motion runs, from this thread or any other, takes its place: it
        is planned from the reference at that instant (no step in speed), and the earlier motion's handle ends at once
        with ``arrival.arrived`` False, ``arrival.reason`` ``superseded``.

        Raises:
            PlanningError: an unknown joint, a target outside the joint limits, a bad speed scale (nothing moves).
            MotionFault: the arm is faulted, or a fault halted it during the move (with ``wait``).
        """
        supervisor = self._guard()
        q = joint_targets(targets, supervisor.controller.reference.position, self._index)
        superseding = not supervisor.controller.idle
        ticket = supervisor.move_to(q, speed_scale)
        self._superseding(superseding)
        if self._remembers:
            self._warn_ambiguous_pose(q)
        return self._handle(supervisor, wait, ticket, q)

    def follow(
        self,
        waypoints: Sequence[Mapping[str, float] | Sequence[float]],
        *,
        speed_scale: float = 1.0,
        wait: bool = True,
    ) -> MotionHandle:
        """Pass through every waypoint without stopping where the motion continues; stop at the last.

        A waypoint is a mapping of joint names (unnamed joints keep the previous waypoint's value) or a full list
        of angles in joint order, degrees.
        """
        supervisor = self._guard()
        rows = waypoint_rows(waypoints, supervisor.controller.reference.position, self._index)
        superseding = not supervisor.controller.idle
        ticket = supervisor.follow(rows, speed_scale)
        self._superseding(superseding)
        if self._remembers:
            self._warn_ambiguous_pose(rows[-1])
        return self._handle(supervisor, wait, ticket, rows[-1])

    @staticmethod
    def _superseding(superseding: bool) -> None:
        """A motion given while another ran takes its place: said in the log, not only by the earlier handle."""
        if superseding:
            logger.info("a motion was given while another ran: it takes that one's place (that one ends superseded)")

    def _handle(self, supervisor: Supervisor, wait: bool, ticket: MotionTicket, target_deg: FloatArray) -> MotionHandle:
        """The handle of the motion just queued (with the configured goal tolerance), waited for with ``wait``."""
        handle = MotionHandle(supervisor, self.config.control, ticket=ticket, target_deg=target_deg)
        if wait:
            handle.wait()
        return handle

    def sleep(self, duration_s: float) -> None:
        """Let ``duration_s`` seconds pass with the arm under control (holding, or moving with ``wait=False``).

        In simulated emulation this is how time passes: the control cycles run in this call. Otherwise it sleeps.

        Raises:
            ValueError: ``duration_s`` is not a finite number of seconds >= 0.
        """
        self._guard().controller.pause(seconds("duration_s", duration_s))

    def identify_tracking(self, *, store: bool = True) -> dict[str, PositionLoopFit]:
        """Identify every joint's position loop with a short full-speed move out and back, one joint at a time (see
        :func:`motion.compose.identify_position_loops`); the following-error check uses the result from now on and,
        with ``store`` (on hardware), in every later connection while the drives keep their gains.

        Raises:
            MotionError: not in position mode.
            MotionFault: a fault halted the arm during a move.
        """
        supervisor = self._guard()
        fits = identify_position_loops(supervisor, self.config)
        if store and not self.emulate:
            self.tracking_file = store_tracking(self.config, supervisor.controller, fits)
        return fits

    def hold(self) -> None:
        """Jerk-limited stop of the current motion; the arm holds where it ends (not a fault)."""
        self._guard().stop_motion()

    def stop(self, timeout_s: float = 1.0) -> None:
        """E-stop: halt every axis now with 0x81 (0x80 under ``halt_policy: off``); clear() before moving again.

        Unlike a fault under ``halt_policy: hold``, an explicit stop never streams a ramp: the drives stop themselves.
        Any thread may call it, also while :meth:`connect` or :meth:`home` runs (see there: homing is interrupted);
        it returns once the halt went out (at most ``timeout_s``), or at once when no loop runs yet (the first cycle
        of the next one halts).

        Raises:
            MotionError: the arm is neither connected nor connecting.
        """
        loop = self._request_stop(_STOP_DETAIL)
        if loop is not None:
            loop.controller.wait_for(lambda: loop.state.faulted, timeout_s)

    def request_stop(self, detail: str = _STOP_DETAIL) -> None:
        """Ask for the E-stop of :meth:`stop` and return at once: the running loop halts every axis in its next cycle.

        It never waits for the loop, runs a simulated one or takes a lock: safe from any thread and from a signal
        handler (``rmd-motion``'s Ctrl-C). ``detail`` goes into the fault (``"SIGINT"``).

        Raises:
            MotionError: the arm is neither connected nor connecting.
        """
        self._request_stop(detail)

    def _request_stop(self, detail: str) -> Supervisor | None:
        """The stop to the loop running now (see ``_stop_latch`` in ``__init__``); returns that loop, if any."""
        if self._connecting:
            self._stop_latch = detail
        loop = self._running
        if loop is None:
            if self._connecting:
                return None  # the next loop halts in its first cycle
            loop = self._guard()  # connected: the arm's loop (raises when never connected)
        loop.request_estop(FaultKind.STOP, self._stop_detail(loop, detail))
        return loop

    def _stop_detail(self, loop: Supervisor, detail: str) -> str:
        """The fault's detail of a stop: ``detail``, and what it interrupted."""
        return detail if loop is self.supervisor else f"{detail} during homing: homing interrupted"

    def clear(self) -> None:
        """Clear a fault (0x9B); raises MotionFault ``clear_failed`` while a cause persists."""
        self._guard().clear()

    @property
    def fault(self) -> MotionFault | None:
        """The fault that halted the arm, if any."""
        return self._guard().fault

    def status(self) -> ArmStatus:
        """Measured and reference state of every joint, the arm state and the loop statistics."""
        return arm_status(self.config.name, self._guard().controller, [b.name for b in self.config.buses])
