"""Video streaming in real Chromium: the dashboard asks WebCodecs what it decodes, the server
streams H.264 (libx264 here: this machine has no NVENC), a Worker decodes it, and the page falls
back to JPEG when asked or when its decoder fails, without a reload."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import snapshot, view_centre, wait_for_frame
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser

BROKEN_WORKER = """
self.onmessage = (e) => {
  if (e.data.type === "chunk") {
    self.postMessage({ type: "error", message: "EncodingError: broken" });
  }
};
"""


def wait_format(dash: object, fmt: str, timeout_ms: int = 90_000) -> None:
    dash.page.wait_for_function(  # type: ignore[attr-defined]
        "(fmt) => document.getElementById('viewport').dataset.format === fmt",
        arg=fmt,
        timeout=timeout_ms,
    )


def test_video_frames_are_decoded_drawn_and_follow_the_simulation(
    open_dashboard: OpenDashboard,
    simulation: OpenMMSimulation,
    live_server: LiveServer,
    artifacts: Path,
) -> None:
    dash = open_dashboard()
    assert "h264" in dash.evaluate("() => document.body.dataset.videoCodecs").split()
    wait_format(dash, "h264")
    first = wait_for_frame(dash)
    before = snapshot(dash)
    assert before.std() > 5, "the decoded frame shows the molecule"
    later = wait_for_frame(dash, first + 5)
    after = snapshot(dash)
    assert later > first and np.abs(after - before).mean() > 0.2, "the picture moves"
    expect(dash.page.locator("#hud-stream")).to_contain_text("H.264 (libx264)")
    expect(dash.page.locator("#hud-stream")).to_contain_text("fps")
    dash.page.screenshot(path=str(artifacts / "dashboard-video.png"))
    streams = live_server.app_state.sessions.get("default").delivery.streams.describe()
    assert [s["codec"] for s in streams] == ["h264"]


def test_a_resize_mid_stream_keeps_the_video_going(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    wait_format(dash, "h264")
    first = wait_for_frame(dash)
    size = dash.page.locator("#viewport").get_attribute("data-image-size")
    dash.page.set_viewport_size({"width": 1100, "height": 720})
    dash.page.wait_for_function(
        """([size, after]) => {
          const v = document.getElementById('viewport').dataset;
          return v.imageSize !== size && Number(v.frame) > after && v.format === 'h264';
        }""",
        arg=[size, first],
        timeout=90_000,
    )
    assert snapshot(dash).std() > 5


def test_a_second_viewer_joining_mid_stream_gets_a_picture(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    steerer = open_dashboard()
    wait_format(steerer, "h264")
    wait_for_frame(steerer)
    time.sleep(1.0)  # the stream runs on
    viewer = open_dashboard("viewer")
    t0 = time.monotonic()
    wait_format(viewer, "h264")
    wait_for_frame(viewer, still=False)
    assert time.monotonic() - t0 < 30
    assert snapshot(viewer).std() > 5
    streams = live_server.app_state.sessions.get("default").delivery.streams.describe()
    assert sum(int(s["viewers"]) for s in streams) == 2  # type: ignore[call-overload]


def test_choosing_jpeg_switches_the_stream_without_a_reload(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    wait_format(dash, "h264")
    dash.page.evaluate("() => { window.__sameDocument = true; }")
    dash.page.select_option("#transport", "jpeg")
    wait_format(dash, "jpeg")
    dash.page.select_option("#transport", "auto")
    wait_format(dash, "h264")
    assert dash.page.evaluate("() => window.__sameDocument === true")


def test_a_decoder_error_falls_back_to_jpeg_without_a_reload(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, chromium: object
) -> None:
    dash = open_dashboard(wait_connected=False, allow=("video decoding failed",))
    dash.page.route(
        "**/video.worker.js",
        lambda route: route.fulfill(body=BROKEN_WORKER, content_type="text/javascript"),
    )
    dash.page.reload()
    dash.page.evaluate("() => { window.__sameDocument = true; }")
    dash.page.wait_for_function(
        "() => document.body.dataset.videoFailed === 'true'", timeout=90_000
    )
    expect(dash.page.locator("#notices")).to_contain_text("video decoding failed")
    wait_format(dash, "jpeg")
    first = wait_for_frame(dash)
    assert wait_for_frame(dash, first) > first
    assert dash.page.evaluate("() => window.__sameDocument === true")


def test_jpeg_from_the_address(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard(wait_connected=False)
    dash.page.goto(f"{live_server.url}/?token={live_server.token}&transport=jpeg")
    first = wait_for_frame(dash)
    wait_for_frame(dash, first)
    assert dash.page.locator("#viewport").get_attribute("data-format") == "jpeg"
    assert dash.page.locator("#transport").input_value() == "jpeg"


def test_dragging_the_camera_turns_the_stream_without_keyframes(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    """A drag sends a view per animation frame: each is a delta frame of the one stream, at
    the interactive size (one keyframe down); once the drag has rested, one keyframe brings
    the stream back to full size, and the page's decoder follows both."""
    dash = open_dashboard()
    wait_format(dash, "h264")
    wait_for_frame(dash)
    default = "{}x{}".format(*live_server.settings.default_size)  # drawn before the page's view
    dash.page.wait_for_function(
        "(d) => { const s = document.getElementById('viewport').dataset.imageSize; "
        "return s && s !== d; }",
        arg=default,
        timeout=90_000,
    )
    first = wait_for_frame(dash)
    viewport = dash.page.locator("#viewport")
    full = viewport.get_attribute("data-image-size")
    session = live_server.app_state.sessions.get("default")
    (before,) = session.summary()["video_streams"]
    cx, cy = view_centre(dash)
    mouse = dash.page.mouse
    mouse.move(cx - 120, cy)
    mouse.down()
    sizes = set()
    for k in range(12):  # a slow drag: a view per step, each drawn before the next
        mouse.move(cx - 120 + 20 * (k + 1), cy + 3 * k, steps=2)
        time.sleep(0.15)
        sizes.add(viewport.get_attribute("data-image-size"))
    mouse.up()
    last = wait_for_frame(dash, first + 3, still=False)  # steering frames are not stills
    (after,) = session.summary()["video_streams"]
    assert after["stream"] == before["stream"], "the drag restarted the stream"
    assert after["frames"] >= before["frames"] + 3, "the drag was not streamed"
    assert after["keyframes"] <= before["keyframes"] + 1, "the drag's frames were keyframes"
    assert sizes - {full}, f"the drag was streamed at full size only ({sizes})"
    dash.page.wait_for_function(  # the drag rests: full size again, still decoded as video
        """([full, after]) => {
          const v = document.getElementById('viewport').dataset;
          return v.imageSize === full && Number(v.frame) > after && v.format === 'h264';
        }""",
        arg=[full, last],
        timeout=90_000,
    )
    (rested,) = session.summary()["video_streams"]
    assert rested["stream"] == before["stream"] and rested["keyframes"] <= before["keyframes"] + 2
    assert snapshot(dash).std() > 5
