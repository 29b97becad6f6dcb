"""A newcomer's first day, the small things, in real Chromium: the API docs authorize with the
dashboard's token, so "Try it out" answers; the pull arrow starts at the atom as it moves."""

from __future__ import annotations

import re

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import front_atom_on_page, session, wait_for_full_view, wait_until
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser


def test_the_api_docs_try_it_out_with_the_token(live_server: LiveServer, chromium: object) -> None:
    """`/docs` had no Authorize button: "Try it out" answered 401 even when opened with a
    token. Opened as `/docs?token=...` it is authorized; the button authorizes by hand."""
    context = chromium.new_context()  # type: ignore[attr-defined]
    try:
        page = context.new_page()
        page.goto(f"{live_server.url}/docs?token={live_server.token}")
        expect(page.locator(".swagger-ui .btn.authorize")).to_be_visible(timeout=60_000)
        expect(page.locator(".swagger-ui .btn.authorize.locked")).to_be_visible()
        operation = page.locator(".opblock-get", has_text=re.compile(r"/api/jobs\s*Jobs"))
        operation.locator(".opblock-summary").click()
        operation.get_by_role("button", name="Try it out").click()
        operation.get_by_role("button", name="Execute").click()
        status = operation.locator(".live-responses-table .response .response-col_status")
        expect(status.first).to_have_text("200", timeout=30_000)
        # without the token, the Authorize dialog takes it
        page.goto(f"{live_server.url}/docs")
        page.locator(".swagger-ui .btn.authorize").click()
        page.locator(".modal-ux input[type=text]").fill(str(live_server.token))
        page.locator(".modal-ux .auth-btn-wrapper .authorize").click()
        page.locator(".modal-ux .btn-done").click()
        operation = page.locator(".opblock-get", has_text=re.compile(r"/api/jobs\s*Jobs"))
        operation.locator(".opblock-summary").click()
        operation.get_by_role("button", name="Try it out").click()
        operation.get_by_role("button", name="Execute").click()
        status = operation.locator(".live-responses-table .response .response-col_status")
        expect(status.first).to_have_text("200", timeout=30_000)
    finally:
        context.close()


def test_the_pull_arrow_starts_at_the_atom_as_it_moves(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    """The arrow started where the atom was picked, and the pulled atom moved away from it."""
    dash = open_dashboard()
    wait_for_full_view(dash)
    page = dash.page
    page.fill("#pull-k", "10")  # a stiff spring: the atom follows it within seconds
    page.fill("#pull-max", "50")
    x, y = front_atom_on_page(dash, live_server)
    page.keyboard.down("Control")
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 120, y - 60, steps=6)
    pulls = wait_until(lambda: dict(session(live_server).forces.pulls), "the server holds the pull")
    atom = next(iter(pulls))
    picked = np.asarray(dash.evaluate("() => window.scalesteer.pull.position"))

    def moved() -> bool:
        now = np.asarray(session(live_server).positions[atom], dtype=np.float64)
        return bool(np.linalg.norm(now - picked) > 3.0)

    # 3 A: a thermal step back and the page's lag (each under 1 A) keep it past 1.5 A
    wait_until(moved, "the pulled atom to move 3 A from where it was picked", 60, page)
    page.wait_for_timeout(500)  # a tracked message or two since
    start, at, shown = dash.evaluate(
        """a => { const s = window.scalesteer; const v = s.viewport;
                  return [v.arrowFrom, v.toOverlay(s.pull.position), s.pull.position]; }""",
        atom,
    )
    server = np.asarray(session(live_server).positions[atom], dtype=np.float64)
    assert np.linalg.norm(np.asarray(shown) - server) < 1.0, "the page follows the atom"
    assert np.linalg.norm(np.asarray(shown) - picked) > 1.5
    assert np.allclose(start, at), "the arrow is drawn from the atom's tracked position"
    page.mouse.up()
    page.keyboard.up("Control")
    wait_until(lambda: not session(live_server).forces.pulls, "the pull was released")
