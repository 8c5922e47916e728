"""The control loop's wake-up jitter with and without the live view (issue 15).

arm2 against `rmd-motion emulate` in its own process over an slcan pty (real time), following a back-and-forth path;
the loop's jitter per cycle (the telemetry log's ``jitter_s``: wake-up minus scheduled start) in three setups,
interleaved over rounds so that the host's drift hits them alike:

- ``none``: no view;
- ``server``: the view running (its process, fed by the loop), nobody watching;
- ``browser``: the view with a page open in headless chromium (Playwright);
- ``elsewhere``: no view of this arm, and the same browser on the view of another arm (emulated in simulated time,
  paced, on the browser's CPU): what the browser costs the arm by itself.

Chromium renders the page's WebGL in software here (no GPU): while the arm moves it takes 1.7 of this 2-core host's
cores, and the emulated drives in their process then miss replies by tens of milliseconds, with no view at all as
much as with it (chromium's own start does it). A browser on another computer, or with a GPU, costs the host nothing
of that. So by default the browser gets one CPU of its own, with the view's process beside it, and the arm and the
emulator the rest, the same in every setup: what differs between them is the view. (With the view's process on the
arm's CPU, though SCHED_IDLE, the loop's jitter p99 went from 2 to 165 µs while a browser had the page: the kernel's
work for its websocket yields to nobody.) ``--same-cpus`` shares every CPU, the hard case.

The pty's bytes are delivered by the kernel's unbound workqueue (tty flip buffers), on whichever CPU it picks: with
chromium busy on its own CPU, an arm with no view at all still missed 4 replies in a row (slcan, 250 Hz). So the
bench also confines the kernel's unbound workqueues to the arm's CPUs (``/sys/devices/virtual/workqueue/cpumask``,
root; restored at the end), as a host with a USB-CAN adapter should be (README, "Real time on a busy host").

    .venv/bin/python bench/view_jitter.py                    # 3 rounds x 4 setups x 8 s, about 3 min
    .venv/bin/python bench/view_jitter.py --rounds 5 --seconds 15 --same-cpus

The rate is :data:`RATE_HZ` (arm6's, the demo's), or the rate check's recommendation for this host when that is
lower. Prints a
Markdown table; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from motion import Arm, MotionFault, ViewOptions  # noqa: E402
from motion.config import ArmConfig, load_config  # noqa: E402
from motion.control.ratecheck import RateError  # noqa: E402
from motion.telemetry import TelemetryOptions, load_log  # noqa: E402

PATH = ((30.0, -40.0), (-20.0, 20.0))
SETUPS = ("none", "server", "browser", "elsewhere")
#: What the browser's process is told to open for ``elsewhere``.
OTHER = "another arm"
#: When a run's faults happened (see :func:`run`).
WHEN = ("while the page loaded", "on the path")
#: How long the browser and the page are given to settle before what is measured, s.
SETTLE_S = 3.0
#: The control rate, Hz: arm6's (the demo's); arm2's 500 Hz needs a CPU of its own for the emulator.
RATE_HZ = 250.0
WORKQUEUE_CPUMASK = Path("/sys/devices/virtual/workqueue/cpumask")


class Browser:
    """Headless chromium in a process of its own (Playwright's driver with it, on CPU ``cpu`` unless None), started
    and given :data:`SETTLE_S` before the arm connects: the start of chromium on a 2-core host delays even an arm with
    no view, which is not what is measured here. :meth:`open` loads a page."""

    def __init__(self, cpu: int | None) -> None:
        command = [sys.executable, __file__, "--browser"]
        self.process = subprocess.Popen(
            command if cpu is None else ["taskset", "-c", str(cpu), *command],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self._expect("ready")
        time.sleep(SETTLE_S)

    def _expect(self, word: str) -> None:
        assert self.process.stdout is not None
        line = self.process.stdout.readline().strip()
        if line != word:
            raise RuntimeError(f"the browser said {line!r}, not {word!r}")

    def open(self, url: str) -> None:
        """Load ``url`` and wait for the view's joint table."""
        assert self.process.stdin is not None
        self.process.stdin.write(url + "\n")
        self.process.stdin.flush()
        self._expect("loaded")

    def close(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()
        self.process.wait(30)


def serve_browser() -> int:
    """The browser's process (``--browser``): a page on each URL read from stdin; ends at EOF."""
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=chromium, args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        )
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        page.goto("about:blank")
        print("ready", flush=True)
        with contextlib.ExitStack() as stack:
            for line in sys.stdin:
                url = line.strip() if line.strip() != OTHER else stack.enter_context(another_arm())
                page.goto(url)
                page.wait_for_selector("span[data-joint]", timeout=60_000)
                print("loaded", flush=True)
        browser.close()
    return 0


@contextlib.contextmanager
def another_arm() -> Iterator[str]:
    """arm2 emulated in simulated time, paced, following the path in a thread, with its view; yields its URL."""
    moving = threading.Event()
    moving.set()
    with Arm(load_config(ROOT / "configs" / "arm2.yaml"), emulate=True, view=ViewOptions(port=0)) as arm:

        def keep_moving() -> None:
            while moving.is_set():
                arm.follow(PATH, speed_scale=0.5)

        thread = threading.Thread(target=keep_moving, daemon=True)
        thread.start()
        assert arm.view is not None
        yield arm.view.url
        moving.clear()
        thread.join()


#: /proc/interrupts rows counted on the arm's CPUs (local timer, rescheduling, function-call and TLB-shootdown IPIs).
INTERRUPT_ROWS = ("LOC", "RES", "CAL", "TLB")


def cpu_counters(cpus: list[int]) -> dict[str, int]:
    """Counts of what interrupted ``cpus`` so far: the :data:`INTERRUPT_ROWS` of /proc/interrupts, every softirq of
    /proc/softirqs (as ``softirq NAME``), and this process's involuntary context switches (its threads preempted)."""
    counts: dict[str, int] = {}
    for source, rows, prefix in (
        ("/proc/interrupts", INTERRUPT_ROWS, ""),
        ("/proc/softirqs", None, "softirq "),
    ):
        with contextlib.suppress(OSError):
            lines = Path(source).read_text().splitlines()
            columns = {name: i for i, name in enumerate(lines[0].split())}
            for line in lines[1:]:
                name, _, rest = line.partition(":")
                name, values = name.strip(), rest.split()
                if rows is not None and name not in rows:
                    continue
                counts[prefix + name] = sum(
                    int(values[columns[f"CPU{c}"]]) for c in cpus if columns.get(f"CPU{c}", len(values)) < len(values)
                )
    switches = 0
    for task in Path("/proc/self/task").iterdir():
        with contextlib.suppress(OSError):
            for line in (task / "status").read_text().splitlines():
                if line.startswith("nonvoluntary_ctxt_switches:"):
                    switches += int(line.split()[1])
    counts["preemptions of this process"] = switches
    return counts


def move_process(pid: int, cpu: int) -> None:
    """Every thread of process ``pid`` to CPU ``cpu`` (threads started later inherit it)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(task.name), {cpu})


def run(
    config: ArmConfig, setup: str, seconds: float, log: Path, *, browser_cpu: int | None, arm_cpus: list[int]
) -> tuple[np.ndarray, dict[str, float], str | None, str | None]:
    """One run; the jitter of every cycle while the path played, s, what interrupted the arm's CPUs meanwhile (per
    second, :func:`cpu_counters`), the fault of the page's first load and the fault that ended the path early
    (None: none)."""
    view: bool | ViewOptions = ViewOptions(port=0) if setup in {"server", "browser"} else False
    browser = Browser(browser_cpu) if setup in {"browser", "elsewhere"} else None
    try:
        for attempt in range(3):  # a refusal by the rate check at connect: a moment of the host's noise, try again
            arm = Arm(config, emulate="realtime", view=view, telemetry=TelemetryOptions(log))
            try:
                arm.connect()
                break
            except RateError as exc:
                print(f"rate check refused ({attempt + 1} of 3): {exc}", file=sys.stderr)
                if attempt == 2:
                    raise
        try:
            if arm.view is not None and browser_cpu is not None:
                move_process(arm.view.pid, browser_cpu)
            if browser is not None:
                browser.open(OTHER if arm.view is None else arm.view.url)
            time.sleep(SETTLE_S)  # every setup holds as long before the path: the page's first load is not measured
            load_fault = arm.fault
            if load_fault is not None:  # said in the table; cleared, so that the steady state can be measured
                arm.clear()
                time.sleep(SETTLE_S)
            begin, before = time.monotonic(), cpu_counters(arm_cpus)
            end = begin + seconds
            path_fault = None
            while time.monotonic() < end:
                try:
                    arm.follow(PATH, speed_scale=0.5)
                except MotionFault as exc:  # counted in the table; the cycles until then are measured
                    path_fault = str(exc)
                    break
            after, elapsed = cpu_counters(arm_cpus), time.monotonic() - begin
            rates = {name: (after[name] - before.get(name, 0)) / elapsed for name in after}
        finally:
            arm.close()
    finally:
        if browser is not None:
            browser.close()
    recorded = load_log(log)
    jitter: np.ndarray = recorded["jitter_s"][recorded.active_rows()]
    return jitter, rates, None if load_fault is None else str(load_fault), path_fault


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--rate", type=float, default=RATE_HZ, help="control rate, Hz (default: %(default)g)")
    parser.add_argument("--same-cpus", action="store_true", help="the browser shares every CPU with the arm")
    parser.add_argument(
        "--setups",
        default=",".join(SETUPS),
        help="which setups, comma-separated, in this order within each round (default: %(default)s)",
    )
    parser.add_argument("--browser", action="store_true", help=argparse.SUPPRESS)  # the browser's own process
    args = parser.parse_args()
    if args.browser:
        return serve_browser()
    args.setups = tuple(args.setups.split(","))
    unknown = sorted(set(args.setups) - set(SETUPS))
    if unknown or not args.setups:
        parser.error(f"--setups: {', '.join(unknown) or 'none given'}; valid: {', '.join(SETUPS)}")
    cpus = sorted(os.sched_getaffinity(0))
    browser_cpu = None if args.same_cpus or len(cpus) < 2 else cpus[-1]
    if browser_cpu is not None:  # this thread, before any other starts: every thread and child inherits it
        os.sched_setaffinity(0, cpus[:-1])
    with confined_workqueues(None if browser_cpu is None else cpus[:-1]) as confined:
        print(f"kernel's unbound workqueues: {confined}", file=sys.stderr)
        return measure(args, browser_cpu, cpus)


@contextlib.contextmanager
def confined_workqueues(cpus: list[int] | None) -> Iterator[str]:
    """The kernel's unbound workqueues on ``cpus`` for the duration (None: left alone); yields what was done."""
    if cpus is None:
        yield "left alone"
        return
    mask = WORKQUEUE_CPUMASK.read_text().strip() if WORKQUEUE_CPUMASK.exists() else None
    try:
        WORKQUEUE_CPUMASK.write_text(f"{sum(1 << c for c in cpus):x}\n")
    except OSError as exc:
        yield f"left on every CPU ({WORKQUEUE_CPUMASK}: {exc})"
        return
    try:
        yield f"confined to CPUs {cpus} (mask was {mask})"
    finally:
        WORKQUEUE_CPUMASK.write_text(f"{mask}\n")


def measure(args: argparse.Namespace, browser_cpu: int | None, cpus: list[int]) -> int:
    """The three setups over the rounds; prints the table."""
    folder = Path(tempfile.mkdtemp(prefix="rmd-view-jitter-"))
    config = load_config(ROOT / "configs" / "arm2.yaml")
    probe = Arm(config, emulate="realtime")
    try:
        check = probe.connect().rate_check
    except RateError as exc:
        check = exc.check
    finally:
        probe.close()
    assert check is not None
    rate = min(args.rate, check.recommended_rate_hz)
    if rate != config.control.rate_hz:  # its highest rate leaves no room for the host's noise over minutes of runs
        print(f"running at {rate:g} Hz (rate check: {check.summary()})", file=sys.stderr)
        config = dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=rate))
    setups = args.setups
    jitter: dict[str, list[np.ndarray]] = {setup: [] for setup in setups}
    faults: dict[str, tuple[list[str], list[str]]] = {setup: ([], []) for setup in setups}
    interrupted: dict[str, list[dict[str, float]]] = {setup: [] for setup in setups}
    arm_cpus = cpus[:-1] if browser_cpu is not None else cpus
    for r in range(args.rounds):
        for setup in setups:
            log = folder / f"{setup}-{r}.mcap"
            measured, rates, *run_faults = run(
                config, setup, args.seconds, log, browser_cpu=browser_cpu, arm_cpus=arm_cpus
            )
            jitter[setup].append(measured)
            interrupted[setup].append(rates)
            for when, fault, kept in zip(WHEN, run_faults, faults[setup], strict=True):
                if fault is not None:
                    kept.append(fault)
                    print(f"round {r + 1} {setup}: {when}: {fault}", file=sys.stderr)
            print(f"round {r + 1} {setup}: done", file=sys.stderr, flush=True)
    where = "every CPU shared" if browser_cpu is None else f"the browser on CPU {browser_cpu}, the rest on {cpus[:-1]}"
    rate, rounds = config.control.rate_hz, args.rounds
    print(f"arm2 over an slcan pty at {rate:g} Hz, {rounds} rounds x {args.seconds:g} s each; {where}")
    print(
        "| setup | cycles | jitter p50 µs | p99 µs | max µs | p99 of the rounds µs | p99 / none | faults: load / path |"
    )
    print("|---|---:|---:|---:|---:|---|---:|---:|")
    base = float(np.percentile(np.concatenate(jitter["none"]), 99)) if "none" in jitter else math.nan
    for setup in setups:
        every = np.concatenate(jitter[setup])
        p50, p99, top = (float(np.percentile(every, q)) * 1e6 for q in (50, 99, 100))
        rounds = ", ".join(f"{np.percentile(j, 99) * 1e6:.1f}" for j in jitter[setup])
        ratio, (at_load, on_path) = p99 / (base * 1e6), faults[setup]
        print(
            f"| {setup} | {len(every)} | {p50:.1f} | {p99:.1f} | {top:.0f} | {rounds} | {ratio:.2f} "
            f"| {len(at_load)} / {len(on_path)} |"
        )
    names = sorted({name for rates in interrupted[setups[0]] for name in rates})
    print(f"\nWhat interrupted the arm's CPUs {arm_cpus} while the path played, per second (median of the rounds):\n")
    print(f"| counter | {' | '.join(setups)} |")
    print(f"|---|{'---:|' * len(setups)}")
    for name in names:
        medians = [float(np.median([rates.get(name, 0.0) for rates in interrupted[setup]])) for setup in setups]
        if any(m >= 0.5 for m in medians):
            print(f"| {name} | {' | '.join(f'{m:.0f}' for m in medians)} |")
    if "browser" in jitter and "elsewhere" in jitter:
        # Paired by round (run one after the other): the round's p99 with this arm's page watched over the one with
        # another arm's page watched, by the same browser.
        pairs = [
            float(np.percentile(b, 99) / np.percentile(e, 99))
            for b, e in zip(jitter["browser"], jitter["elsewhere"], strict=True)
        ]
        low, mid, high = np.percentile(pairs, [25, 50, 75])
        pooled = np.percentile(np.concatenate(jitter["browser"]), 99) / np.percentile(
            np.concatenate(jitter["elsewhere"]), 99
        )
        print(
            f"\nbrowser / elsewhere, p99 per round paired: median {mid:.2f} (quartiles {low:.2f}-{high:.2f}; "
            f"{sum(x > 1 for x in pairs)} of {len(pairs)} rounds above 1); pooled: {pooled:.2f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
