"""The periodic box panel in real Chromium, on tz2 in its truncated octahedron (MDAnalysisTests'
AMBER parm7/NetCDF) sent by a simulation client with its box: the panel shows the session's
choices, a choice made there reaches the session, and "Show the box" outlines the box over the
picture."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from playwright.sync_api import expect

import protocol as p
from tests.browser.conftest import OpenDashboard
from tests.browser.test_dashboard import session, wait_for_full_view, wait_until
from tests.conftest import LiveServer
from tests.server.peers import Peer

pytestmark = pytest.mark.browser
datafiles = pytest.importorskip("MDAnalysisTests.datafiles")

OUTLINE = """() => {
  const c = document.getElementById('overlay');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) {
    if (d[i + 3] > 100 && Math.abs(d[i] - 200) < 12 && Math.abs(d[i + 2] - 215) < 12) n += 1;
  }
  return n;
}"""


@pytest.fixture
def boxed(live_server: LiveServer) -> Iterator[Peer]:
    """tz2's first frame, with its box, in the default session."""
    from structures.reader import load

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        structure = load(datafiles.PRM7, [datafiles.NCDFtruncoct])
        positions, box = structure.frame(0)
    sim = Peer(live_server.ws_url, "simulation", live_server.token)
    sim.send(structure.topology)
    sim.send(
        p.Frame(
            step=0,
            time_ps=0.0,
            positions=p.WireArray.from_numpy(positions, "<f4"),
            box=p.WireArray.from_numpy(np.asarray(box), "<f4"),
        )
    )
    yield sim
    sim.close()


def test_the_periodic_panel_steers_the_session_and_outlines_the_box(
    open_dashboard: OpenDashboard, boxed: Peer, live_server: LiveServer, artifacts: Path
) -> None:
    dash = open_dashboard()
    page: Any = dash.page
    wait_for_full_view(dash)
    page.click("#periodic-details summary")
    expect(page.locator("#periodic-mode")).to_have_value("molecules")
    expect(page.locator("#periodic-center")).to_have_value("auto")
    expect(page.locator("#periodic-center-selection")).to_have_value("protein")
    expect(page.locator("#periodic-fit-selection")).to_be_disabled()  # the fit is off
    assert dash.evaluate(OUTLINE) == 0
    page.select_option("#periodic-mode", "whole")
    wait_until(lambda: session(live_server).render_params.periodic == "whole", "whole arrived")
    page.check("#periodic-cell")
    wait_until(lambda: session(live_server).render_params.show_cell, "show_cell arrived")
    wait_until(lambda: dash.evaluate(OUTLINE) > 200, "the box's outline is drawn")
    page.screenshot(path=str(artifacts / "periodic_cell.png"))
    page.select_option("#periodic-fit", "rotation")
    expect(page.locator("#periodic-fit-selection")).to_be_enabled()
    wait_until(lambda: session(live_server).render_params.fit == "rotation", "the fit arrived")
    page.uncheck("#periodic-cell")
    wait_until(lambda: dash.evaluate(OUTLINE) == 0, "the outline is gone")
