"""The main job (``rmd-motion demo``): the 6-DOF example arm on emulated drives, recorded and plotted.

Two runs of ``configs/arm6.yaml`` on emulated CAN drives, each with its telemetry (per-cycle log and candump trace)
and a plot:

1. ``position``: a waypoint path through every joint's range in position mode (0xA4 streaming);
2. ``torque``: from where the path ended, the arm holds against gravity, makes a coordinated move and holds again in
   torque mode with gravity feed-forward (the same configuration with ``control.mode: torque``).

``--drives v3`` runs both on emulated V3-driver drives (the newer protocol family, told at connect as with real
drives), with ``configs/arm6_v3.yaml``: the same arm on those drives (at 125 Hz: they report whole degrees, so every
cycle also reads the fine angle, twice the frames of the older family; see the file's header).

The configuration is the packaged example (:func:`motion.config.example_config`), the same file in a wheel, an
editable install and a source checkout: the demo runs from any directory.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from motion.api import Arm, realtime_capacity
from motion.config import ArmConfig, example_config, load_config
from motion.config.schema import ControlMode, ProtocolSetting
from motion.errors import ConfigError, MotionError, MotionFault, TransportError
from motion.plot import plot_log
from motion.protocol.generation import GENERATIONS
from motion.protocol.table import ProtocolFamily
from motion.telemetry import TelemetryLog, TelemetryOptions
from motion.view import ViewOptions

CONFIG_NAME = "arm6.yaml"
#: The configuration of each drive generation's runs.
CONFIG_NAMES = {ProtocolFamily.V2: CONFIG_NAME, ProtocolFamily.V3: "arm6_v3.yaml"}
DEFAULT_OUT_DIR = "rmd-motion-demo"

#: The position-mode path, joint angles in configuration order (deg).
WAYPOINTS_DEG = (
    (30.0, 20.0, -40.0, 45.0, 30.0, -60.0),
    (-30.0, 40.0, -70.0, -45.0, -20.0, 60.0),
    (10.0, 30.0, -45.0, 0.0, 20.0, 0.0),
)
#: The torque-mode target (deg).
TORQUE_TARGET_DEG = (-20.0, -15.0, -90.0, 30.0, -30.0, 45.0)
#: Share of the joints' velocity, acceleration and jerk limits the demo uses: all of them (the following-error check
#: expects the drives' own lag, which at full speed trails the stream by more than the 4 deg limit).
SPEED_SCALE = 1.0
TORQUE_SPEED_SCALE = 1.0
#: Time the torque run holds against gravity before and after its move, s.
HOLD_S = 0.5
#: With a view: how long a run waits for a browser to open the page before it starts, s.
VIEW_WAIT_S = 60.0
#: ... before the later runs (the open page reconnects to the next run's server by itself), s.
VIEW_REOPEN_S = 15.0


@dataclasses.dataclass(frozen=True, slots=True)
class PhaseResult:
    """One recorded run of the demo."""

    name: str
    log: TelemetryLog
    files: tuple[Path, ...]
    fault: MotionFault | None
    final_deg: tuple[float, ...]


def config_path(drives: ProtocolFamily = ProtocolFamily.V2) -> Path:
    """The example configuration of the runs on ``drives`` (see the module docstring).

    Raises:
        ConfigError: the examples are not installed.
    """
    return example_config(CONFIG_NAMES[drives])


def _follow_path(arm: Arm) -> None:
    arm.follow(WAYPOINTS_DEG, speed_scale=SPEED_SCALE)


def _gravity_move(arm: Arm) -> None:
    arm.sleep(HOLD_S)
    arm.move_to(dict(zip(arm.names, TORQUE_TARGET_DEG, strict=True)), speed_scale=TORQUE_SPEED_SCALE)
    arm.sleep(HOLD_S)


def _run_phase(
    name: str,
    config: ArmConfig,
    out_dir: Path,
    motion: Callable[[Arm], None],
    initial_deg: Sequence[float] | None,
    *,
    view: ViewOptions | None = None,
    view_wait_s: float = 0.0,
    drives: ProtocolFamily = ProtocolFamily.V2,
) -> PhaseResult:
    log_path, trace_path, png_path = (out_dir / f"{name}{suffix}" for suffix in (".mcap", ".log", ".png"))
    telemetry = TelemetryOptions(log_path, trace_path)
    arm = Arm(
        config, emulate=True, initial_deg=initial_deg, telemetry=telemetry, view=view or False, emulated_protocol=drives
    )
    fault = None
    with arm:
        if arm.view is not None:
            print(
                f"the {name} run: open {arm.view.url} (it starts when a browser has the page, or in {view_wait_s:g} s)",
                flush=True,
            )
            arm.view.wait_for_client(view_wait_s)
        try:
            motion(arm)
        except MotionFault as exc:
            fault = exc
        final = tuple(arm.positions().values())
    assert arm.telemetry is not None and arm.telemetry.result is not None
    log = arm.telemetry.result
    plot_log(log, png_path)
    return PhaseResult(name, log, (log_path, trace_path, png_path), fault, final)


_HEADER = (
    "run",
    "mode",
    "recorded",
    "cycles",
    "rate",
    "jitter p50/p99/max",
    "overruns",
    "limited",
    "max following error",
)


def _summary_row(result: PhaseResult) -> tuple[str, ...]:
    log = result.log
    active = log.active_rows()
    error = np.abs(log.following_error_deg()[active])
    worst = "-"
    if error.size:
        worst = f"{error.max():.3f} deg ({log.joint_names[int(np.argmax(error.max(axis=0)))]})"
    loop = log.meta["loop"]
    jitter_us = (round(loop[key] * 1e6) for key in ("jitter_p50_s", "jitter_p99_s", "jitter_max_s"))
    return (
        result.name,
        str(log.meta["mode"]),
        f"{log.duration_s:.2f} s",
        str(log.cycles),
        f"{loop['achieved_rate_hz']:.1f} Hz",
        " / ".join(map(str, jitter_us)) + " us",
        str(loop["overruns"]),
        f"{int(log['limited'][active].any(axis=1).sum())} cycles",
        worst,
    )


def _print_summary(
    config: Path, results: Sequence[PhaseResult], elapsed_s: float, drives: ProtocolFamily, rate_hz: float
) -> None:
    table = [_HEADER, *(_summary_row(result) for result in results)]
    widths = [max(len(row[c]) for row in table) for c in range(len(_HEADER))]
    print(
        f"rmd-motion demo: the 6-DOF arm of {config} on emulated CAN drives of the {GENERATIONS[drives].title} "
        f"at {rate_hz:g} Hz"
    )
    for row in table:
        print("  " + "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip())
    print("  (limited: cycles in which a joint's current limit clipped its torque command)")
    print(f"done in {elapsed_s:.1f} s; files:")
    for result in results:
        for path in result.files:
            print(f"  {path}")


def _print_realtime(config: ArmConfig, drives: ProtocolFamily) -> None:
    """What this host holds in real time: the rate check against the arm's drives emulated in their own process."""
    try:
        checks = realtime_capacity(config, drives)
    except (MotionError, OSError) as exc:  # informative only: the demo's result does not depend on it
        print(f"real time on this host: not measured ({exc})")
        return
    rate = config.control.rate_hz
    parts = [
        f"{mode} mode up to {check.highest_rate_hz:g} Hz (round trip p99 {check.round_trip_p99_s * 1e3:.2f} ms)"
        for mode, check in checks.items()
    ]
    print(
        "the runs above are in simulated time (the same on every host); real time on this host, against the drives "
        f"emulated in their own process over a slcan pty: {'; '.join(parts)}; the configured {rate:g} Hz "
        + ("holds" if all(c.holds for c in checks.values()) else "does NOT hold here")
    )


def run_demo(
    out_dir: Path | None = None,
    *,
    quiet: bool = False,
    view: ViewOptions | None = None,
    drives: ProtocolFamily = ProtocolFamily.V2,
) -> int:
    """Run the demo and write its logs, traces and plots to ``out_dir`` (default ``./rmd-motion-demo``).

    Args:
        out_dir: where the files go (created if needed).
        quiet: print nothing but errors.
        view: show each run live in the browser (:mod:`motion.view`), paced to the wall clock.
        drives: the emulated drives' protocol generation (V3: with ``arm6_v3.yaml``).

    Returns:
        The exit code: 0 done, 1 a motion fault halted the arm (its run is still recorded and plotted), 2 the
        configuration or the output directory is unusable, 3 a communication error.
    """
    start = time.monotonic()
    target = (Path(DEFAULT_OUT_DIR) if out_dir is None else Path(out_dir)).resolve()
    try:
        path = config_path(drives)
        position = load_config(path)
        # the controller tells the drives' generation at connect, as with real drives (the file names it)
        position = dataclasses.replace(
            position, buses=(dataclasses.replace(position.bus, protocol=ProtocolSetting.AUTO),)
        )
        target.mkdir(parents=True, exist_ok=True)
    except (ConfigError, OSError) as exc:
        print(f"rmd-motion demo: {exc}", file=sys.stderr)
        return 2
    torque = dataclasses.replace(
        position,
        control=dataclasses.replace(position.control, mode=ControlMode.TORQUE, gravity_feedforward=True),
    )
    results: list[PhaseResult] = []
    try:
        results.append(
            _run_phase(
                "position", position, target, _follow_path, None, view=view, view_wait_s=VIEW_WAIT_S, drives=drives
            )
        )
        if results[-1].fault is None:
            final = results[-1].final_deg
            results.append(
                _run_phase(
                    "torque", torque, target, _gravity_move, final, view=view, view_wait_s=VIEW_REOPEN_S, drives=drives
                )
            )
    except MotionFault as exc:  # outside a motion (while connecting or closing)
        print(f"rmd-motion demo: motion fault: {exc}", file=sys.stderr)
        return 1
    except TransportError as exc:
        print(f"rmd-motion demo: communication error: {exc}", file=sys.stderr)
        return 3
    except OSError as exc:
        print(f"rmd-motion demo: {exc}", file=sys.stderr)
        return 2
    if not quiet:
        _print_summary(path, results, time.monotonic() - start, drives, position.control.rate_hz)
        _print_realtime(position, drives)
    fault = results[-1].fault
    if fault is not None:
        print(f"rmd-motion demo: motion fault in the {results[-1].name} run: {fault}", file=sys.stderr)
        return 1
    return 0
