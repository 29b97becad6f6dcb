"""The temporal scale control in real Chromium: choosing warped smoothing in the dashboard
reaches the session and its renderer, which then draws the smoothed path."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import session, wait_for_frame, wait_until
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser


def test_the_temporal_scale_control_reaches_the_renderer(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    wait_for_frame(dash)
    page.click("#time-details summary")
    expect(page.locator("#tau-frames")).to_be_disabled()  # nothing to set while off
    page.select_option("#time-smoothing", "warped")
    expect(page.locator("#tau-frames")).to_be_enabled()
    page.locator("#time-window").fill("8")
    page.select_option("#time-kernel", "centred")
    expect(page.locator("#time-lag")).to_have_text("Display lag: 3 frames.")
    live = session(live_server)
    wait_until(
        lambda: (
            live.render_params.time_smoothing == "warped"
            and live.render_params.time_window == 8
            and live.render_params.time_kernel == "centred"
        ),
        "the settings reached the session",
    )
    slot = live_server.app_state.gpu._slots[live.slot]

    def smoothing() -> bool:
        state = slot.renderer._temporal
        return state is not None and state.smoother is not None and state.smoother.count == 8

    wait_until(smoothing, "the renderer smoothing over a full window", timeout=90)
    link = dash.evaluate("() => window.location.hash")
    assert "ts=warped" in link and "tw=8" in link and "tk=centred" in link  # the link keeps it
    page.select_option("#color-by", "motion")
    expect(page.locator("#legend")).to_contain_text("γ′", timeout=30_000)
