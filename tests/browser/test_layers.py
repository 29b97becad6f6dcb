"""The layers panel in real Chromium: a typed selection is counted on the server as it is
typed, an invalid one is marked where it goes wrong and changes nothing, an applied one
changes the picture; a viewer sees the layers and cannot edit them; a late state does not take
back an edit made after the one it answers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgpack
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


def enter(page: Any, selector: str, text: str) -> None:
    """Type `text` into the field and press Enter, as a steerer applies a value."""
    field = page.locator(selector)
    field.fill(text)
    field.press("Enter")


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
    enter(page, "#layer-1-selection", "resid 13-35")
    # as a user would: the next field once the panel shows the applied selection's count
    wait_until(
        lambda: session(live_server).render_params.layers[1].selection == "resid 13-35",
        "the second selection was applied",
    )
    expect(page.locator("#layer-1-status")).to_contain_text("atoms")
    enter(page, "#layer-1-sigma", "0.6")
    wait_until(lambda: session(live_server).render_params.layers[1].sigma_A == 0.6, "layer 2 sigma")
    page.screenshot(path=str(artifacts / "dashboard-layers.png"))
    viewer = open_dashboard("viewer")
    vpage = viewer.page
    expect(vpage.locator("#layer-list li")).to_have_count(2)
    expect(vpage.locator("#layer-1-selection")).to_have_value("resid 13-35")
    for selector in ("#layer-add", "#layer-0-selection", "#layer-1-sigma", "#layer-0-visible"):
        expect(vpage.locator(selector)).to_be_disabled()
    expect(vpage.locator("#layers-reason")).to_contain_text("Read-only")


def message_type(message: Any) -> Any:
    if not isinstance(message, bytes):
        return None
    return msgpack.unpackb(message, raw=False, strict_map_key=False).get("type")


class HeldStates:
    """The dashboard's WebSocket, passed through the test: the server's `state` messages wait
    while `held` and then go on in order, as on a slow link (everything else passes). The
    test's Playwright calls are what move messages along, so it waits with
    `wait_until(..., page=page)`."""

    def __init__(self) -> None:
        self.held = False
        self.waiting: list[Any] = []
        self.page_side: Any = None

    def route(self, ws: Any) -> None:
        server = ws.connect_to_server()
        self.page_side = ws
        ws.on_message(server.send)
        server.on_message(self._from_server)

    def _from_server(self, message: Any) -> None:
        if self.held and message_type(message) == "state":
            self.waiting.append(message)
        else:
            self.page_side.send(message)

    def release_through(self, selection: str) -> dict[str, Any]:
        """Pass on the states that waited, up to the first whose first layer has `selection`;
        returns that one decoded."""
        while True:
            assert self.waiting, f"no state with the selection {selection!r} was held"
            message = self.waiting.pop(0)
            self.page_side.send(message)
            m = dict(msgpack.unpackb(message, raw=False, strict_map_key=False))
            layers = (m.get("render_params") or {}).get("layers") or [{}]
            if layers[0].get("selection") == selection:
                return m

    def release(self) -> None:
        self.held = False
        while self.waiting:
            self.page_side.send(self.waiting.pop(0))


def test_a_late_state_does_not_take_back_a_later_edit(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    """A selection applied and then a scale typed before the selection's state comes back: that
    state (which has no scale) must not clear the typed scale, on the page or in the session."""
    link = HeldStates()
    dash = open_dashboard(before_open=lambda page: page.route_web_socket("**/ws/view*", link.route))
    page = dash.page
    wait_for_full_view(dash)
    page.click("#layer-add")
    wait_until(lambda: len(session(live_server).render_params.layers) == 1, "the layer arrived")
    expect(page.locator("#layer-0-selection")).to_have_value("protein")
    link.held = True
    enter(page, "#layer-0-selection", "resid 1-12")
    wait_until(
        lambda: session(live_server).render_params.layers[0].selection == "resid 1-12",
        "the selection reached the session",
        page=page,
    )
    enter(page, "#layer-0-sigma", "0.6")
    wait_until(
        lambda: session(live_server).render_params.layers[0].sigma_A == 0.6,
        "the scale reached the session",
        page=page,
    )
    page.locator("#layer-add").focus()  # out of the list: the panel redraws from states
    first = link.release_through("resid 1-12")  # the selection's state, without the scale
    assert first["render_params"]["layers"][0].get("sigma_A") is None
    page.wait_for_timeout(500)
    expect(page.locator("#layer-0-sigma")).to_have_value("0.6")
    expect(page.locator("#layer-0-selection")).to_have_value("resid 1-12")
    link.release()
    page.wait_for_timeout(300)
    expect(page.locator("#layer-0-sigma")).to_have_value("0.6")
    # an edit after all that builds on the whole list: the scale stays in the session
    enter(page, "#layer-0-name", "N-terminus")
    wait_until(
        lambda: session(live_server).render_params.layers[0].name == "N-terminus",
        "name",
        page=page,
    )
    assert session(live_server).render_params.layers[0].sigma_A == 0.6


def test_a_change_made_while_a_layer_field_has_the_focus_shows_when_it_leaves(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    """Another steerer renames a layer while this page's focus is in the layers list: the
    rows are left alone then (a selection may be half typed), and show the new name once the
    focus leaves the list, with no further state from the session."""
    first = open_dashboard()
    wait_for_full_view(first)
    page = first.page
    page.click("#layer-add")
    wait_until(lambda: len(session(live_server).render_params.layers) == 1, "the layer arrived")
    other = open_dashboard().page
    expect(other.locator("#layer-0-name")).to_have_value("layer 1")
    page.locator("#layer-0-selection").focus()
    enter(other, "#layer-0-name", "backbone")
    wait_until(lambda: session(live_server).render_params.layers[0].name == "backbone", "rename")
    page.wait_for_timeout(1000)  # the rename's state has reached this page by now
    expect(page.locator("#layer-0-name")).to_have_value("layer 1")  # left alone while focused
    page.locator("#layer-add").focus()
    expect(page.locator("#layer-0-name")).to_have_value("backbone")
