"""A steered run recorded from the dashboard and replayed with its steering on the timeline,
in real Chromium: record, change the temperature, stop, replay from the Session panel, and a
click on the temperature mark takes the replay to the frame where it took effect."""

from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

import protocol as p
from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import session, wait_until
from tests.conftest import LiveServer
from tests.server.peers import Peer

pytestmark = pytest.mark.browser


def test_a_recorded_run_replays_with_its_steering_marks(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    expect(page.locator("#conn-text")).to_have_text("connected", timeout=60_000)
    page.click("#btn-record-run")
    expect(page.locator("#btn-record-run")).to_have_text(re.compile(r"^Stop run"), timeout=30_000)
    live = session(live_server)
    start = live.status.step
    wait_until(lambda: live.status.step > start + 60, "the run to go on")
    steerer = Peer(live_server.view_url, "steerer", live_server.token)
    try:
        steerer.send(p.SimParams(temperature_K=330.0))
        ack = steerer.expect(p.ParamsAck)
        assert ack.ok
    finally:
        steerer.close()
    wait_until(lambda: live.status.step > ack.step + 60, "frames after the change")
    expect(page.locator("#btn-record-run")).to_have_text(re.compile(r"· \d"))  # the size, live
    page.click("#btn-record-run")
    expect(page.locator("#btn-record-run")).to_have_text("Record run", timeout=30_000)
    item = page.locator("#recordings li").first
    expect(item).to_contain_text("frames", timeout=30_000)
    with page.expect_navigation(url=re.compile(r"session=replay-"), timeout=60_000):
        item.get_by_role("button", name=re.compile("^Replay")).click()
    expect(page.locator("#timeline")).to_be_visible(timeout=60_000)
    mark = page.locator(".tl-mark-sim_params")
    expect(mark).to_have_count(1, timeout=30_000)
    frame = int(mark.get_attribute("data-frame") or "-1")
    assert frame > 0
    # a replay without loop pauses on its last frame (a click on Pause could come after that and
    # play it again from the start); then jump to the mark
    expect(page.locator("#tl-play")).to_have_text("Play", timeout=60_000)
    expect(page.locator("#tl-frame")).to_have_text(re.compile(r"^frame (\d+) / \1$"))
    mark.click()
    expect(page.locator("#tl-frame")).to_have_text(re.compile(rf"^frame {frame + 1} / \d+$"))
    assert "temperature_K 330.0" in (mark.get_attribute("title") or "")
    live_server.app_state.replays.close()
