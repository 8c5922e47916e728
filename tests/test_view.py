"""The live view and the replay (motion.view) in a real browser: Playwright driving Debian's chromium, headless.

The registry's Playwright cannot download its own browser here: ``.ci/run`` installs Debian's ``chromium`` when it is
missing, and these tests point Playwright at it (they are skipped, saying so, on a machine without it).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from motion import Arm, MotionFault, ViewOptions
from motion.compose import arm_figure
from motion.config import load_config
from motion.control.snapshot import JOINT_ROWS, CycleSnapshot, frozen
from motion.telemetry import TelemetryOptions, load_log
from motion.view import LiveView, Replay, host_warning
from tests.motion_rig import CONFIGS

playwright = pytest.importorskip("playwright.sync_api")
from PIL import Image  # noqa: E402 - matplotlib's dependency

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no chromium here: .ci/run installs Debian's (apt-get install chromium)"
)
ARM6 = CONFIGS / "arm6.yaml"
#: Software WebGL: the page and its 3D scene take a few seconds to come up on a slow host.
PAGE_TIMEOUT_MS = 60_000


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        )
        yield browser
        browser.close()


class Page:
    """A browser page and the errors it reported (console errors and uncaught exceptions)."""

    def __init__(self, browser: object) -> None:
        self.context = browser.new_context(viewport={"width": 1200, "height": 800})  # type: ignore[attr-defined]
        self.page = self.context.new_page()
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))

    def open(self, url: str) -> None:
        self.page.goto(url, timeout=PAGE_TIMEOUT_MS)
        self.page.wait_for_selector("span[data-joint]", timeout=PAGE_TIMEOUT_MS)

    def angle(self, joint: str) -> float:
        return float(self.page.inner_text(f"span[data-joint='{joint}']"))

    def text(self) -> str:
        return str(self.page.inner_text("body"))

    def scene(self) -> np.ndarray:
        """The 3D area (the page left of the control panel) as an RGB array."""
        png = self.page.screenshot(clip={"x": 320, "y": 150, "width": 460, "height": 600})
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


@pytest.fixture
def page(browser: object) -> Iterator[Page]:
    page = Page(browser)
    yield page
    page.context.close()


def _differing(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels that differ visibly."""
    return float((np.abs(a - b).max(axis=2) > 24).mean())


def _wait_until(condition: object, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < end, "timed out"
        time.sleep(0.05)


def test_the_page_loads_without_errors_and_draws_the_arm(page: Page, browser: object) -> None:
    import viser

    empty = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        blank = Page(browser)
        blank.page.goto(f"http://127.0.0.1:{empty.get_port()}", timeout=PAGE_TIMEOUT_MS)
        blank.page.wait_for_selector("canvas", timeout=PAGE_TIMEOUT_MS)
        time.sleep(2.0)
        empty_scene = blank.scene()
        blank.context.close()
    finally:
        empty.stop()
    with Arm(load_config(ARM6), emulate=True, view=ViewOptions(port=0)) as arm:
        assert arm.view is not None
        page.open(arm.view.url)
        assert "READY" in page.text()
        time.sleep(2.0)  # the scene renders
        before = page.scene()
        assert _differing(before, empty_scene) > 0.01  # the arm (and its floor) are drawn
        arm.move_to({"base_yaw": 90.0, "shoulder_pitch": 40.0}, speed_scale=1.0)
        arm.sleep(0.5)
        time.sleep(1.0)
        assert _differing(page.scene(), before) > 0.002  # and drawn where it now is
    assert page.errors == []


def test_a_joints_displayed_angle_follows_an_emulated_move(page: Page) -> None:
    with Arm(load_config(ARM6), emulate=True, view=ViewOptions(port=0)) as arm:
        assert arm.view is not None
        page.open(arm.view.url)
        assert page.angle("shoulder_pitch") == pytest.approx(0.0, abs=0.02)
        # the page itself samples what it shows, every 50 ms, while the arm moves (about 5 s, paced)
        page.page.evaluate(
            """() => { window.seen = []; setInterval(() => window.seen.push(parseFloat(
                document.querySelector("span[data-joint='shoulder_pitch']").textContent)), 50); }"""
        )
        # a page that has just opened can be busy for seconds (its scene's first software render on a cold browser,
        # during which it samples once and shows nothing new): the move starts once it has sampled for half a second
        page.page.wait_for_function("() => window.seen.length >= 10", timeout=PAGE_TIMEOUT_MS)
        # the move in a thread: this one keeps serving the browser's driver (Playwright's sync API)
        mover = threading.Thread(target=lambda: arm.move_to({"shoulder_pitch": 40.0}, speed_scale=0.15))
        mover.start()
        while mover.is_alive():
            page.page.wait_for_timeout(50)
        mover.join()
        arm.sleep(0.3)  # the view's next snapshots
        final = arm.positions()["shoulder_pitch"]
        _wait_until(lambda: abs(page.angle("shoulder_pitch") - final) < 0.006)
        seen = page.page.evaluate("() => window.seen")
    # on the way: the page showed the joint between start and target, in order (a browser that renders in software
    # on a busy host applies only some of the updates: at least two on the way)
    between = [a for a in seen if 0.1 < a < 39.9]
    assert len(set(between)) >= 2, f"{len(seen)} samples, of which these differ: {sorted(set(seen))}"
    assert between == sorted(between)
    assert page.errors == []


def test_stop_halts_the_emulated_arm_and_the_page_says_why(page: Page) -> None:
    with Arm(load_config(ARM6), emulate=True, view=ViewOptions(port=0)) as arm:
        assert arm.view is not None and arm.emulator is not None
        page.open(arm.view.url)
        outcome: list[BaseException] = []

        def move() -> None:
            try:
                arm.move_to({"base_yaw": 150.0, "elbow_pitch": -100.0}, speed_scale=0.1)  # about 10 s
            except MotionFault as exc:
                outcome.append(exc)

        mover = threading.Thread(target=move)
        mover.start()
        _wait_until(lambda: "MOVING" in page.text())
        page.page.get_by_role("button", name="STOP").click()
        clicked = arm.positions()["base_yaw"]
        mover.join(30.0)
        assert not mover.is_alive()
        assert len(outcome) == 1 and isinstance(outcome[0], MotionFault)
        assert outcome[0].kind == "estop" and "STOP pressed in the view" in str(outcome[0])
        # halted on the way, as Ctrl-C halts (arm6's halt_policy: hold: a stop ramp, then every axis holds still)
        assert arm.supervisor is not None and arm.supervisor.state.faulted
        arm.sleep(1.0)
        held = arm.positions()
        assert clicked < held["base_yaw"] < 140.0
        arm.sleep(1.0)
        # holding: the drives' loops settle within a degree (moving on, base_yaw would have gone 15 degrees)
        assert arm.positions() == pytest.approx(held, abs=1.0)
        _wait_until(lambda: "FAULTED" in page.text() and "STOP pressed in the view" in page.text())
    assert page.errors == []


@pytest.fixture(scope="module")
def demo_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from motion.demo import run_demo

    out = tmp_path_factory.mktemp("demo")
    assert run_demo(out, quiet=True) == 0
    return out / "position.mcap"


def test_replay_of_a_demo_log_shows_the_final_pose_at_the_end_of_the_slider(page: Page, demo_log: Path) -> None:
    log = load_log(demo_log)
    config = load_config(ARM6)
    replay = Replay(log, config, arm_figure(config), port=0)
    try:
        page.open(replay.url)
        start = log["q_deg"][0]
        assert page.angle("shoulder_pitch") == pytest.approx(start[1], abs=0.006)
        slider = page.page.get_by_role("slider").first
        slider.focus()
        slider.press("End")
        final = log["q_deg"][-1]
        _wait_until(lambda: abs(page.angle("elbow_pitch") - final[2]) < 0.006)
        for name, q in zip(log.joint_names, final, strict=True):
            assert page.angle(name) == pytest.approx(q, abs=0.006), name
        assert float(re.search(r"t = ([0-9.]+) s", page.text()).group(1)) == pytest.approx(  # type: ignore[union-attr]
            log["t_s"][-1], abs=0.01
        )
    finally:
        replay.close()
    assert page.errors == []


def test_cli_view_replays_a_log_until_ctrl_c_and_warns_beyond_this_computer(page: Page, demo_log: Path) -> None:
    command = [sys.executable, "-m", "motion.cli", "view", str(demo_log), "--host", "0.0.0.0", "--view-port", "0"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        match = re.search(r"at http://[^:]+:(\d+)", line)
        assert match, line
        page.open(f"http://127.0.0.1:{match.group(1)}")
        assert "shoulder_pitch" in page.text()
        process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=30)
    finally:
        with contextlib.suppress(ProcessLookupError):
            process.kill()
    assert process.returncode == 0, err
    assert "anyone who can reach its port sees the arm and can press STOP" in err


def test_cli_move_with_view_shows_the_move_and_stays_open_until_ctrl_c(page: Page) -> None:
    command = [sys.executable, "-m", "motion.cli", "move", "--config", str(CONFIGS / "arm2.yaml"), "shoulder=25"]
    command += ["--emulate", "--view", "--view-port", "0"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert process.stderr is not None
        line = process.stderr.readline()
        match = re.search(r"view: (http://\S+)", line)
        assert match, line
        page.open(match.group(1))
        _wait_until(lambda: abs(page.angle("shoulder") - 25.0) < 0.05)
        stderr = process.stderr
        _wait_until(lambda: "stays open" in stderr.readline())
        process.send_signal(signal.SIGINT)
        out, _ = process.communicate(timeout=30)
    finally:
        with contextlib.suppress(ProcessLookupError):
            process.kill()
    assert process.returncode == 0
    reached = re.search(r"at shoulder=(-?\d+\.\d+)", out)
    assert reached and abs(float(reached.group(1)) - 25.0) <= 0.1, out  # (arrived: within control.goal_tolerance_deg)


def test_view_options_and_host_warning() -> None:
    with pytest.raises(ValueError, match=r"70000 is outside 0\.\.65535"):
        ViewOptions(port=70000)
    assert host_warning("127.0.0.1") is None
    assert "0.0.0.0" in (host_warning("0.0.0.0") or "")


def test_a_paced_simulation_runs_at_the_wall_clocks_speed_with_the_same_result(tmp_path: Path) -> None:
    results, walls = [], []
    views: tuple[bool | ViewOptions, ...] = (False, ViewOptions(port=0))
    for k, view in enumerate(views):
        telemetry = TelemetryOptions(tmp_path / f"run{k}.mcap")
        with Arm(load_config(ARM6), emulate=True, view=view, telemetry=telemetry) as arm:
            start = time.monotonic()
            handle = arm.move_to({"shoulder_pitch": 20.0}, speed_scale=1.0, wait=False)
            duration = handle.progress().duration_s
            handle.wait()
            walls.append((time.monotonic() - start, duration))
        assert arm.telemetry is not None and arm.telemetry.result is not None
        results.append(arm.telemetry.result["q_deg"])
    assert np.array_equal(results[0], results[1])
    paced_wall, duration = walls[1]
    assert paced_wall >= 0.95 * duration


def test_a_urdf_with_visuals_is_drawn_from_its_meshes(page: Page, demo_log: Path, tmp_path: Path) -> None:
    # arm6's URDF with a cylinder visual on every link (yourdfpy, through viser's URDF helper), replaying the demo
    urdf = (CONFIGS / "arm6.urdf").read_text()
    visual = '<visual><origin xyz="0 0 0.05"/><geometry><cylinder radius="0.03" length="0.1"/></geometry></visual>'
    urdf = re.sub(r"(<link name=\"[a-z_]+\">)", r"\1" + visual, urdf)
    (tmp_path / "arm6.urdf").write_text(urdf)
    (tmp_path / "arm6.yaml").write_text(ARM6.read_text())
    config = load_config(tmp_path / "arm6.yaml")
    log = load_log(demo_log)
    replay = Replay(log, config, arm_figure(config), port=0)
    try:
        figure = replay._page.measured
        assert type(figure).__name__ == "_UrdfFigure"
        page.open(replay.url)
        replay.show(float(log["t_s"][-1]))
        # the helper's actuated joints got the recorded angles (radians, its order)
        names = list(figure._urdf.get_actuated_joint_names())
        angles = dict(zip(names, figure._urdf._urdf.cfg, strict=True))
        final = dict(zip(log.joint_names, log["q_deg"][-1], strict=True))
        assert {n: math.degrees(a) for n, a in angles.items()} == pytest.approx(final, abs=1e-9)
        _wait_until(lambda: abs(page.angle("elbow_pitch") - final["elbow_pitch"]) < 0.006)
    finally:
        replay.close()
    assert page.errors == []


def test_the_loop_never_waits_for_a_page_that_is_behind() -> None:
    config = load_config(ARM6)
    view = LiveView(config, arm_figure, lambda: None, port=0)
    pid = view.pid
    os.kill(pid, signal.SIGSTOP)  # the page's process reads nothing more
    try:
        joints = frozen([np.zeros(len(config.joints))] * len(JOINT_ROWS))

        def loop() -> None:
            for k in range(5000):  # a second apart: every one is due
                view.publish(CycleSnapshot(k, float(k), joints, True, state="moving"))

        publishing = threading.Thread(target=loop, daemon=True)
        publishing.start()
        publishing.join(60.0)  # a publish that waited would never end: the page's process is stopped
        assert not publishing.is_alive(), "publish waited for the stopped page"
        # the socket filled, and the rest were dropped, not waited for
        assert view.updates > 0
        assert view.dropped > 0
        assert view.updates + view.dropped == 5000
    finally:
        os.kill(pid, signal.SIGCONT)
        view.close()
    assert view._process.returncode == 0


def test_a_snapshot_the_view_cannot_send_is_counted_not_raised_into_the_loop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = load_config(ARM6)
    view = LiveView(config, arm_figure, lambda: None, port=0)
    try:
        joints = frozen([np.zeros(len(config.joints))] * len(JOINT_ROWS))
        for k in (1, 2):  # a state that is no text: the view's failure, not the loop's
            view.publish(CycleSnapshot(k, float(k), joints, True, state=None))  # type: ignore[arg-type]
        view.publish(CycleSnapshot(3, 3.0, joints, True, state="moving"))
    finally:
        view.close()
    assert (view.failures, view.updates) == (2, 1)
    assert [r.getMessage() for r in caplog.records if r.name == "motion.view"] == [
        "the view could not be sent a cycle (further failures are counted, not logged)"
    ]


def test_a_script_without_a_main_guard_opens_one_view(tmp_path: Path) -> None:
    # the page's process is a program of its own: it does not run the caller's script again (multiprocessing's spawn
    # would: a second arm)
    script = tmp_path / "arm.py"
    script.write_text(
        "from motion import Arm, ViewOptions\n"
        "from motion.config import load_config\n"
        f"with Arm(load_config({str(ARM6)!r}), emulate=True, view=ViewOptions(port=0)) as arm:\n"
        "    print('view', arm.view.url, flush=True)\n"
        "    arm.move_to({'elbow_pitch': -10.0}, speed_scale=0.5)\n"
        "print('done', flush=True)\n"
    )
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=180, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("view http://127.0.0.1:") == 1
    assert result.stdout.splitlines()[-1] == "done"


def test_a_picture_held_back_reaches_the_page_once_the_loop_pauses() -> None:
    # simulated time stops while the program does not wait: the move's last pictures, dropped while the page was
    # behind (or held back by the view's rate), would otherwise leave the page showing an older pose for good
    with Arm(load_config(ARM6), emulate=True, view=ViewOptions(port=0)) as arm:
        view = arm.view
        assert view is not None
        feed = view._feed

        class Behind:
            def sendmsg(self, parts: object) -> int:
                raise BlockingIOError  # the page's socket is full

        view._feed = Behind()  # type: ignore[assignment]
        try:
            arm.move_to({"shoulder_pitch": 10.0})
            dropped = view.dropped
            assert dropped > 0 and view._sent is not view._latest, (dropped, view.updates)
            time.sleep(0.3)  # the latest picture tried (a drop, where the view's rate had held it back) ...
            tried = view.dropped
            assert tried <= dropped + 1
            time.sleep(0.3)  # ... and tried again while the page is behind: not counted again
            assert view.dropped == tried
        finally:
            view._feed = feed
        end = time.monotonic() + 10.0
        while view._sent is not view._latest:
            assert time.monotonic() < end, "the latest picture never went out"
            time.sleep(0.02)
        sent = view._sent
        assert sent is not None
        position = sent.joints[JOINT_ROWS.index("position_deg")]
        np.testing.assert_allclose(position, list(arm.positions().values()), atol=1e-9)
