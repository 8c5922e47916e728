"""What a second bus costs a cycle (issue 35): twelve joints on two buses against six on one.

Part ``wire`` (simulated time: the bus model alone, the same on every host): the arm holds still in position mode
for ``--seconds`` of simulated time, and each cycle's exchange is timed from its start to its last reply, in
simulated seconds (the frames' bits at 1 Mbit/s, the drives' reply latency); arm6.yaml (one bus, six joints) against
bimanual.yaml (two buses, six joints each). The ratio is the issue's "2 buses × 6 joints cost ≤ 1.2× the cycle of
1 bus × 6 joints".

Part ``live`` (real time, this host): the arm holds still at ``--rate`` Hz in position mode against ``rmd-motion
emulate --config`` in a process of its own on slcan pseudo-terminals (one per bus), for ``--seconds``; reports the
share of cycles whose every reply came within the cycle's reply budget, and the exchange's p50 / p99 (scheduled
start to replies taken in). bimanual runs twice: the buses' exchanges at the same time (a worker thread per bus
beyond the first: the default) and one after the other in the loop's thread; arm6 on one pty for reference.

    .venv/bin/python bench/buses_bench.py                      # both parts
    .venv/bin/python bench/buses_bench.py --part live --rate 500 --seconds 20
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from motion.api import Arm
from motion.compose import build_controller, open_bus
from motion.config import ArmConfig, load_config
from motion.control.controller import Controller
from motion.transport.base import Reply, Transport
from motion.transport.buses import Buses

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "configs"
#: The configurations compared: six joints on one bus, and two copies of them on two buses.
ONE_BUS, TWO_BUSES = "arm6.yaml", "bimanual.yaml"
#: The issue's bound on the ratio of the cycles (simulated wire time), and its share of complete cycles (live).
RATIO_TARGET, COMPLETE_TARGET = 1.2, 0.99


def wire_cycle_s(name: str, seconds: float) -> tuple[float, float, int]:
    """Simulated time from each cycle's start to its last reply, p50 and max, and the cycles measured."""
    took: list[float] = []

    def record(_controller: Controller, start_s: float, replies: list[Reply]) -> None:
        times = [r.received_s for r in replies if r.received_s is not None]
        if times and len(times) == len(replies):
            took.append(max(times) - start_s)

    with Arm.from_config(CONFIGS / name, emulate=True) as arm:
        assert arm.supervisor is not None
        arm.supervisor.controller.cycle_hooks.append(record)
        arm.sleep(seconds)
    return float(np.percentile(took, 50)), float(np.max(took)), len(took)


def run_wire(seconds: float) -> None:
    one, two = wire_cycle_s(ONE_BUS, seconds), wire_cycle_s(TWO_BUSES, seconds)
    print("## simulated wire time per cycle (position mode, holding; start to last reply)\n")
    print("| arm | buses × joints | cycles | p50 (ms) | max (ms) |")
    print("|---|---|---:|---:|---:|")
    for name, shape, (p50, most, n) in ((ONE_BUS, "1 × 6", one), (TWO_BUSES, "2 × 6", two)):
        print(f"| {name} | {shape} | {n} | {p50 * 1e3:.3f} | {most * 1e3:.3f} |")
    ratio = two[0] / one[0]
    verdict = "met" if ratio <= RATIO_TARGET else "NOT met"
    print(f"\nratio 2 × 6 / 1 × 6 (p50): **{ratio:.3f}** (target <= {RATIO_TARGET}: {verdict})\n")


@contextlib.contextmanager
def emulator(name: str, links: dict[str, Path]) -> Iterator[None]:
    """``rmd-motion emulate --config`` of ``name`` with a slcan pty per bus (``links``: bus name -> path, "" for
    the one bus of an arm on one)."""
    command = [sys.executable, "-m", "motion.cli", "emulate", "--config", str(CONFIGS / name)]
    for bus, link in links.items():
        command += ["--slcan-link", f"{bus}={link}" if bus else str(link)]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=ROOT)
    try:
        assert process.stdout is not None
        while not process.stdout.readline().startswith("emulating motors"):
            if process.poll() is not None:
                raise RuntimeError(f"{' '.join(command)} did not start")
        yield
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=10)


@dataclasses.dataclass(frozen=True)
class LiveResult:
    label: str
    cycles: int
    complete_share: float
    done_p50_s: float
    done_p99_s: float
    overruns: int


def run_live_case(name: str, rate_hz: float, seconds: float, *, parallel: bool = True) -> LiveResult:
    config = load_config(CONFIGS / name)
    config = dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=rate_hz))
    with tempfile.TemporaryDirectory(prefix="rmd-buses-") as tmp:
        links = {bus.name: Path(tmp) / f"slcan-{bus.name or 'bus'}" for bus in config.buses}
        channel: object = {k: str(v) for k, v in links.items()} if len(links) > 1 else str(*links.values())
        with (
            emulator(name, links),
            open_bus(config, interface="slcan", channel=channel, bitrate=1_000_000, sleep_after_open=0) as opened,
        ):
            # (sequential: the same ports, one bus after the other in the loop's thread)
            sequential = isinstance(opened, Buses) and not parallel
            bus = (
                Buses(opened.buses, opened.names, parallel=False)
                if isinstance(opened, Buses) and sequential
                else opened
            )
            return _hold(config, bus, seconds, f"{name} ({'sequential' if sequential else 'parallel'})")


def _hold(config: ArmConfig, bus: Transport, seconds: float, label: str) -> LiveResult:
    controller = build_controller(config, bus)
    controller.read_positions()
    complete: list[bool] = []
    done_s: list[float] = []

    def record(_controller: Controller, start_s: float, replies: list[Reply]) -> None:
        done_s.append(time.monotonic() - start_s)
        complete.append(all(r.ok for r in replies))

    controller.cycle_hooks.append(record)
    controller.start()
    time.sleep(seconds)
    stats = controller.shutdown()
    return LiveResult(
        label,
        len(complete),
        sum(complete) / len(complete) if complete else math.nan,
        float(np.percentile(done_s, 50)) if done_s else math.nan,
        float(np.percentile(done_s, 99)) if done_s else math.nan,
        stats.overruns,
    )


def run_live(rate_hz: float, seconds: float) -> None:
    results = [
        run_live_case(ONE_BUS, rate_hz, seconds),
        run_live_case(TWO_BUSES, rate_hz, seconds),
        run_live_case(TWO_BUSES, rate_hz, seconds, parallel=False),
    ]
    print(f"## live: holding at {rate_hz:g} Hz, position mode, slcan ptys, {seconds:g} s each\n")
    print("| arm | cycles | complete | exchange p50 (ms) | p99 (ms) | overruns |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in results:
        print(
            f"| {r.label} | {r.cycles} | {r.complete_share * 100:.1f} % | {r.done_p50_s * 1e3:.2f} | "
            f"{r.done_p99_s * 1e3:.2f} | {r.overruns} |"
        )
    share = results[1].complete_share
    verdict = "met" if share >= COMPLETE_TARGET else "NOT met"
    ratio = results[1].done_p50_s / results[0].done_p50_s
    print(
        f"\nbimanual (parallel) {share * 100:.1f} % of cycles complete (target >= {COMPLETE_TARGET * 100:g} %: "
        f"{verdict}); its exchange p50 / arm6's: {ratio:.2f}; sequential / parallel: "
        f"{results[2].done_p50_s / results[1].done_p50_s:.2f}\n"
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--part", choices=("wire", "live", "all"), default="all")
    parser.add_argument("--seconds", type=float, default=10.0, help="per case (default %(default)g)")
    parser.add_argument("--rate", type=float, default=500.0, help="live part's rate, Hz (default %(default)g)")
    args = parser.parse_args(argv)
    if args.part in ("wire", "all"):
        run_wire(args.seconds)
    if args.part in ("live", "all"):
        run_live(args.rate, args.seconds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
