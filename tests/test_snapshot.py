"""The snapshot the loop publishes every cycle: immutable, one cycle's consistent picture, what status and progress
read (simulated time)."""

from __future__ import annotations

import numpy as np
import pytest

from motion.api import Arm
from motion.control.snapshot import CycleSnapshot
from motion.errors import FaultKind, MotionFault
from tests.motion_rig import arm_config


def test_every_cycle_publishes_a_new_immutable_snapshot() -> None:
    with Arm(arm_config("arm2.yaml", rate_hz=200), emulate=True) as arm:
        controller = arm.controller
        assert controller is not None
        first = controller.snapshot  # the start-up and rate-check reads, before the first cycle
        assert first.cycle == 0 and not first.commanded and first.fresh.all()
        # the reference holds where the start-up reads found the arm; the rate check's reads came a few simulated
        # milliseconds later, with the drives still off
        assert np.allclose(first.position_deg, first.reference_deg, atol=0.01)
        arm.move_to({"shoulder": 20.0}, wait=False)
        arm.sleep(0.1)
        later = controller.snapshot
        assert later is not first and later.cycle == controller.loop.cycles
        assert 0.1 - 0.005 <= later.time_s - first.time_s <= 0.1 + 0.005  # the latest cycle of the 0.1 s
        for array in (later.joints, later.position_deg):
            with pytest.raises(ValueError, match="read-only"):
                array[0] = 1.0
        kept = later.position_deg.copy()
        arm.sleep(0.1)  # the arm moved on; what a reader holds did not
        assert np.array_equal(later.position_deg, kept)
        assert not np.array_equal(controller.snapshot.position_deg, kept)
        # status reads the published cycle, all fields from the same one
        status = arm.status()
        snapshot: CycleSnapshot = controller.snapshot
        assert [j.position_deg for j in status.joints] == list(snapshot.position_deg)
        assert [j.reference_deg for j in status.joints] == list(snapshot.reference_deg)
        assert snapshot.commanded and snapshot.fresh.all()


def test_motion_handle_progress_runs_from_zero_to_done() -> None:
    with Arm(arm_config("arm2.yaml", rate_hz=200), emulate=True) as arm:
        handle = arm.move_to({"shoulder": 40.0, "elbow": -30.0}, speed_scale=0.5, wait=False)
        seen = []
        while not handle.done:
            seen.append(handle.progress())
            arm.sleep(0.05)
        assert len(seen) > 5
        durations = {round(p.duration_s, 9) for p in seen[1:]}
        assert len(durations) == 1 and durations.pop() > 0.5  # one planned motion
        fractions = [p.fraction for p in seen[1:]]
        assert fractions == sorted(fractions) and fractions[0] < 0.2 and fractions[-1] > 0.8
        assert all(not p.done for p in seen)
        end = handle.progress()
        assert end.done and end.fraction == 1.0


def test_the_state_fault_and_loop_counters_are_published_with_each_transition() -> None:
    with Arm(arm_config("arm2.yaml", rate_hz=200), emulate=True) as arm:
        controller, supervisor = arm.controller, arm.supervisor
        assert controller is not None and supervisor is not None
        assert controller.snapshot.state == "ready" and controller.snapshot.fault is None
        handle = arm.move_to({"shoulder": 30.0}, speed_scale=0.5, wait=False)
        moving = controller.snapshot  # MOVE is published at once, before the next cycle ran
        assert moving.state == "moving" and moving.fault is None
        arm.sleep(0.1)
        assert controller.snapshot.state == "moving" and controller.snapshot.cycle > moving.cycle
        assert controller.snapshot.overruns == 0 and controller.snapshot.skipped_cycles == 0  # simulated time
        before = controller.snapshot
        arm.stop()  # the E-stop: 0x81 to every axis
        with pytest.raises(MotionFault):
            handle.wait()
        halted = controller.snapshot
        assert halted.state in ("halting", "halted") and halted.fault is supervisor.fault
        assert halted.fault is not None and halted.fault.kind is FaultKind.STOP
        assert before.state == "moving" and before.fault is None  # what a reader holds never changes
        status = arm.status()
        assert status.state == halted.state and status.fault == str(halted.fault)
        arm.sleep(0.05)
        settled = controller.snapshot
        assert settled.state == "halted" and settled.fault is halted.fault
        arm.sleep(0.25)  # (clear() takes the joints once each has read at rest for 50 ms, after the drives' stop)
        arm.clear()
        cleared = controller.snapshot
        assert cleared.state == "ready" and cleared.fault is None
    assert controller.snapshot.state == "closed"
