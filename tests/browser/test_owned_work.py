"""Nothing a closed tab started runs on unseen, in real Chromium: a recording of the run and a
movie of the view, started from the dashboard, are listed with Stop in the Session panel of
every page (marked as this page's in the one that started them), and end once their tab
closes."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from playwright.sync_api import expect

from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import wait_until
from tests.conftest import LiveServer, make_settings, start_server

pytestmark = pytest.mark.browser
GRACE_S = 1.5
AUTH = {"Authorization": "Bearer test-token"}


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[LiveServer]:
    """The browser tests' server (no frame budget), with a short grace for a closed page."""
    server = start_server(make_settings(tmp_path, frame_budget_ms=0.0, owner_grace_s=GRACE_S))
    yield server
    server.stop()


def test_closing_the_tab_ends_its_recording_and_its_movie(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    page.click("#btn-record-run")
    expect(page.locator("#btn-record-run")).to_have_text(re.compile(r"^Stop run"), timeout=30_000)
    page.click("#btn-record")
    expect(page.locator("#btn-record")).to_have_text(re.compile(r"^Stop recording"), timeout=30_000)
    page.locator("#panel-session summary").click()
    mine = page.locator("#running-work li.mine")
    expect(mine).to_have_count(2, timeout=30_000)
    expect(page.locator("#running-work li[data-kind=recording]")).to_contain_text("this page")
    expect(page.locator("#running-work li[data-kind=movie]")).to_contain_text("this page")
    other = open_dashboard().page  # another tab sees them too, as another page's, with Stop
    other.locator("#panel-session summary").click()
    listed = other.locator("#running-work li")
    expect(listed).to_have_count(2, timeout=30_000)
    expect(listed.first).to_contain_text("another page")
    expect(listed.get_by_role("button", name=re.compile("^Stop"))).to_have_count(2)

    with httpx.Client(base_url=live_server.url, headers=AUTH, timeout=30) as c:
        jobs = c.get("/api/jobs", params={"active": "true"}).json()
        recs = [r for r in c.get("/api/recordings").json() if r["state"] == "recording"]
        assert len(jobs) == 1 and len(recs) == 1
        job, rec = jobs[0]["id"], recs[0]["id"]
        page.context.close()  # the tab closes mid-recording

        def ended() -> Any:
            movie = c.get(f"/api/jobs/{job}").json()["movie"]
            recording = c.get(f"/api/recordings/{rec}").json()
            done = not movie["recording"] and recording["state"] == "finished"
            return done and (movie, recording)

        movie, recording = wait_until(ended, "the recording and the movie to end", 60, other)
        why = "the page that started it left session 'default'"
        assert recording["ended_because"] == why and recording["frames"] > 0
        assert movie["ended_because"] == why and movie["taken"] > 0
        # the other tab's list empties (the movie may still render its frames: cancel it)
        expect(other.locator("#running-work li[data-kind=recording]")).to_have_count(0)
        movie_row = other.locator("#running-work li[data-kind=movie]")
        if movie_row.count():
            movie_row.get_by_role("button", name=re.compile("^Cancel")).click()
        expect(other.locator("#running-work li")).to_have_count(0, timeout=30_000)
        assert c.get(f"/api/jobs/{job}").json()["state"] in ("done", "cancelled")
