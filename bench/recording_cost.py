"""Benchmark of issue 34: what recording a run costs the control cycle, and what writing its MCAP file costs after it.

Run by hand from the repository root (about half a minute; prints Markdown)::

    .venv/bin/python bench/recording_cost.py [--cycles 20000] [--rounds 20]

The cycle: the whole ``Controller.cycle`` of a synthetic 6-axis arm (position and torque mode) on the loopback
transport of ``bench/cycle_bench.py``, without and with the recorder (a cycle hook filling preallocated rows) and the
bus trace (the transport's frame tap), interleaved in rounds so that machine noise hits both alike; the ratio of the
medians is the figure. The write: :meth:`motion.telemetry.TelemetryLog.save` of what was recorded (with the frames and
the arm's link transforms), per recorded cycle; it runs once the loop has ended, never inside a cycle.
"""

from __future__ import annotations

import argparse
import io
import statistics
import time

from cycle_bench import make_cpu_case, run_cycle_batch, synthetic_config

from kinematics.frames import LinkFrames
from motion.config.schema import ControlMode
from motion.telemetry import BusTrace, Recorder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20_000, help="cycles per case and variant")
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    batch = max(1, args.cycles // args.rounds)
    print("| mode | cycle p50 without (µs) | with recording (µs) | ratio | MCAP write per cycle (µs) |")
    print("|---|---|---|---|---|")
    for mode in (ControlMode.POSITION, ControlMode.TORQUE):
        plain, recorded = make_cpu_case(6, mode, 1000.0), make_cpu_case(6, mode, 1000.0)
        recorder = Recorder(recorded.controller).attach()
        trace = BusTrace().install(recorded.controller.bus)
        for case in (plain, recorded):
            run_cycle_batch(case, 200, 0)
            case.stages["cycle"].clear()
        for r in range(args.rounds):
            for case in (plain, recorded) if r % 2 else (recorded, plain):
                run_cycle_batch(case, batch, 200 + r * batch)
        without = statistics.median(plain.stages["cycle"]) / 1e3
        with_recording = statistics.median(recorded.stages["cycle"]) / 1e3
        recorder.detach()
        trace.uninstall()
        log = recorder.log(config="bench", emulated=False)
        robot = LinkFrames(synthetic_config(6, mode=mode, rate_hz=1000.0))
        start = time.perf_counter()
        log.save(io.BytesIO(), robot=robot, frames=trace)
        write_us = (time.perf_counter() - start) / log.cycles * 1e6
        print(
            f"| {mode.value} | {without:.1f} | {with_recording:.1f} | {with_recording / without:.3f} | {write_us:.0f} "
            f"({log.cycles} cycles, {len(trace)} frames) |"
        )


if __name__ == "__main__":
    main()
