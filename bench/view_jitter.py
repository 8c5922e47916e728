"""The control loop's wake-up jitter with and without the live view (issue 15).

arm2 against `rmd-motion emulate` in its own process over an slcan pty (real time), following a back-and-forth path;
the loop's jitter per cycle (the telemetry log's ``jitter_s``: wake-up minus scheduled start) in three setups,
interleaved over rounds so that the host's drift hits them alike:

- ``none``: no view;
- ``server``: the view's server and thread running, nobody watching;
- ``browser``: the view with a page open in headless chromium (Playwright; software WebGL), on the same host.

    .venv/bin/python bench/view_jitter.py                    # 3 rounds x 3 setups x 8 s, about 2 min
    .venv/bin/python bench/view_jitter.py --rounds 5 --seconds 15

The rate is arm2's configured one, or the rate check's recommendation when this host cannot hold it. Prints a
Markdown table; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from motion import Arm, ViewOptions  # noqa: E402
from motion.config import ArmConfig, load_config  # noqa: E402
from motion.control.ratecheck import RateError  # noqa: E402
from motion.telemetry import TelemetryOptions, load_log  # noqa: E402

PATH = ((30.0, -40.0), (-20.0, 20.0))
SETUPS = ("none", "server", "browser")


@contextlib.contextmanager
def browser_page(url: str | None) -> Iterator[None]:
    """A headless chromium page on ``url`` for the duration (nothing when ``url`` is None)."""
    if url is None:
        yield
        return
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=chromium, args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        )
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        page.goto(url)
        page.wait_for_selector("span[data-joint]", timeout=60_000)
        yield
        browser.close()


def run(config: ArmConfig, setup: str, seconds: float, log: Path) -> np.ndarray:
    """One run; the jitter of every cycle while the path played, s."""
    view: bool | ViewOptions = False if setup == "none" else ViewOptions(port=0)
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
        with browser_page(arm.view.url if setup == "browser" and arm.view is not None else None):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                arm.follow(PATH, speed_scale=0.5)
    finally:
        arm.close()
    recorded = load_log(log)
    jitter: np.ndarray = recorded["jitter_s"][recorded.active_rows()]
    return jitter


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=8.0)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="rmd-view-jitter-"))
    config = load_config(ROOT / "configs" / "arm2.yaml")
    try:
        Arm(config, emulate="realtime").connect().close()
    except RateError as exc:
        rate = exc.check.recommended_rate_hz
        print(f"{config.control.rate_hz:g} Hz refused by the rate check; running at {rate:g} Hz", file=sys.stderr)
        config = dataclasses.replace(config, control=dataclasses.replace(config.control, rate_hz=rate))
    jitter: dict[str, list[np.ndarray]] = {setup: [] for setup in SETUPS}
    for r in range(args.rounds):
        for setup in SETUPS:
            jitter[setup].append(run(config, setup, args.seconds, folder / f"{setup}-{r}.npz"))
            print(f"round {r + 1} {setup}: done", file=sys.stderr, flush=True)
    print(f"arm2 over an slcan pty at {config.control.rate_hz:g} Hz, {args.rounds} rounds x {args.seconds:g} s each")
    print("| setup | cycles | jitter p50 µs | p99 µs | max µs | p99 of the rounds µs | p99 / none |")
    print("|---|---:|---:|---:|---:|---|---:|")
    base = float(np.percentile(np.concatenate(jitter["none"]), 99))
    for setup in SETUPS:
        every = np.concatenate(jitter[setup])
        p50, p99, top = (float(np.percentile(every, q)) * 1e6 for q in (50, 99, 100))
        rounds = ", ".join(f"{np.percentile(j, 99) * 1e6:.0f}" for j in jitter[setup])
        print(f"| {setup} | {len(every)} | {p50:.0f} | {p99:.0f} | {top:.0f} | {rounds} | {p99 / (base * 1e6):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
