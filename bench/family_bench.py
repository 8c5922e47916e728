"""What the V3 family's fine angle costs on the bus (issue 17): one control cycle's frames and their time on a
1 Mbit/s CAN bus, for drives of the older family and for V3-driver drives, and the highest rate the rate check then
allows (simulated time: the same figures on every host).

V3 drives report whole degrees in their motion replies, so each cycle also reads 0x92 per joint; the older drives'
motion replies carry the encoder the controller unwraps. Run from the repository root (a few seconds)::

    .venv/bin/python bench/family_bench.py
    .venv/bin/python bench/family_bench.py --axes 2 6 12

Prints a Markdown table (see bench/README.md).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.cycle_bench import CAN_BITRATE, synthetic_config  # noqa: E402
from motion.compose import build_controller  # noqa: E402
from motion.config.schema import ControlMode  # noqa: E402
from motion.control.ratecheck import measure_rate  # noqa: E402
from motion.emulator.arm import emulator_for  # noqa: E402
from motion.emulator.simulated import SimulatedBus, SimulatedClock, Simulation  # noqa: E402
from motion.emulator.timing import can_frame_bits  # noqa: E402
from motion.protocol import WireProtocol  # noqa: E402
from motion.protocol.table import ProtocolFamily  # noqa: E402

#: The rate the synthetic arms are configured at (the cycle measured does not depend on it), Hz.
RATE_HZ = 100.0


@dataclass(frozen=True)
class CycleCost:
    """One cycle of one family: frames each way, their bits on the bus, the rate check's figures."""

    requests: int
    replies: int
    wire_us: float
    round_trip_p99_ms: float
    highest_rate_hz: float


def cycle_cost(n_axes: int, mode: ControlMode, family: ProtocolFamily) -> CycleCost:
    """A cycle at rest of a synthetic ``n_axes`` arm on emulated ``family`` drives in simulated time."""
    config = synthetic_config(n_axes, mode=mode, rate_hz=RATE_HZ)
    simulation = Simulation(emulator_for(config, family=family), WireProtocol.CAN, bitrate=CAN_BITRATE)
    bus = SimulatedBus(simulation)
    controller = build_controller(config, bus, clock=SimulatedClock(simulation))
    controller.read_positions()
    period = controller.period_s
    # the first cycles also read the older drives' loop settings: the cycle measured is one after them
    while controller.tracking.unread:
        now = simulation.now_s
        controller.step(now, now + period)
    frames: list[tuple[bool, int]] = []
    bus.frame_tap = lambda _t, received, arbitration_id, data: frames.append(
        (received, can_frame_bits(arbitration_id, bytes(data)))
    )
    now = simulation.now_s
    controller.step(now, now + period)
    bus.frame_tap = None
    check = measure_rate(controller)
    return CycleCost(
        requests=sum(1 for received, _ in frames if not received),
        replies=sum(1 for received, _ in frames if received),
        wire_us=sum(bits for _, bits in frames) / CAN_BITRATE * 1e6,
        round_trip_p99_ms=check.round_trip_p99_s * 1e3,
        highest_rate_hz=check.highest_rate_hz,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--axes", type=int, nargs="+", default=[1, 2, 4, 6, 12], help="arm sizes (default 1 2 4 6 12)")
    args = parser.parse_args(argv)
    print(
        "| axes | mode | v2 frames out / in | v2 wire, µs | v3 frames out / in | v3 wire, µs | **v3 / v2 wire** "
        "| round trip p99, ms v2 / v3 | highest rate, Hz v2 / v3 |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for n in args.axes:
        for mode in ControlMode:
            v2, v3 = (cycle_cost(n, mode, family) for family in (ProtocolFamily.V2, ProtocolFamily.V3))
            print(
                f"| {n} | {mode.value} | {v2.requests} / {v2.replies} | {v2.wire_us:.0f} "
                f"| {v3.requests} / {v3.replies} | {v3.wire_us:.0f} | **{v3.wire_us / v2.wire_us:.2f}** "
                f"| {v2.round_trip_p99_ms:.2f} / {v3.round_trip_p99_ms:.2f} "
                f"| {v2.highest_rate_hz:g} / {v3.highest_rate_hz:g} |"
            )
    print(
        "\nwire: the bits of one cycle's frames (set-points, the family's reads, their replies; stuff bits included) "
        f"at {CAN_BITRATE / 1e6:g} Mbit/s. Round trip and highest rate: the connect's rate check (margin 1.5, 80 % of "
        "the period for the replies) in simulated time."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
