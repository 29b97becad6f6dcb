"""A replay's timeline in real Chromium, on two pages of one session fed by a scripted replay:
both show the speed and loop the replay plays at, whoever changed them and however odd the
speed, and what the replay's acknowledgements say is taken only as the session keeps it."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import msgpack
import pytest
from playwright.sync_api import expect

import protocol as p
from tests.browser.conftest import OpenDashboard
from tests.browser.test_dashboard import session
from tests.conftest import LiveServer
from tests.server.peers import Peer, frame, molecule

pytestmark = pytest.mark.browser
NO_MARKS = ("status of 404",)
"""A replay not opened through the API has no marks: the page's request for them is refused."""


@pytest.fixture
def replay(live_server: LiveServer) -> Iterator[Peer]:
    """A replay of a helix in the default session, playing at 3x (a speed a script set: the
    Speed list does not offer it), looping."""
    sim = Peer(live_server.ws_url, "simulation", live_server.token)
    sim.send(
        p.EngineInfo(
            name="replay of a helix",
            kind="replay",
            n_frames=10,
            controls=["pause", "resume", "seek", "speed", "loop"],
            playback=p.Playback(speed=3.0, loop=True),
        )
    )
    topology, positions = molecule(12)
    sim.send(topology)
    sim.send(frame(positions, 0))
    yield sim
    sim.close()


def acknowledge(sim: Peer, applied: dict[str, Any]) -> None:
    """Acknowledge the next control as applied with `applied`, sent as is (unchecked)."""
    control = sim.expect(p.Control)
    ack = {"type": "params_ack", "ref": control.seq, "step": 0, "applied": applied}
    sim.ws.send(msgpack.packb(ack, use_bin_type=True))


def test_every_page_shows_the_speed_and_loop_the_replay_plays_at(
    open_dashboard: OpenDashboard, replay: Peer, live_server: LiveServer
) -> None:
    steerer = open_dashboard(allow=NO_MARKS)
    asked: list[str] = []  # the viewer's requests for the timeline's steering marks

    def count_marks(page: Any) -> None:
        page.on("request", lambda r: asked.append(r.url) if "/api/replays/" in r.url else None)

    viewer = open_dashboard("viewer", before_open=count_marks, allow=NO_MARKS)
    for dash in (steerer, viewer):
        # 3x is not in the list: the box had shown nothing
        expect(dash.page.locator("#tl-speed")).to_have_value("3")
        expect(dash.page.locator("#tl-speed option:checked")).to_have_text("3×")
        expect(dash.page.locator("#tl-loop")).to_be_checked()
    steerer.page.select_option("#tl-speed", "0.5")
    acknowledge(replay, {"action": "speed", "speed": 0.5})
    expect(viewer.page.locator("#tl-speed")).to_have_value("0.5")
    # acknowledgements the session cannot take as they are: a speed that is no number, a
    # loop that is a word (read as "off"); the page that asked had shown them raw (a blank
    # Speed, its Loop ticked) while every other page showed the playback the session keeps
    steerer.page.select_option("#tl-speed", "4")
    acknowledge(replay, {"action": "speed", "speed": "nan"})
    steerer.page.uncheck("#tl-loop")
    acknowledge(replay, {"action": "loop", "loop": "no"})
    expect(viewer.page.locator("#tl-loop")).not_to_be_checked()
    assert session(live_server).engine.playback == p.Playback(speed=0.5, loop=False)
    for dash in (steerer, viewer):
        expect(dash.page.locator("#tl-speed")).to_have_value("0.5")
        expect(dash.page.locator("#tl-loop")).not_to_be_checked()
    # the marks belong to the replay, not to its speed or loop: asked for once, not again
    # with each change
    assert len(asked) == 1, asked
