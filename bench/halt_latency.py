"""Detection-to-halt latency of the safety supervisor, measured on emulated drives.

For each fault kind, an emulated arm (configs/arm2.yaml, halt policy ``stop``, position mode at 200 Hz on the
in-process CAN bus) starts a move, the fault is injected, and the run records:

* the cycle in which the fault was detected and the cycle in which the halt frames were sent (same cycle = 0),
* detection -> halt frames handed to the bus (ms, controller clock),
* detection -> the last drive received its 0x81 (ms, from the emulator's frame log).

Also counted: fault injection -> detection, in cycles, which depends on the source (flags come round-robin).

Run: ``.venv/bin/python bench/halt_latency.py [--runs N]``
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

from motion.api import Arm
from motion.config import load_config
from motion.config.schema import ControlMode, HaltPolicy
from motion.emulator import Fault, InjectedFault
from motion.errors import MotionFault

CONFIG = Path(__file__).resolve().parent.parent / "configs" / "arm2.yaml"
KINDS = {
    "silent": (InjectedFault.SILENT, None),
    "over_temperature_75C": (InjectedFault.OVER_TEMPERATURE, 75.0),
    "under_voltage_12V": (InjectedFault.UNDER_VOLTAGE, 12.0),
    "estop": (None, None),
}


def _one(kind: str, workdir: Path) -> tuple[int, float, float, float]:
    config = load_config(CONFIG)
    config = dataclasses.replace(
        config,
        control=dataclasses.replace(
            config.control, mode=ControlMode.POSITION, rate_hz=200, halt_policy=HaltPolicy.STOP
        ),
        model=dataclasses.replace(config.model, gravity_m_s2=(0.0, 0.0, -9.81)),
    )
    log_path = workdir / f"{kind}-{time.monotonic_ns()}.log"
    arm = Arm(config, emulate=True, emulator_log=log_path)
    arm.connect()
    assert arm.supervisor is not None and arm.emulator is not None and arm.frame_log is not None
    log_start = arm.frame_log.start_s
    try:
        arm.move_to({"shoulder": 60.0, "elbow": -60.0}, speed_scale=0.3, wait=False)
        time.sleep(0.3)
        injected = arm.supervisor.controller.clock.now()
        fault_kind, value = KINDS[kind]
        if fault_kind is None:
            arm.supervisor.estop()
        else:
            now = arm.emulator.time_s
            arm.emulator.add_fault(Fault(fault_kind, 2, start_s=now, end_s=now + 5.0, value=value))
        with contextlib.suppress(MotionFault):
            arm.supervisor.wait(5.0)
        time.sleep(0.1)
        halt = arm.supervisor.halts[0]
    finally:
        arm.close()
    period = arm.supervisor.controller.period_s
    first: dict[str, float] = {}  # CAN id -> first 0x81 received after the detection
    for line in log_path.read_text().splitlines():
        fields = line.split()
        if len(fields) > 4 and fields[1] == "IN" and fields[4] == "81":
            t = log_start + float(fields[0])
            if t >= halt.detected_s and fields[3] not in first:
                first[fields[3]] = t
    last_received = max(first.values()) if len(first) == len(config.joints) else float("nan")
    detect_cycles = round((halt.detected_s - injected) / period)
    return detect_cycles, (halt.halt_sent_s - halt.detected_s) * 1e3, (last_received - halt.detected_s) * 1e3, period


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'fault':<22} {'inject->detect':>15} {'detect->sent':>14} {'detect->last drive':>19}")
        for kind in KINDS:
            rows = [_one(kind, Path(tmp)) for _ in range(args.runs)]
            period_ms = rows[0][3] * 1e3
            detect = [r[0] for r in rows]
            sent = [r[1] for r in rows]
            last = [r[2] for r in rows]
            print(
                f"{kind:<22} {min(detect):>5}..{max(detect):<3} cycles "
                f"{statistics.median(sent):>6.2f} ms (max {max(sent):.2f}) "
                f"{statistics.median(last):>6.2f} ms (max {max(last):.2f})   period {period_ms:.1f} ms"
            )


if __name__ == "__main__":
    main()
