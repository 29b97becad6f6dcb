"""The layers panel in real Chromium: a typed selection is counted on the server as it is
typed, an invalid one is marked where it goes wrong and changes nothing, an applied one
changes the picture; a viewer sees the layers and cannot edit them."""

from __future__ import annotations

from pathlib import Path

import pytest
from playwright.sync_api import expect

from tests.browser.conftest import OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import (
    session,
    snapshot,
    wait_for_full_view,
    wait_for_new_image,
    wait_until,
)
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser


def test_a_typed_selection_is_counted_checked_and_drawn(
    open_dashboard: OpenDashboard,
    simulation: OpenMMSimulation,
    live_server: LiveServer,
    artifacts: Path,
) -> None:
    dash = open_dashboard()
    page = dash.page
    wait_for_full_view(dash)
    live = session(live_server)
    assert live.render_params.layers == []  # the dry villin: every atom, one layer
    n_atoms = live.topology.n_atoms
    expect(page.locator("#layers-empty")).to_be_visible()
    before = snapshot(dash)
    page.click("#layer-add")
    wait_until(lambda: len(session(live_server).render_params.layers) == 1, "the layer arrived")
    status = page.locator("#layer-0-status")
    expect(status).to_have_text(f"{n_atoms} atoms")  # villin is all protein
    selection = page.locator("#layer-0-selection")
    # an invalid selection is marked in place and not applied
    selection.fill("resid 1-12 and (name CA")
    expect(status).to_contain_text("character 24")
    expect(page.locator("#layer-0-status mark")).to_be_visible()
    expect(selection).to_have_attribute("aria-invalid", "true")
    selection.press("Enter")
    page.wait_for_timeout(500)
    assert session(live_server).render_params.layers[0].selection == "protein"
    # a valid one shows its count as it is typed, and Enter applies it
    selection.fill("resid 1-12")
    wait_until(lambda: "atoms" in status.inner_text(), "the count arrived")
    count = int(status.inner_text().split()[0].replace(",", ""))
    assert 0 < count < n_atoms
    selection.press("Enter")
    wait_until(
        lambda: session(live_server).render_params.layers[0].selection == "resid 1-12",
        "the selection was applied",
    )
    wait_for_new_image(dash, before, threshold=4.0)
    wait_until(lambda: "layers=" in dash.evaluate("() => location.hash"), "the URL carries it")
    # a second, finer layer; then the viewer's page shows both, read-only
    page.click("#layer-add")
    wait_until(lambda: len(session(live_server).render_params.layers) == 2, "two layers")
    page.locator("#layer-1-selection").fill("resid 13-35")
    page.locator("#layer-1-selection").press("Enter")
    page.locator("#layer-1-sigma").fill("0.6")
    page.locator("#layer-1-sigma").press("Enter")
    wait_until(lambda: session(live_server).render_params.layers[1].sigma_A == 0.6, "layer 2 sigma")
    page.screenshot(path=str(artifacts / "dashboard-layers.png"))
    viewer = open_dashboard("viewer")
    vpage = viewer.page
    expect(vpage.locator("#layer-list li")).to_have_count(2)
    expect(vpage.locator("#layer-1-selection")).to_have_value("resid 13-35")
    for selector in ("#layer-add", "#layer-0-selection", "#layer-1-sigma", "#layer-0-visible"):
        expect(vpage.locator(selector)).to_be_disabled()
    expect(vpage.locator("#layers-reason")).to_contain_text("Read-only")
