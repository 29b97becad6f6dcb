"""A newcomer's first day, the small things, in real Chromium: the API docs authorize with the
dashboard's token, so "Try it out" answers."""

from __future__ import annotations

import re

import pytest
from playwright.sync_api import expect

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
