"""Commands that run the guarded control loop: ``move`` and ``run``.

The arm connects (reads every joint, homes the joints asked for, starts the loop holding where it is), moves, and
closes: closing halts every axis with 0x81 and releases the bus. Ctrl-C or SIGTERM during any of it is an E-stop:
the loop running then (homing's while connecting) halts every axis in its next cycle, the bus is released, and the
command exits with 130.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any, Final, TextIO

from motion.api import Arm, MotionHandle
from motion.cli.common import (
    EXIT_FAULT,
    EXIT_OK,
    Interrupts,
    Session,
    UsageError,
    parse_pose,
    parse_targets,
    print_json,
    print_table,
    view_options,
    warn,
)
from motion.cli.program import MoveStep, PathStep, Program, WaitStep, load_program
from motion.compose import session_link_timeout_ms
from motion.config import ArmConfig, JointConfig
from motion.control.family import FAMILIES
from motion.errors import MotionError, MotionFault, PortLost
from motion.homing import homed_joints
from motion.telemetry import TelemetryOptions

if TYPE_CHECKING:
    from motion.api.commissioning import HoldingVerdict

#: How often the progress display is refreshed (and the wait for a motion polled), s.
POLL_S: Final = 0.1
#: While the view stays open after a command: how long each wait runs the loop, s.
VIEW_POLL_S: Final = 0.2
#: Width of the terminal progress bar, characters.
BAR_WIDTH: Final = 30


class Progress:
    """A motion's progress on ``stream``: a bar redrawn in place on a terminal, otherwise two plain lines.

    Args:
        label: what moves (``move``, ``step 2/5 path``).
        stream: where to write (stderr: stdout stays for results).
    """

    def __init__(self, label: str, stream: TextIO) -> None:
        self.label = label
        self.stream = stream
        self.tty = stream.isatty()
        self._drawn = False
        self._announced = False

    def update(self, elapsed_s: float, total_s: float) -> None:
        """The motion is ``elapsed_s`` into its planned ``total_s``."""
        if self.tty:
            shown_s = min(max(elapsed_s, 0.0), total_s)
            filled = round(BAR_WIDTH * shown_s / total_s) if total_s > 0 else BAR_WIDTH
            bar = "#" * filled + "-" * (BAR_WIDTH - filled)
            self.stream.write(f"\r{self.label} [{bar}] {shown_s:5.1f}/{total_s:.1f} s")
            self.stream.flush()
            self._drawn = True
        elif not self._announced:
            print(f"{self.label}: {total_s:.2f} s planned", file=self.stream, flush=True)
            self._announced = True

    def close(self, outcome: str) -> None:
        """End the display with ``outcome`` (``done in 1.23 s``, ``halted``)."""
        if self._drawn:
            self.stream.write("\n")
        print(f"{self.label}: {outcome}", file=self.stream, flush=True)


def wait_with_progress(arm: Arm, handle: MotionHandle, label: str) -> float:
    """Wait for a motion while showing its progress on stderr; returns the wall time it took, s.

    Raises:
        MotionFault: a fault halted every axis.
    """
    progress = Progress(label, sys.stderr)
    now_s = _arm_clock(arm)
    start = now_s()
    outcome = "ended"
    try:
        while not handle.wait(POLL_S):
            now = handle.progress()
            if now.duration_s > 0:
                progress.update(now.elapsed_s, now.duration_s)
        outcome = f"done in {now_s() - start:.2f} s"
        if handle.arrival is not None:
            outcome += f" ({handle.arrival.text(arm.config.control.goal_tolerance_deg)})"
    except KeyboardInterrupt:
        outcome = "interrupted"
        raise
    except MotionFault:
        outcome = "halted by a fault"
        raise
    finally:
        progress.close(outcome)
    return now_s() - start


def _arm_clock(arm: Arm) -> Callable[[], float]:
    """The arm's own clock (simulated time with ``--emulate``, the monotonic clock on hardware), s."""
    controller = arm.controller
    return controller.clock.now if controller is not None else time.monotonic


def hold_for(arm: Arm, seconds: float) -> None:
    """Hold for ``seconds`` (the loop keeps the arm where it is).

    Raises:
        MotionFault: a fault halted every axis meanwhile.
    """
    if arm.emulation == "simulated":  # simulated time passes in the arm's own sleep
        arm.sleep(seconds)
        if arm.fault is not None:
            raise arm.fault
        return
    end = time.monotonic() + seconds
    while (remaining := end - time.monotonic()) > 0:
        time.sleep(min(POLL_S, remaining))
        fault = arm.fault
        if fault is not None:
            raise fault


def undelivered_halt(arm: Arm) -> PortLost | None:
    """When the arm's bus was lost under its running loop (a dead adapter, an unplugged cable): the error that says
    so, that the halt could not be delivered, and what stops the drives instead; else None."""
    bus = arm.bus
    if bus is None or bus.lost is None:
        return None
    # (while homing or connecting there is no supervisor: the drives' settings are those a session sets)
    protected = {FAMILIES[f].link_protection for f in bus.families}  # (an arm's buses may have drives of both)
    timeout_ms = session_link_timeout_ms(arm.config) if True in protected else 0
    fallback = []
    if timeout_ms:
        fallback.append(
            f"drives with driver V3 stop by themselves after safety.link_timeout_ms = {timeout_ms} ms "
            "without a frame (their link-loss protection); make sure they did, with the hardware E-stop (cut the "
            "motor power) if not"
        )
    elif True in protected:
        fallback.append(
            "the drives' link-loss protection is off (safety.link_timeout_ms: 0): they keep their last command until "
            "their power is cut: use the hardware E-stop now"
        )
    if False in protected:
        fallback.append(
            "drives of the older generation keep executing their last command (a set-point is held, a torque or "
            "speed is kept) until their power is cut: use the hardware E-stop now"
        )
    told = "; ".join(fallback)
    return PortLost(f"the bus was lost ({bus.lost}): the halt could not be delivered to the drives; {told}")


def with_arm(
    args: argparse.Namespace,
    session: Session,
    interrupts: Interrupts,
    body: Callable[[Arm], int],
    *,
    config: ArmConfig | None = None,
    **options: Any,
) -> int:
    """Connect the arm (recording ``--log`` / ``--trace``), run ``body``, close the arm; an interrupt halts every
    axis first. ``config`` replaces the session's configuration, ``options`` go to :class:`~motion.api.Arm`.

    Raises:
        KeyboardInterrupt: after the E-stop and the close (the caller exits with 130).
        OSError: a telemetry file cannot be created (before anything moves) or written.
        PortLost: the bus was lost under the running loop (in place of whatever else was raised): the halt could not
            be delivered; its message says what stops the drives then.
    """
    log, trace = getattr(args, "log", None), getattr(args, "trace", None)
    try:
        telemetry = TelemetryOptions(log, trace) if log or trace else None
    except ValueError as exc:
        raise UsageError(f"--log {exc}") from None
    overrides = session.overrides
    if options.get("emulate"):
        if overrides:
            given = ", ".join(f"--{name}" for name in overrides if name != "sleep_after_open")
            raise UsageError(f"--emulate opens no port: drop {given}")
        overrides = {}
    options.setdefault("forget_turns", getattr(args, "forget_turns", False))
    options.setdefault("keep_turns", getattr(args, "keep_turns", False))
    options.setdefault("view", view_options(args) or False)
    if getattr(args, "start_pose", None):
        if not options.get("emulate"):
            raise UsageError("--start-pose applies to the emulated drives of --emulate")
        options["start_pose"] = parse_pose(config or session.config, args.start_pose)
    arm = Arm(config or session.config, bus_overrides=overrides, telemetry=telemetry, **options)
    try:
        # a signal asks the running loop for the E-stop at once (also homing's, while connecting): every axis halted
        # in its next cycle, whatever the main thread is doing
        with interrupts.halting(arm.request_stop):
            # a signal while connecting is raised once the loop runs, or once connect ended (a homing it halted)
            with interrupts.deferred():
                arm.connect()
            if arm.view is not None:
                print(f"view: {arm.view.url}", file=sys.stderr, flush=True)
            code = body(arm)
        return keep_view_open(arm) if arm.view is not None and code == EXIT_OK else code
    except KeyboardInterrupt as interrupt:
        interrupts.ignore()
        warn(_halt_after_interrupt(arm, interrupt.__cause__))
        raise
    finally:
        with interrupts.deferred():
            arm.close()  # halts every axis (0x81) unless halted already, releases the bus
        lost = undelivered_halt(arm)
        if lost is not None:
            raise lost
        # (only the drives that never answered: one that answered and then missed a read is halted all the same)
        silent = sorted(arm.supervisor.unanswered) if arm.supervisor is not None else []
        if silent:  # "every axis halted" does not hold for these
            labels = {j.address: f"{j.name} ({j.drive_label})" for j in arm.config.joints}
            warn(
                f"{', '.join(labels.get(a, f'motor {a}') for a in silent)} never acknowledged the halt (sent to them "
                "every cycle until "
                "the arm closed): they may still run their last command; use the hardware E-stop"
            )


def _halt_after_interrupt(arm: Arm, cause: BaseException | None) -> str:
    """After Ctrl-C or SIGTERM: the E-stop of the arm's loop, if it runs (the signal asked for it already: this waits
    for it to go out); returns what was halted, for stderr.

    Args:
        cause: what ended a connect that the signal interrupted (the fault of a homing it halted), if anything.
    """
    if arm.supervisor is not None:
        try:
            arm.stop()  # E-stop: every axis halted in the next cycle
        except MotionError as exc:  # already closed: closing halted the axes
            warn(f"E-stop: {exc}")
        return "interrupted: E-stop sent to every axis"
    if isinstance(cause, MotionFault):
        return f"interrupted: every axis halted ({cause})"
    if cause is not None:
        return f"interrupted while connecting, which ended with {type(cause).__name__}: {cause}"
    return "interrupted before the arm connected: nothing moved"


def keep_view_open(arm: Arm) -> int:
    """After the command's work: the arm holds (its loop running, simulated time paced) and the view stays open
    until Ctrl-C or SIGTERM; exit 0, or 1 when STOP (or another fault) halted the arm meanwhile."""
    assert arm.view is not None
    print(f"done; the view stays open at {arm.view.url}: Ctrl-C ends", file=sys.stderr, flush=True)
    try:
        while True:
            arm.sleep(VIEW_POLL_S)
    except KeyboardInterrupt:
        pass
    fault = arm.fault
    if fault is not None:
        warn(f"motion fault while the view was open: {fault}")
        return EXIT_FAULT
    return EXIT_OK


def _summary(command: str, arm: Arm, wall_s: float, extra: Mapping[str, object]) -> dict[str, object]:
    assert arm.summary is not None and arm.controller is not None  # (connected)
    summary = arm.summary.as_dict(arm.controller)
    return {
        "command": command,
        **extra,
        "duration_s": round(wall_s, 3),
        "status": arm.status().as_dict(),
        "run": summary,
    }


@contextlib.contextmanager
def _summary_on_fault(command: str, arm: Arm, args: argparse.Namespace, extra: Mapping[str, object]) -> Iterator[None]:
    """``move`` / ``run``: a fault that halts the arm is reported with the run's summary as far as it went (``--json``:
    the summary with the fault and its likely cause on stdout), then raised on (the command exits with its code)."""
    now_s = _arm_clock(arm)
    start = now_s()
    try:
        yield
    except MotionFault as fault:
        if arm.summary is not None and arm.controller is not None:
            if args.json:
                said = {
                    "kind": str(fault.kind),
                    "joint": fault.joint,
                    "joints": list(fault.joints),
                    "value": fault.value,
                    "threshold": fault.threshold,
                    "time_s": fault.time_s,
                    "detail": fault.detail,
                    "cause": fault.cause,
                }
                print_json(_summary(command, arm, now_s() - start, {**extra, "fault": said}))
            else:
                print(f"run until the fault: {arm.summary.text(arm.controller)}")
        raise


def _print_positions(arm: Arm, wall_s: float) -> None:
    reached = " ".join(f"{name}={deg:.2f}" for name, deg in arm.positions().items())
    print(f"at {reached} deg after {wall_s:.2f} s")
    if arm.summary is not None and arm.controller is not None:
        print(f"run: {arm.summary.text(arm.controller)}")


def move(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``move JOINT=DEG ...``: every target is checked before the bus is opened."""
    session = Session.from_args(args)
    targets = parse_targets(session.config, args.targets)

    def body(arm: Arm) -> int:
        verdicts = holding_first(arm, args)
        extra: dict[str, object] = {"targets": targets, "speed_scale": args.speed_scale, "holding": verdicts}
        with _summary_on_fault("move", arm, args, extra):
            handle = arm.move_to(targets, speed_scale=args.speed_scale, wait=False)
            wall = wait_with_progress(arm, handle, "move")
        if args.json:
            extra["arrival"] = None if handle.arrival is None else dataclasses.asdict(handle.arrival)
            print_json(_summary("move", arm, wall, extra))
        else:
            _print_positions(arm, wall)
        return EXIT_OK

    return with_arm(args, session, interrupts, body, emulate=args.emulate)


#: ``jog``: the default excursion, joint degrees, and the speed scale of the jog.
JOG_DEG = 5.0
JOG_SPEED_SCALE = 0.1
#: A drive whose angle changed by less than this share of the commanded excursion (motor side) did not move.
JOG_MOVED_SHARE = 0.5


def jog(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``jog JOINT [--deg D]``: move one joint slowly by D degrees and back, and report which drive's angle changed
    and by how much (commissioning: the user watches that the configured joint moved, the configured way, as far)."""
    session = Session.from_args(args)
    joint = session.joint(args.joint)
    if args.deg == 0.0 or not math.isfinite(args.deg):
        raise UsageError(f"--deg: a non-zero number of joint degrees, found {args.deg:g}")

    def body(arm: Arm) -> int:
        assert arm.controller is not None
        controller = arm.controller
        start = arm.positions()
        target = start[joint.name] + args.deg
        if not joint.position_min_deg <= target <= joint.position_max_deg:
            raise UsageError(
                f"{joint.name} at {start[joint.name]:.2f} deg: {args.deg:+g} deg takes it outside its limits "
                f"[{joint.position_min_deg:g}, {joint.position_max_deg:g}]: jog the other way (--deg {-args.deg:g})"
            )
        before = controller.axes.motor_deg.copy()
        wait_with_progress(arm, arm.move_to({joint.name: target}, speed_scale=JOG_SPEED_SCALE, wait=False), "jog")
        turned = controller.axes.motor_deg - before
        wait_with_progress(
            arm, arm.move_to({joint.name: start[joint.name]}, speed_scale=JOG_SPEED_SCALE, wait=False), "back"
        )
        expected = args.deg * joint.direction * joint.gear_ratio  # motor degrees
        rows, moved = [], []
        for spec, delta in zip(controller.specs, turned, strict=True):
            if abs(delta) >= JOG_MOVED_SHARE * abs(expected):
                moved.append((spec, float(delta)))
            rows.append((spec.name, spec.drive_label.removeprefix("motor "), f"{delta:+.2f}"))
        report = _jog_verdict(joint, expected, moved, args.deg)
        if args.json:
            turned_by = {spec.name: round(float(d), 3) for spec, d in zip(controller.specs, turned, strict=True)}
            print_json(
                {"joint": joint.name, "deg": args.deg, "expected_motor_deg": expected, "turned_motor_deg": turned_by,
                 "verdict": report}
            )  # fmt: skip
        else:
            print_table(("joint", "motor", "motor deg turned"), rows)
            print(report)
        return EXIT_OK

    return with_arm(args, session, interrupts, body, emulate=args.emulate)


def _verdict_dict(verdict: HoldingVerdict) -> dict[str, Any]:
    return dataclasses.asdict(verdict) | {"matches": verdict.matches}


def holding_first(arm: Arm, args: argparse.Namespace) -> list[dict[str, Any]] | str:
    """``move`` / ``run`` / ``collision-calibrate``: the holding check before the first motion (``home``: after the
    seek, before the arm is handed over) (:mod:`motion.api.commissioning`), on real buses (emulated drives are built
    from the configuration itself: they always match it) unless ``--no-holding-check``. Returns the verdicts for
    ``--json``, or why the check was skipped.

    Raises:
        UsageError: a joint's holding torque differs from the model's beyond its bound (each such joint named with
            what may be wrong; with ``--json`` the verdicts are printed first): nothing (more) has moved.
        MotionFault: the arm is halted by a fault, or one halted it during the check.
    """
    if args.no_holding_check:
        return "skipped: --no-holding-check"
    if args.emulate:
        return "skipped: --emulate (the emulated drives are built from the configuration)"
    from motion.api.commissioning import check_holding  # noqa: PLC0415 - Pinocchio only where a check needs it

    verdicts = check_holding(arm)
    wrong = [v for v in verdicts if not v.matches]
    if wrong:
        if args.json:
            moved = args.command == "home"  # (home: the seek has moved the homed joints; nothing moves after it)
            print_json({"command": args.command, "holding": [_verdict_dict(v) for v in verdicts], "moved": moved})
        said = "; ".join(v.text() for v in wrong)
        raise UsageError(
            f"holding torque does not match the model: {said}. Check the configuration before moving "
            "(`rmd-motion check --holding` shows every joint; --no-holding-check skips this check)"
        )
    return [_verdict_dict(v) for v in verdicts]


def holding(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``check --holding``: connect, hold still, and set each joint's holding torque against the model's gravity
    torque (:mod:`motion.api.commissioning`); exit 2 when a joint's differs beyond its bound (naming what may be
    wrong)."""
    from motion.api.commissioning import check_holding  # noqa: PLC0415 - Pinocchio only where a check needs it

    session = Session.from_args(args)

    def body(arm: Arm) -> int:
        verdicts = check_holding(arm)
        if args.json:
            print_json({"joints": [_verdict_dict(v) for v in verdicts]})
        else:
            for verdict in verdicts:
                print(verdict.text())
        wrong = [v for v in verdicts if not v.matches]
        if wrong:
            names = ", ".join(v.name for v in wrong)
            raise UsageError(
                f"holding torque does not match the model for {names}: check the configuration before moving"
            )
        return EXIT_OK

    return with_arm(args, session, interrupts, body, emulate=getattr(args, "emulate", False))


def _jog_verdict(joint: JointConfig, expected_motor_deg: float, moved: list[tuple[Any, float]], deg: float) -> str:
    """In words: which drives turned against what was commanded, and what the user must watch. The readings follow
    the configuration (the drive is commanded and read through the same ``motor_id``, ``direction`` and
    ``gear_ratio``), so only the arm itself shows a swapped id, a reversed direction or a wrong gear."""
    label = f"{joint.name} ({joint.drive_label})"
    ids = [spec.motor_id for spec, _ in moved]  # (the drives' addresses)
    if not moved:
        return (
            f"{label} was commanded {expected_motor_deg:+.1f} motor deg and no drive turned: check that the joint is "
            "free to move and its drive runs (`rmd-motion status`)"
        )
    if ids != [joint.address]:
        turned = ", ".join(f"{spec.drive_label} ({spec.name}) {delta:+.1f} motor deg" for spec, delta in moved)
        return f"{label} was commanded {expected_motor_deg:+.1f} motor deg; turned: {turned}: the joints are coupled?"
    delta = moved[0][1]
    if not 0.8 <= delta / expected_motor_deg <= 1.25:
        return (
            f"{label} turned {delta:+.1f} motor deg for {expected_motor_deg:+.1f} commanded: the drive did not follow"
        )
    return (
        f"{label} turned {delta:+.1f} motor deg, as commanded. Its reading follows the configuration, so watch the "
        f"arm: {joint.name} should have moved {deg:+g} deg and back. If another joint moved, its motor_id is "
        f"another's; if it moved the other way, flip its direction; if it moved {joint.gear_ratio:g} times too far "
        "or too little, fix its gear_ratio"
    )


def run_program(arm: Arm, program: Program, speed_scale: float) -> None:
    """Run every step of ``program``, each step's speed scale times ``speed_scale``."""
    count = len(program.steps)
    for index, step in enumerate(program.steps):
        if isinstance(step, WaitStep):
            print(f"step {index + 1}/{count} wait: {step.seconds:g} s", file=sys.stderr, flush=True)
            hold_for(arm, step.seconds)
            continue
        scale = step.speed_scale * speed_scale
        if isinstance(step, MoveStep):
            handle = arm.move_to(step.targets, speed_scale=scale, wait=False)
            label = f"step {index + 1}/{count} move"
        else:
            assert isinstance(step, PathStep)
            handle = arm.follow(list(step.waypoints), speed_scale=scale, wait=False)
            label = f"step {index + 1}/{count} path ({len(step.waypoints)} waypoints)"
        wait_with_progress(arm, handle, label)


def run(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``run PROGRAM.yaml``: the whole program is validated before the bus is opened."""
    session = Session.from_args(args)
    program = load_program(args.program, session.config)

    def body(arm: Arm) -> int:
        verdicts = holding_first(arm, args)
        now_s = _arm_clock(arm)
        start = now_s()
        extra = {"program": program.source, "steps": len(program.steps), "holding": verdicts}
        with _summary_on_fault("run", arm, args, extra):
            run_program(arm, program, args.speed_scale)
        wall = now_s() - start
        if args.json:
            print_json(_summary("run", arm, wall, extra))
        else:
            _print_positions(arm, wall)
        return EXIT_OK

    return with_arm(args, session, interrupts, body, emulate=args.emulate)


def home(args: argparse.Namespace, interrupts: Interrupts) -> int:
    """``home JOINT...``: each joint seeks its configured hard stop, backs off, and its turn offset is set from it;
    then the holding check (as before a move: a homed joint's angle is known only now), exit 2 on a mismatch."""
    session = Session.from_args(args)
    joints = tuple(args.joints)
    homed_joints(session.config, joints)  # refused before the bus is opened

    def body(arm: Arm) -> int:
        verdicts = holding_first(arm, args)
        rows = [
            {
                "joint": r.name,
                "stop_found_deg": round(r.stop_found_deg, 3),
                "turns_correction": r.turns_correction,
                "remainder_deg": round(r.remainder_deg, 3),
                "seek_s": round(r.seek_s, 3),
                "current_a": round(r.current_a, 3),
            }
            for r in arm.homing
        ]
        if args.json:
            print_json({"command": "home", "joints": rows, "holding": verdicts, "status": arm.status().as_dict()})
            return EXIT_OK
        for r in arm.homing:
            print(
                f"{r.name}: stop reached after {r.seek_s:.2f} s at {r.current_a:.2f} A; turn offset corrected by "
                f"{r.turns_correction:+d} motor turns (the stop yielded {r.remainder_deg:+.2f} deg)"
            )
        reached = " ".join(f"{name}={deg:.2f}" for name, deg in arm.positions().items())
        print(f"at {reached} deg")
        return EXIT_OK

    return with_arm(args, session, interrupts, body, emulate=args.emulate, home=joints)
