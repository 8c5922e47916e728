"""The fixed-rate loop: absolute deadlines, overrun handling, statistics, threads."""

from __future__ import annotations

import threading

import pytest

from motion.control.clock import ManualClock, MonotonicClock
from motion.control.scheduler import FixedRateLoop


def test_absolute_deadlines_do_not_drift_with_variable_cycle_time() -> None:
    clock = ManualClock(100.0)
    starts: list[float] = []
    busy = [0.0002, 0.0009, 0.0, 0.0005] * 50

    def cycle(k: int, start: float, deadline: float) -> bool:
        starts.append(clock.now())
        assert deadline == pytest.approx(start + 0.001)
        clock.advance(busy[k])
        return k < 199

    loop = FixedRateLoop(1000, cycle, clock=clock)
    loop.run()
    assert len(starts) == 200
    assert starts == pytest.approx([100.0 + k * 0.001 for k in range(200)], abs=1e-9)
    assert loop.overruns == 0
    stats = loop.statistics()
    assert stats.achieved_rate_hz == pytest.approx(1000.0)
    assert stats.jitter_max_s == pytest.approx(0.0)


def test_overrun_is_counted_and_missed_grid_points_are_skipped() -> None:
    clock = ManualClock(0.0)
    starts: list[float] = []

    def cycle(k: int, start: float, deadline: float) -> bool:
        starts.append(start)
        if k == 3:
            clock.advance(0.0125)  # 2.5 periods of 5 ms
        return len(starts) < 8

    loop = FixedRateLoop(200, cycle, clock=clock)
    loop.run()
    assert loop.overruns == 1
    assert loop.skipped_cycles == 2
    # cycles 4 and 5 are skipped; the grid is kept (no drift): 0, 5, 10, 15, 30, 35, ... ms
    assert starts == pytest.approx([0.0, 0.005, 0.010, 0.015, 0.030, 0.035, 0.040, 0.045])


def test_exception_in_cycle_ends_loop_and_is_kept() -> None:
    def cycle(k: int, start: float, deadline: float) -> bool:
        if k == 2:
            raise RuntimeError("boom")
        return True

    loop = FixedRateLoop(100, cycle, clock=ManualClock())
    with pytest.raises(RuntimeError, match="boom"):
        loop.run()
    assert isinstance(loop.error, RuntimeError) and loop.cycles == 2


def test_threaded_real_clock_run_and_stop() -> None:
    seen = threading.Event()
    count = 0

    def cycle(k: int, start: float, deadline: float) -> bool:
        nonlocal count
        count += 1
        if count == 20:
            seen.set()
        return True

    loop = FixedRateLoop(500, cycle, clock=MonotonicClock())
    loop.start()
    assert seen.wait(5.0)
    loop.stop()
    assert loop.join(2.0)
    stats = loop.statistics()
    assert stats.cycles >= 20 and loop.error is None
    assert stats.period_mean_s > 0


@pytest.mark.parametrize("rate", [0, -5, 1e6, True, "100"])
def test_rate_is_validated(rate: object) -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        FixedRateLoop(rate, lambda k, s, d: False)  # type: ignore[arg-type]
