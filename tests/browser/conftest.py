"""Fixtures for the dashboard tests: Debian's Chromium through Playwright, a real server
(`live_server`), and one simulation source (`simulation`) feeding it.

The simulation source is the only fixture that knows what feeds the server: replace it with a
real adapter (trajectory replay, OpenMM) and every test runs unchanged.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tests.browser.simulation import OpenMMSimulation
from tests.conftest import LiveServer, make_settings, start_server

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"
CLIENT_DIR = Path(__file__).resolve().parents[2] / "client_web"
DEFAULT_VIEWPORT = (960, 640)
"""Small enough for the CPU renderer to keep up, wide enough for the two-column layout."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    reasons = []
    if not CHROMIUM.exists():
        reasons.append(f"{CHROMIUM} is not installed (apt-get install chromium)")
    modules = CLIENT_DIR / "node_modules"
    needed = [modules / "@msgpack/msgpack/dist.esm/index.mjs", modules / "uplot/dist/uPlot.esm.js"]
    if not all(path.is_file() for path in needed):
        reasons.append("the dashboard's npm dependencies are missing (make client)")
    for item in items:
        if item.get_closest_marker("browser") is None:
            continue
        for reason in reasons:
            item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(scope="package")
def chromium() -> Iterator[Any]:
    """One browser for the browser tests, closed after the last of them: Playwright's
    synchronous API holds this thread's event loop while it is open, and later tests run
    their own loops here."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        yield browser
        browser.close()


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[LiveServer]:
    """A server without the frame-time budget: the budget sizes images by how fast this
    machine renders, and these tests check what the page shows at its own view size (the
    budget has its own tests, in tests/server/session/test_scheduler.py)."""
    server = start_server(make_settings(tmp_path, frame_budget_ms=0.0))
    yield server
    server.stop()


@pytest.fixture
def simulation(live_server: LiveServer) -> Iterator[OpenMMSimulation]:
    """The simulation feeding the server's default session; `stop()` kills it, `start()`
    brings it back."""
    sim = OpenMMSimulation(live_server.ws_url, live_server.token)
    sim.start()
    yield sim
    sim.stop()


@dataclass
class Dashboard:
    """One dashboard page and what its console said."""

    page: Any
    console_errors: list[str] = field(default_factory=list)

    def evaluate(self, script: str, arg: Any = None) -> Any:
        return self.page.evaluate(script, arg)


OpenDashboard = Callable[..., Dashboard]


@pytest.fixture
def open_dashboard(live_server: LiveServer, chromium: Any) -> Iterator[OpenDashboard]:
    """Open the dashboard as `role` ("steerer", "viewer", or "steerer-with-viewer-token");
    `before_open(page)` runs before the page loads. At teardown no page may have logged a
    console error (apart from `allow` patterns)."""
    contexts: list[Any] = []
    pages: list[Dashboard] = []
    allowed: list[re.Pattern[str]] = []

    def open_page(
        role: str = "steerer",
        *,
        size: tuple[int, int] = DEFAULT_VIEWPORT,
        hash: str = "",
        allow: tuple[str, ...] = (),
        wait_connected: bool = True,
        before_open: Callable[[Any], None] | None = None,
    ) -> Dashboard:
        allowed.extend(re.compile(a) for a in allow)
        query = {
            "steerer": f"?token={live_server.token}",
            "viewer": f"?role=viewer&token={live_server.viewer_token}",
            "steerer-with-viewer-token": f"?token={live_server.viewer_token}",
        }[role]
        context = chromium.new_context(
            viewport={"width": size[0], "height": size[1]},
            device_scale_factor=1,
            accept_downloads=True,
        )
        contexts.append(context)
        page = context.new_page()
        page.set_default_timeout(60_000)
        dash = Dashboard(page)
        page.on(
            "console",
            lambda m: dash.console_errors.append(m.text) if m.type == "error" else None,
        )
        page.on("pageerror", lambda e: dash.console_errors.append(f"page error: {e}"))
        pages.append(dash)
        if before_open is not None:  # e.g. routes that must be in place before the page loads
            before_open(page)
        page.goto(f"{live_server.url}/{query}{hash}")
        if wait_connected:
            wait_text(page, "#conn-text", "connected")
        return dash

    yield open_page
    try:
        for dash in pages:
            errors = [e for e in dash.console_errors if not any(a.search(e) for a in allowed)]
            assert not errors, f"console errors: {errors}"
    finally:
        for context in contexts:
            context.close()


def wait_text(page: Any, selector: str, text: str, timeout_ms: int = 60_000) -> None:
    from playwright.sync_api import expect

    expect(page.locator(selector)).to_have_text(text, timeout=timeout_ms)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS
