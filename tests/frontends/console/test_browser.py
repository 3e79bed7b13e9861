"""The console's REAL page in headless Chromium, against arm, force, decision, vision and the
console's virtual master, all in simulation on a private Zenoh network.

The page loads and mirrors the arm (the pedestal is drawn where the model puts it), the
Initialize and Home buttons make the arm ready and home (page and bus agree), a real mouse
drag of the gizmo moves the simulated arm (the gizmo is large enough at the default view
for a first drag to grab it), the E-STOP button's event shows in the page's log, the button
and the robot's status show the latch, and Reset re-engages the master. The loading
indicator goes once everything has arrived; the video fills its own window, keeping its
aspect. The page is kept as artifacts/console.png (git-ignored): docs/console.png is a
tracked picture refreshed deliberately from it (docs/console.md, "The screenshot").

With the arm service running the FR3 instead, the page draws the FR3 from the URDF visuals
its description carries (no PUMA anywhere): artifacts/console-fr3.png.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.bus import keys
from services.bus.messages import Event, RobotState
from services.bus.node import Node, Subscription
from services.control.arm.config import ArmConfig
from services.control.arm.model import load_model
from services.control.arm.service import ArmService
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from services.control.master.config import MasterConfig
from services.control.master.service import MasterService
from services.control.vision.config import VisionConfig
from services.control.vision.service import VisionService
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig
from services.geometry import R_from_wxyz
from tests.conftest import wait_until

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
ROOT = Path(__file__).resolve().parents[3]
ARTIFACT = ROOT / "artifacts" / "console.png"
ARTIFACT_FR3 = ROOT / "artifacts" / "console-fr3.png"
MIN_GIZMO_PX = 100.0
"""A gizmo handle at least this long on screen at the default view (1280×800)."""
MIN_VIDEO_PX = 400.0
NO_WAIT = True
"""A click is done when the page got it; what it does is awaited with `expect`. (Waiting
for "scheduled navigations" after a click needs the renderer's main thread, which software
WebGL on a loaded 2-core machine holds for tens of seconds at a time.)"""
CLICK_MS = 60_000
"""How long a click may wait for its button to be clickable, for the same reason."""
HOME_TOOL_P = np.array([0.55, 0.0, 0.65])
DRAG_M = 0.06

pytestmark = [
    pytest.mark.browser,
    pytest.mark.system,
    pytest.mark.skipif(
        not CHROMIUM.exists(),
        reason="no /usr/bin/chromium (make system-deps installs it: apt-get install chromium)",
    ),
    # A hang guard above the sum of the steps' own deadlines (the first test's waits add up
    # to about 250 s): on CI's starved 2 cores, 180 s cut a run that was still progressing.
    pytest.mark.timeout(360),
]


@dataclass
class System:
    console: Console
    client: Node
    state: Subscription[RobotState]
    events: list[Event]


@pytest.fixture
def system(net: Any) -> Iterator[System]:
    closers: list[Any] = []
    try:
        closers.append(
            ArmService(
                net.node("arm"),
                ArmConfig(sim_calibration_s=0.05, control_rate_hz=200.0, state_rate_hz=100.0),
            )
        )
        closers.append(ForceService(net.node("force"), ForceConfig(period_ms=5.0)))
        # Software WebGL on two cores starves every loop for tens of milliseconds at a time:
        # the supervisor's watchdogs are widened so they test nothing here (they are tested
        # in tests/control/decision), and the console is what is under test.
        closers.append(
            DecisionService(
                net.node("decision"),
                DecisionConfig(rate_hz=200.0, watchdog_ms=1000.0, state_stale_ms=1000.0),
            )
        )
        closers.append(
            VisionService(net.node("vision"), VisionConfig(width=320, height=240, fps=5.0))
        )
        closers.append(
            MasterService(
                net.node("master", instance="console"),
                MasterConfig(master_id="console", device="virtual", engage_on_start=False),
            )
        )
        console = Console(
            net.node("console"),
            ConsoleConfig(port=0, gui_rate_hz=20.0, shadows=False, video_fps=5.0),
        )
        closers.append(console)
        client = net.node("test")
        events: list[Event] = []
        client.subscribe(keys.EVENTS, events.append)
        yield System(console, client, client.subscribe(keys.STATE), events)
    finally:
        for c in reversed(closers):
            c.close()


def _project(cam: Any, p_world: np.ndarray) -> tuple[float, float]:
    """Pixel (u, v) of a world point in the client's view: viser reports the camera in
    OpenCV's convention (x right, y down, z forward) with a vertical field of view."""
    R = R_from_wxyz(cam.wxyz)
    pc = R.T @ (np.asarray(p_world, dtype=float) - np.asarray(cam.position))
    assert pc[2] > 0, "point behind the camera"
    f = 0.5 * cam.image_height / np.tan(0.5 * cam.fov)
    return f * pc[0] / pc[2] + 0.5 * cam.image_width, f * pc[1] / pc[2] + 0.5 * cam.image_height


def _camera(
    console: Console, width_px: int | None = None, timeout_s: float = 20.0, page: Any = None
) -> Any:
    """The page's camera as a client reports it (once it has, at `width_px` if given).

    Every client is looked at (a page that reconnected under load is a new client). With
    `page`, a camera still reported at another width after a resize is asked for again
    every 5 s by resizing the page by a pixel and back: the client reports its camera on a
    resize; twice in a `make test` the wait ran out (its report lost, or never sent, under
    load: the nudge covers both)."""
    deadline = time.monotonic() + timeout_s
    nudge_at = time.monotonic() + 5.0
    seen: list[int] = []
    while time.monotonic() < deadline:
        for client in list(console.server.get_clients().values()):
            cam = client.camera
            if cam.update_timestamp == 0.0:
                continue
            if width_px is None or cam.image_width == width_px:
                return cam
            seen.append(int(cam.image_width))
        if page is not None and width_px is not None and time.monotonic() > nudge_at:
            size = page.viewport_size
            page.set_viewport_size({"width": width_px - 1, "height": size["height"]})
            page.set_viewport_size({"width": width_px, "height": size["height"]})
            nudge_at = time.monotonic() + 5.0
        time.sleep(0.05)  # polling a third-party handle that offers no wait
    widths = sorted(set(seen))[:5]
    raise AssertionError(f"the page never reported its camera (at {width_px} px; seen {widths})")


def _scene_canvas(page: Any, timeout_s: float = 30.0) -> dict[str, float]:
    """The 3D view's canvas: the largest on the page (the plots draw on canvases too)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        # One look at the DOM: the plots' canvases come and go as they redraw.
        boxes = page.evaluate(
            "() => [...document.querySelectorAll('canvas')].map(c => {"
            " const r = c.getBoundingClientRect();"
            " return {x: r.x, y: r.y, width: r.width, height: r.height}; })"
        )
        if boxes:
            best = max(boxes, key=lambda b: b["width"] * b["height"])
            if best["width"] > 0 and best["height"] > 0:
                return best
        time.sleep(0.1)  # the page lays itself out: nothing to wait on but its DOM
    raise AssertionError("the page shows no 3D canvas")


def _plot_tails(page: Any) -> list[tuple[int, float, float]]:
    """Per uPlot chart on the page (viser's test hook): its number of points, its newest x
    and its first series' newest y."""
    tails = page.evaluate(
        "() => Object.values(window.__viserTestpoints?.uplots ?? {}).map(p => {"
        " const d = p.chart.data; const n = d[0].length;"
        " return [n, n ? d[0][n - 1] : null, n ? d[1][n - 1] : null]; })"
    )
    return [(int(n), float(x), float(y)) for n, x, y in tails]


def _pixels(png: bytes) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return np.asarray(img)


def _video_box(page: Any) -> dict[str, float] | None:
    """The video's box on the page: the widest image (the icons are ≤ 100 px)."""
    boxes = [
        b
        for b in (img.bounding_box() for img in page.locator("img").all())
        if b is not None and b["width"] > 100
    ]
    return max(boxes, key=lambda b: b["width"]) if boxes else None


def test_console_page_drives_the_sim_arm(system: System) -> None:
    from playwright.sync_api import expect, sync_playwright

    console = system.console
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(console.url)

            # --- the page loads and mirrors the arm (the pixels are checked below) ----------
            status = page.locator("#tr-robot-status")
            expect(status).to_have_attribute("data-status", "disconnected", timeout=30_000)
            expect(page.locator("#tr-alive li[data-alive='decision']")).to_have_count(1)
            expect(page.locator("#tr-tool-p")).not_to_be_empty()
            # Everything arrives (state, supervisor, force, video): the indicator goes.
            expect(page.locator("#tr-loading")).to_be_hidden(timeout=60_000)
            assert console.loaded
            # The force plots are live in the page's own charts: many points, the newest
            # within a second of now, and they keep changing (not frozen on one picture).
            first = _plot_tails(page)
            assert len(first) == 2 and all(n >= 2 and -1.0 <= x <= 0.0 for n, x, _ in first), first
            deadline = time.monotonic() + 20.0
            while _plot_tails(page) == first:
                assert time.monotonic() < deadline, f"the force plots are frozen at {first}"
                time.sleep(0.1)  # the page's charts offer no event to wait on
            cam = _camera(console)
            canvas = _scene_canvas(page)

            # --- Initialize: ready on the page and on the bus -----------------------------
            page.get_by_role("button", name="Initialize").click(
                no_wait_after=NO_WAIT, timeout=CLICK_MS
            )
            expect(status).to_have_attribute("data-status", "ready", timeout=20_000)
            assert system.state.wait_for(lambda s: s.status == "ready", 5.0) is not None

            # --- Home: the arm goes home; the gizmo is parked on the tool ------------------
            page.get_by_role("button", name="Home").click(no_wait_after=NO_WAIT, timeout=CLICK_MS)
            expect(page.locator("#tr-action")).to_have_text("home: done", timeout=40_000)
            home = system.state.wait_for(
                lambda s: float(np.linalg.norm(np.asarray(s.tool_p) - HOME_TOOL_P)) < 0.005, 5.0
            )
            assert home is not None, "the arm is not at home"
            expect(page.locator("#tr-master")).to_have_attribute(
                "data-link", "parked", timeout=10_000
            )
            p_start = np.asarray(system.state.latest.tool_p)  # type: ignore[union-attr]
            gizmo_p = np.asarray(console.gizmo.position)
            assert np.linalg.norm(gizmo_p - p_start) < 0.005, "the gizmo is not on the tool"

            # --- a real mouse drag on the gizmo's arrow moves the arm ---------------------
            # Drag along the gizmo axis that looks longest on screen.
            R = R_from_wxyz(console.gizmo.wxyz)
            scale = console.config.gizmo_scale_m
            o = np.array(_project(cam, gizmo_p))
            lengths = [
                np.linalg.norm(np.array(_project(cam, gizmo_p + R[:, k])) - o) for k in (0, 1, 2)
            ]
            axis = R[:, int(np.argmax(lengths))]
            # At the default view the handle is long enough on screen to be grabbed.
            assert max(lengths) * scale >= MIN_GIZMO_PX, f"gizmo {max(lengths) * scale:.0f} px"
            grab = gizmo_p + 0.75 * scale * axis
            x0, y0 = _project(cam, grab)
            x1, y1 = _project(cam, grab + DRAG_M * axis)
            ox, oy = canvas["x"], canvas["y"]
            page.mouse.move(ox + x0, oy + y0)
            page.mouse.down()
            steps = 8
            for i in range(1, steps + 1):
                page.mouse.move(ox + x0 + (x1 - x0) * i / steps, oy + y0 + (y1 - y0) * i / steps)
            page.mouse.up()
            moved = system.state.wait_for(
                lambda s: float(np.dot(np.asarray(s.tool_p) - p_start, axis)) > 0.8 * DRAG_M,
                10.0,
            )
            assert moved is not None, (
                f"the arm did not follow the gizmo (gizmo at {console.gizmo.position}, "
                f"tool at {system.state.latest.tool_p if system.state.latest else None})"
            )
            gizmo_moved = np.asarray(console.gizmo.position) - gizmo_p
            assert abs(float(np.dot(gizmo_moved, axis)) - DRAG_M) < 0.02
            # The drag took the lease for the console's master; letting go disengaged it
            # cleanly: parked where released, the lease given back, no watchdog.
            assert any(
                e.kind == "lease" and (e.data or {}).get("action") == "taken" for e in system.events
            ), "the drag never engaged the console's master"
            expect(page.locator("#tr-master")).to_have_attribute(
                "data-link", "parked", timeout=10_000
            )
            expect(page.locator("#tr-lease")).to_have_attribute("data-lease", "", timeout=10_000)
            assert not [e for e in system.events if e.kind == "watchdog"]

            # --- E-STOP shows its event on the page ----------------------------------------
            # From here on the page is tall enough for the whole control panel (status,
            # video, plots, log) in the screenshot below; resized now, so that the plots
            # have been redrawn at the new size by then.
            page.set_viewport_size({"width": 1400, "height": 1500})
            page.get_by_role("button", name="E-STOP", exact=True).click(
                no_wait_after=NO_WAIT, timeout=CLICK_MS
            )
            expect(page.locator("#tr-events li[data-kind='estop']").first).to_be_visible(
                timeout=10_000
            )
            expect(page.locator("#tr-estop")).to_be_visible(timeout=10_000)
            assert any(e.kind == "estop" and e.source == "decision" for e in system.events)
            # The button and the robot's status say the latch is set; Reset is offered.
            expect(page.get_by_role("button", name="E-STOP — LATCHED")).to_be_visible(
                timeout=10_000
            )
            expect(status).to_have_attribute("data-estop", "latched", timeout=10_000)
            expect(page.get_by_role("button", name="Reset e-stop")).to_be_enabled()

            # --- the video fills its window, keeping the frames' aspect --------------------
            box = _video_box(page)
            assert box is not None, "no video image on the page"
            assert box["width"] >= MIN_VIDEO_PX, f"the video is {box['width']:.0f} px wide"
            # side-by-side of two 320×240 eyes: 640×240
            assert box["width"] / box["height"] == pytest.approx(640 / 240, rel=0.03)

            # --- the page as a picture: 3D mirror, video, plots, status, events ------------
            notices = page.locator("button.mantine-Notification-closeButton")
            for close in notices.all():
                close.click(no_wait_after=NO_WAIT, timeout=CLICK_MS)
            expect(notices).to_have_count(0, timeout=10_000)  # gone, not fading out
            assert console.frames_shown > 0, "no stereo frame reached the page"
            cam = _camera(console, width_px=1400, page=page)
            canvas = _scene_canvas(page)
            ARTIFACT.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACT))
            shot = _pixels(ARTIFACT.read_bytes())
            assert shot.std() > 20, "the page is blank"
            # The arm is drawn where the model puts it: the pixel of the pedestal is its dark
            # grey, not the white background.
            u, v = _project(cam, np.array([0.0, 0.0, 0.35]))
            px = shot[int(canvas["y"] + v), int(canvas["x"] + u)]
            assert px.mean() < 170, f"no arm at the pedestal's pixel ({px})"

            # --- one eye: a frame narrower than the window still fills it --------------------
            # The left eye alone is 320×240 (160×120 while the camera's link is congested),
            # narrower than the window: the browser scales it up to the window's width.
            page.get_by_label("View").click(no_wait_after=NO_WAIT, timeout=CLICK_MS)
            page.get_by_role("option", name="left", exact=True).click(
                no_wait_after=NO_WAIT, timeout=CLICK_MS
            )

            def one_eye() -> dict[str, float] | None:
                b = _video_box(page)
                return b if b is not None and b["width"] / b["height"] < 1.5 else None

            assert wait_until(lambda: one_eye() is not None, 20.0, poll_s=0.1, what="one eye")
            eye = one_eye()
            assert eye is not None, f"the view shows no single eye ({_video_box(page)})"
            assert eye["width"] == pytest.approx(box["width"], abs=2.0), (eye, box)
            assert eye["width"] / eye["height"] == pytest.approx(320 / 240, rel=0.03)
            natural = page.evaluate("Math.max(...[...document.images].map((i) => i.naturalWidth))")
            assert natural < eye["width"], f"the frame ({natural} px) is not narrower"

            # --- Reset: the latch clears and the hand is parked on the tool again ----------
            page.get_by_role("button", name="Reset e-stop").click(
                no_wait_after=NO_WAIT, timeout=CLICK_MS
            )
            expect(page.locator("#tr-action")).to_have_text("reset: cleared", timeout=10_000)
            expect(page.locator("#tr-estop")).to_have_count(0, timeout=10_000)
            expect(page.get_by_role("button", name="E-STOP", exact=True)).to_be_visible()
            expect(status).to_have_attribute("data-estop", "clear", timeout=10_000)
            expect(page.locator("#tr-master")).to_have_attribute(
                "data-link", "parked", timeout=10_000
            )
            assert console.gui_errors == 0
        finally:
            browser.close()


def test_console_page_draws_the_fr3_from_its_description(net: Any) -> None:
    """The arm service runs the FR3: the page draws its URDF visuals (7 joints, the hand),
    mounted where its description puts it (x = 0.30 m, in front of the table), at home
    (the hand pointing down at the tool point (0.55, 0, 0.65)), and says so."""
    from playwright.sync_api import expect, sync_playwright

    arm = ArmService(net.node("arm"), ArmConfig(model="fr3", sim_calibration_s=0.05))
    console = Console(
        net.node("console"), ConsoleConfig(port=0, gui_rate_hz=20.0, shadows=False, video_fps=5.0)
    )
    fr3 = load_model("fr3")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(console.url)
                arm_line = page.locator("#tr-arm")
                expect(arm_line).to_have_attribute("data-arm", "visuals", timeout=60_000)
                expect(arm_line).to_have_attribute("data-model", "fr3")
                expect(arm_line).to_contain_text("7 joints")
                assert console.arm is not None and console.arm.n == 7
                n_visuals = len(fr3.geometry().geometryObjects)
                assert len(console.arm.parts) == n_visuals
                st = console.mirror.state.latest
                assert st is not None and len(st.q) == 7
                assert np.allclose(st.tool_p, HOME_TOOL_P, atol=1e-3)

                cam = _camera(console)
                canvas = _scene_canvas(page)
                # The forearm at home, from joint 4's origin to joint 5's: drawn there.
                origins = fr3.kinematics().link_origins(fr3.home)
                forearm = 0.5 * (origins[4] + origins[5])
                u, v = _project(cam, forearm)
                x, y = int(canvas["x"] + u), int(canvas["y"] + v)
                ARTIFACT_FR3.parent.mkdir(parents=True, exist_ok=True)

                def forearm_drawn() -> bool:
                    page.screenshot(path=str(ARTIFACT_FR3))
                    px = _pixels(ARTIFACT_FR3.read_bytes())[y, x]
                    return bool(px.mean() < 235)  # not the white background

                assert wait_until(forearm_drawn, 60.0, poll_s=0.5), "no FR3 at its forearm"
                assert console.gui_errors == 0
            finally:
                browser.close()
    finally:
        console.close()
        arm.close()
