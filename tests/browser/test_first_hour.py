"""What a newcomer's first hour needs, in real Chromium: the colour legend, measuring between
atoms that follow the simulation, saving and opening a view, recording a movie of the view,
opening trajectory files from the browser into a replay with a timeline, and the API docs
served without a network."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.browser.conftest import Dashboard, OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.browser.test_dashboard import (
    session,
    wait_for_full_view,
    wait_until,
)
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser
pytest.importorskip("MDAnalysisTests")


def atoms_on_page(dash: Dashboard, server: LiveServer) -> list[tuple[float, float]]:
    """Page coordinates of the atoms nearest the camera, well apart on the screen."""
    positions = np.asarray(session(server).positions, dtype=np.float64)
    points = dash.evaluate(
        "ps => ps.map(p => window.scalesteer.projectToPage(p))", positions.tolist()
    )
    box = dash.page.locator("#view").bounding_box()
    assert box is not None
    inside = sorted(
        (
            q
            for q in points
            if q["depth"] > 0
            and box["x"] + 20 < q["x"] < box["x"] + box["width"] - 20
            and box["y"] + 20 < q["y"] < box["y"] + box["height"] - 60
        ),
        key=lambda q: q["depth"],
    )
    chosen: list[tuple[float, float]] = []
    for q in inside:
        if all(math.hypot(q["x"] - x, q["y"] - y) > 40 for x, y in chosen):
            chosen.append((q["x"], q["y"]))
        if len(chosen) == 3:
            break
    return chosen


def test_the_legend_names_the_colours(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    legend = dash.page.locator("#legend")
    expect(legend).to_be_visible()
    expect(legend.locator(".legend-title")).to_have_text("Element")
    labels = legend.locator(".legend-entries li").all_text_contents()
    assert {"C", "N", "O", "H"} <= {t.strip() for t in labels}
    dash.page.select_option("#color-by", "residue")
    expect(legend.locator(".legend-title")).to_have_text("Residue class")
    expect(legend.locator(".legend-entries")).to_contain_text("hydrophobic")
    # motion's unit had been a bare "γ′": the legend says what it is and what sets it
    dash.page.select_option("#color-by", "motion")
    expect(legend.locator(".legend-title")).to_have_text("Motion: warp rate γ′")
    expect(legend.locator(".legend-ends")).to_have_text(re.compile(r"1 γ′ at rest\s*3 γ′ fast"))
    expect(legend.locator(".legend-note")).to_contain_text("frames of warped time per frame")


def test_shift_clicking_atoms_measures_and_the_markers_follow_them(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    wait_for_full_view(dash)
    (x1, y1), (x2, y2), (x3, y3) = atoms_on_page(dash, live_server)
    page.mouse.click(x1, y1)
    expect(page.locator("#pick-atom")).to_have_text(re.compile(r"^index \d+$"))
    page.keyboard.down("Shift")
    page.mouse.click(x2, y2)
    page.keyboard.up("Shift")
    expect(page.locator("#pick-measure")).to_have_text(re.compile(r"^distance [\d.]+ Å"))
    # read together: the positions move with every tracked frame
    picks, measure = dash.evaluate(
        """() => [window.scalesteer.picks.atoms.map(a => [a.atom, a.position]),
                  document.getElementById('pick-details').dataset.measure]"""
    )
    (a, pa), (b, pb) = picks
    assert a != b
    shown = float(measure.split(":")[1])
    assert shown == pytest.approx(float(np.linalg.norm(np.subtract(pa, pb))), rel=1e-6)
    # the positions follow the simulation (tracked by the server with every frame)
    wait_until(
        lambda: dash.evaluate("() => window.scalesteer.picks.atoms[0].position") != pa,
        "the marked atom moved with the simulation",
    )
    page.keyboard.down("Shift")
    page.mouse.click(x3, y3)
    page.keyboard.up("Shift")
    expect(page.locator("#pick-measure")).to_have_text(re.compile(r"^angle [\d.]+ °"))
    # the three atoms' labels and the angle's: none covers another (they had overlapped)
    rects = dash.evaluate("() => window.scalesteer.viewport.labelRects")
    assert [r["text"].split()[0] for r in rects[:3]] == ["1", "2", "3"] and len(rects) == 4
    for i, a in enumerate(rects):
        for b in rects[i + 1 :]:
            apart = (
                a["x"] + a["w"] <= b["x"]
                or b["x"] + b["w"] <= a["x"]
                or a["y"] + a["h"] <= b["y"]
                or b["y"] + b["h"] <= a["y"]
            )
            assert apart, (a, b)
    page.keyboard.press("Escape")
    expect(page.locator("#pick-measure")).to_have_text(re.compile("^Shift-click"))


def test_a_saved_view_opens_again(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, tmp_path: Path
) -> None:
    dash = open_dashboard()
    page = dash.page
    wait_for_full_view(dash)
    page.keyboard.press("x")  # look along +x: a camera of its own
    page.fill("#sigma-number", "2.2")
    page.press("#sigma-number", "Enter")
    wait_until(lambda: dash.evaluate("() => window.scalesteer.render.sigma_A") == 2.2, "sigma")
    camera = dash.evaluate("() => window.scalesteer.camera")
    with page.expect_download() as info:
        page.click("#btn-save-view")
    saved = json.loads(Path(info.value.path()).read_text())
    assert saved["scalesteer_view"] == 1 and saved["render_params"]["sigma_A"] == 2.2
    # change both, then open the file: the camera and the rendering come back
    page.keyboard.press("y")
    page.fill("#sigma-number", "1.2")
    page.press("#sigma-number", "Enter")
    wait_until(lambda: dash.evaluate("() => window.scalesteer.render.sigma_A") == 1.2, "sigma")
    page.set_input_files("#open-view-file", info.value.path())
    wait_until(lambda: dash.evaluate("() => window.scalesteer.render.sigma_A") == 2.2, "restored")
    restored = dash.evaluate("() => window.scalesteer.camera")
    assert restored["orientation"] == pytest.approx(camera["orientation"])
    bad = tmp_path / "notes.json"
    bad.write_text('{"hello": 1}')
    page.set_input_files("#open-view-file", str(bad))
    expect(page.locator("#notices")).to_contain_text("not a view file")
    # a damaged copy is refused whole, naming each problem: neither its camera nor its sigma
    damaged = dict(saved, camera={**saved["camera"], "distance": -5})
    damaged["render_params"] = {**saved["render_params"], "sigma_A": "x", "mode": "hologram"}
    broken = tmp_path / "damaged.json"
    broken.write_text(json.dumps(damaged))
    page.set_input_files("#open-view-file", str(broken))
    notices = page.locator("#notices")
    expect(notices).to_contain_text("was not applied")
    expect(notices).to_contain_text("camera.distance -5")
    expect(notices).to_contain_text('render_params.sigma_A "x" is not a number')
    assert dash.evaluate("() => window.scalesteer.render.sigma_A") == 2.2
    assert dash.evaluate("() => window.scalesteer.camera")["distance"] == restored["distance"]


def test_recording_the_view_downloads_a_movie_of_it(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    import av

    dash = open_dashboard()
    page = dash.page
    wait_for_full_view(dash)
    page.click("#btn-record")
    expect(page.locator("#btn-record")).to_have_attribute("aria-pressed", "true")
    expect(page.locator("#btn-record")).to_have_text(re.compile(r"Stop recording 0:0[2-9]"))
    with page.expect_download(timeout=120_000) as info:
        page.click("#btn-record")
    assert info.value.suggested_filename.endswith(".mp4")
    with av.open(info.value.path()) as container:
        frames = [f for f in container.decode(video=0)]
    assert len(frames) >= 2
    expect(page.locator("#btn-record")).to_have_text("Record movie")


def test_files_opened_from_the_browser_replay_with_a_timeline(
    open_dashboard: OpenDashboard, live_server: LiveServer
) -> None:
    from MDAnalysisTests.datafiles import DCD, PSF

    dash = open_dashboard()
    page = dash.page
    with page.expect_navigation(url=re.compile(r"session=replay-adk"), timeout=120_000):
        page.set_input_files("#open-files", [DCD, PSF])  # in any order
    expect(page.locator("#conn-text")).to_have_text("connected", timeout=60_000)
    timeline = page.locator("#timeline")
    expect(timeline).to_be_visible(timeout=60_000)
    expect(page.locator("#tl-frame")).to_have_text(re.compile(r"^frame \d+ / 98$"))
    # the bar had covered the view's status line (step, fps, latency)
    hud, bar = page.locator("#hud").bounding_box(), timeline.bounding_box()
    assert hud is not None and bar is not None
    assert hud["y"] + hud["height"] <= bar["y"], (hud, bar)
    page.click("#tl-play")  # pause, then seek to frame 50
    expect(page.locator("#tl-play")).to_have_text("Play")
    page.locator("#tl-scrub").fill("49")
    wait_until(lambda: session(live_server, "replay-adk").status.step == 49, "seeked to 50")
    expect(page.locator("#tl-frame")).to_have_text("frame 50 / 98")
    page.select_option("#tl-speed", "2")
    wait_until(
        lambda: any(
            "speed" in e.get("action", "") or e.get("speed") == 2.0 for e in _log(live_server)
        ),
        "the speed change reached the replay",
    )
    # a replay has no temperature: the field says why instead of failing later
    temperature = page.locator("#sim-temperature")
    expect(temperature).to_be_disabled()
    assert "no thermostat" in (temperature.get_attribute("title") or "")
    page.click("#tl-play")
    live_server.app_state.replays.close()


def _log(server: LiveServer) -> list[dict[str, object]]:
    return server.app_state.steering_log.read("replay-adk")


def test_the_api_docs_work_without_a_network(live_server: LiveServer, chromium: object) -> None:
    context = chromium.new_context()  # type: ignore[attr-defined]
    outside: list[str] = []

    def only_local(route: object) -> None:
        url = route.request.url  # type: ignore[attr-defined]
        if url.startswith(live_server.url):
            route.continue_()  # type: ignore[attr-defined]
        else:
            outside.append(url)
            route.abort()  # type: ignore[attr-defined]

    try:
        page = context.new_page()
        page.route("**/*", only_local)
        page.goto(f"{live_server.url}/docs")
        expect(page.locator(".swagger-ui .opblock").first).to_be_visible(timeout=60_000)
        expect(page.locator(".swagger-ui")).to_contain_text("/api/render")
        page.goto(f"{live_server.url}/redoc")
        expect(page.locator("redoc, [role=navigation], .menu-content").first).to_be_attached(
            timeout=60_000
        )
        expect(page.locator("body")).to_contain_text("api/jobs", timeout=60_000)
        # ReDoc's sidebar badge asks its CDN for a logo and hides itself when that fails;
        # everything the pages need came from this server
        assert not [u for u in outside if u != "https://cdn.redoc.ly/redoc/logo-mini.svg"]
    finally:
        context.close()
