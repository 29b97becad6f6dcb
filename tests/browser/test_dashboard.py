"""The dashboard in real Chromium against a real server fed by a simulation: images, camera,
render and simulation steering, picking and pulling, roles, reconnects, plots, layout."""

from __future__ import annotations

import csv
import io
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import expect

from tests.browser.conftest import Dashboard, OpenDashboard
from tests.browser.simulation import OpenMMSimulation
from tests.conftest import LiveServer

pytestmark = pytest.mark.browser

SNAPSHOT_JS = """() => {
  const c = document.getElementById('view');
  const w = 64, h = 40;
  const g = new OffscreenCanvas(w, h).getContext('2d');
  g.drawImage(c, 0, 0, w, h);
  const d = g.getImageData(0, 0, w, h).data;
  const out = [];
  for (let i = 0; i < d.length; i += 4) out.push((d[i] + d[i + 1] + d[i + 2]) / 3);
  return out;
}"""


def snapshot(dash: Dashboard) -> np.ndarray:
    """The view canvas, downsampled to 64x40 grey levels."""
    return np.asarray(dash.evaluate(SNAPSHOT_JS), dtype=np.float64).reshape(40, 64)


def frame_id(dash: Dashboard) -> int:
    value = dash.page.locator("#viewport").get_attribute("data-frame")
    return int(value) if value else -1


def view_centre(dash: Dashboard) -> tuple[float, float]:
    """The page coordinates of the middle of the live view (where drags start)."""
    box = dash.page.locator("#view").bounding_box()
    assert box is not None
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


def wait_for_frame(dash: Dashboard, after: int = -1, *, still: bool = True) -> int:
    """Wait until an image newer than `after` is on screen (a full-quality still by default)."""
    dash.page.wait_for_function(
        """([after, still]) => {
          const v = document.getElementById('viewport').dataset;
          return Number(v.frame ?? -1) > after && (!still || v.still === 'true');
        }""",
        arg=[after, still],
        timeout=90_000,
    )
    return frame_id(dash)


def wait_for_full_view(dash: Dashboard) -> None:
    """Wait for a still rendered at this page's own view size (not the server's default)."""
    dash.page.wait_for_function(
        """() => {
          const v = document.getElementById('viewport').dataset;
          const c = document.getElementById('view');
          return v.still === 'true' && v.imageSize === `${c.width}x${c.height}`;
        }""",
        timeout=90_000,
    )


def wait_until(
    condition: Callable[[], Any], what: str, timeout: float = 60.0, page: Any = None
) -> Any:
    """Poll `condition`; with a `page`, wait with its timer, so that the page's routes and
    events keep being handled meanwhile (Playwright dispatches them only during its calls)."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting until {what}")
        if page is None:
            time.sleep(0.1)
        else:
            page.wait_for_timeout(100)


def wait_for_new_image(dash: Dashboard, before: np.ndarray, threshold: float = 4.0) -> np.ndarray:
    """Wait for stills until one differs from `before` by `threshold` grey levels on average."""

    def changed() -> list[np.ndarray]:
        wait_for_frame(dash, frame_id(dash) - 1)
        now = snapshot(dash)
        return [now] if np.abs(now - before).mean() > threshold else []

    result: np.ndarray = wait_until(changed, "the image changed")[0]
    return result


def session(server: LiveServer, name: str = "default") -> Any:
    live = server.app_state.sessions.get(name)
    assert live is not None, f"no session {name}"
    return live


def front_atom_on_page(dash: Dashboard, server: LiveServer) -> tuple[float, float]:
    """Page coordinates of the atom nearest the camera (its centre lies inside the surface)."""
    positions = np.asarray(session(server).positions, dtype=np.float64)
    points = dash.evaluate(
        "ps => ps.map(p => window.scalesteer.projectToPage(p))", positions.tolist()
    )
    box = dash.page.locator("#view").bounding_box()
    assert box is not None
    inside = [
        q
        for q in points
        if q["depth"] > 0
        and box["x"] + 4 < q["x"] < box["x"] + box["width"] - 4
        and box["y"] + 4 < q["y"] < box["y"] + box["height"] - 4
    ]
    assert inside, "no atom projects into the view"
    nearest = min(inside, key=lambda q: q["depth"])
    return nearest["x"], nearest["y"]


def record_text(dash: Dashboard, selector: str) -> None:
    """Record every text the element shows from now on (window.__texts)."""
    dash.evaluate(
        """sel => {
          const node = document.querySelector(sel);
          window.__texts = [node.textContent];
          new MutationObserver(() => window.__texts.push(node.textContent))
            .observe(node, {childList: true, characterData: true, subtree: true});
        }""",
        selector,
    )


# ---------------------------------------------------------------------- live view


def test_page_loads_and_streamed_frames_are_drawn(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, artifacts: Path
) -> None:
    dash = open_dashboard()
    # the canvas and the id of the frame on it, read together: the first frame may already
    # be drawn by now, and only a canvas without one shows what "blank" looks like
    shown = dash.evaluate(
        f"""() => ({{pixels: ({SNAPSHOT_JS})(),
                    frame: Number(document.getElementById('viewport').dataset.frame ?? -1)}})"""
    )
    if shown["frame"] < 0:
        blank = np.asarray(shown["pixels"], dtype=np.float64)
        assert blank.std() < 1.0, "before any frame the canvas is empty"
    first = wait_for_frame(dash)
    image = snapshot(dash)
    assert image.std() > 5.0, "the molecule is not visible on the canvas"
    later = wait_for_frame(dash, first)
    assert later > first, "frames keep arriving as the simulation runs"
    wait_for_full_view(dash)
    page = dash.page
    expect(page.locator("#view-placeholder")).to_be_hidden()
    expect(page.locator("#role-badge")).to_have_text("steerer")
    expect(page.locator("#sim-state")).to_have_text("running")
    # the canvas holds device pixels of its box, and that is the size the server was asked for
    size = dash.evaluate("() => [view.width, view.height, view.clientWidth, view.clientHeight]")
    assert size[0] == size[2] and size[1] == size[3]
    page.screenshot(path=str(artifacts / "dashboard.png"))


def test_sigma_slider_changes_the_received_image(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    wait_for_full_view(dash)
    before = snapshot(dash)
    slider = dash.page.locator("#sigma-slider")
    slider.focus()
    slider.press("End")  # keyboard-operable: the top of the log scale, 12 A
    expect(dash.page.locator("#sigma-number")).to_have_value("12")
    wait_until(lambda: session(live_server).render_params.sigma_A == 12.0, "the server took sigma")
    wait_for_new_image(dash, before, threshold=6.0)
    # the numeric field steers too
    dash.page.fill("#sigma-number", "0.8")
    dash.page.press("#sigma-number", "Enter")
    wait_until(lambda: session(live_server).render_params.sigma_A == 0.8, "sigma 0.8 arrived")
    wait_until(lambda: "sigma=0.8" in dash.evaluate("() => location.hash"), "the URL names it")
    # a number outside the field's range is not sent (it was quietly moved to the nearest end,
    # 1e400 to 12 A, or left in the field unsent): the page says so and shows the value in effect
    for typed, said in (
        ("-3", "σ -3 is outside 0.3–12 Å; not sent"),
        ("0", "σ 0 is outside 0.3–12 Å; not sent"),
        ("1e400", "σ must be a number from 0.3 to 12 Å; not sent"),  # the input reads no number
    ):
        dash.page.fill("#sigma-number", typed)
        dash.page.press("#sigma-number", "Enter")
        expect(dash.page.locator("#notices")).to_contain_text(said)
        expect(dash.page.locator("#sigma-number")).to_have_value("0.8")
    dash.page.fill("#iso-number", "0")
    dash.page.press("#iso-number", "Enter")
    expect(dash.page.locator("#notices")).to_contain_text("iso level 0 is outside 0.01–100")
    expect(dash.page.locator("#iso-number")).to_have_value("0.25")
    assert session(live_server).render_params.sigma_A == 0.8
    assert session(live_server).render_params.iso_level == 0.25


def test_a_field_with_the_focus_shows_another_steerers_change_when_the_focus_leaves(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    """A number field is not overwritten while it has the focus (it may be half typed); a
    change another steerer made meanwhile shows once the focus leaves it."""
    first = open_dashboard()
    wait_for_full_view(first)
    page = first.page
    other = open_dashboard().page
    page.locator("#sigma-number").focus()
    other.fill("#sigma-number", "2.4")
    other.press("#sigma-number", "Enter")
    wait_until(lambda: session(live_server).render_params.sigma_A == 2.4, "sigma 2.4 arrived")
    page.wait_for_timeout(1000)  # its state has reached the first page by now
    expect(page.locator("#sigma-number")).not_to_have_value("2.4")
    page.locator("#btn-reset-view").focus()
    expect(page.locator("#sigma-number")).to_have_value("2.4")


def test_the_geodesic_and_carved_scale_spaces_are_one_click_away(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    wait_for_full_view(dash)
    page = dash.page
    strength = page.locator("#warp-strength")
    rounding = page.locator("#geodesic-smoothing")
    expect(strength).to_be_disabled()  # classical: neither applies
    expect(rounding).to_be_disabled()
    expect(page.locator("#space-help")).to_contain_text("through the bonds")
    before = snapshot(dash)
    page.locator('input[name="scale-space"][value="geodesic"]').check()
    wait_until(lambda: session(live_server).render_params.scale_space == "geodesic", "geodesic")
    expect(strength).to_be_enabled()
    expect(rounding).to_be_enabled()

    def changed_from(image: np.ndarray, timeout: float) -> np.ndarray:
        def differs() -> list[np.ndarray]:
            wait_for_frame(dash, frame_id(dash) - 1)
            now = snapshot(dash)
            return [now] if np.abs(now - image).mean() > 4.0 else []

        result: np.ndarray = wait_until(differs, "the image changed", timeout)[0]
        return result

    # the first geodesic frame compiles its kernels (once per machine: warp caches them)
    geodesic = changed_from(before, 240.0)
    rounding.focus()
    # the sharpest rounding, the thesis's own creases (the smoothest, 2, renders this canvas
    # in about 45 s on two CPU cores with the test server's frame budget off)
    rounding.press("Home")
    wait_until(lambda: session(live_server).render_params.geodesic_smoothing == 0.05, "0.05")
    sharp = changed_from(geodesic, 60.0)
    page.locator('input[name="scale-space"][value="carved"]').check()
    wait_until(lambda: session(live_server).render_params.scale_space == "carved", "carved")
    expect(rounding).to_be_disabled()
    expect(strength).to_be_enabled()
    carved = changed_from(sharp, 120.0)
    strength.focus()
    strength.press("Home")  # strength 0: the classical density again
    wait_until(lambda: session(live_server).render_params.warp_strength == 0.0, "strength 0")
    changed_from(carved, 60.0)
    wait_until(lambda: "space=carved" in dash.evaluate("() => location.hash"), "URL keeps it")


def test_dragging_rotates_the_view(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    wait_for_full_view(dash)
    before = snapshot(dash)
    q0 = dash.evaluate("() => window.scalesteer.camera.orientation")
    cx, cy = view_centre(dash)
    mouse = dash.page.mouse
    mouse.move(cx - 120, cy)
    mouse.down()
    mouse.move(cx, cy + 20, steps=8)
    mouse.move(cx + 120, cy + 40, steps=8)
    mouse.up()
    q1 = dash.evaluate("() => window.scalesteer.camera.orientation")
    assert np.abs(np.subtract(q0, q1)).max() > 0.1, "the camera did not turn"
    wait_for_new_image(dash, before, threshold=4.0)
    wait_until(lambda: "cam=" in dash.evaluate("() => location.hash"), "the camera is in the URL")


def test_clicking_an_atom_shows_its_details(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    wait_for_full_view(dash)
    x, y = front_atom_on_page(dash, live_server)
    dash.page.mouse.click(x, y)
    page = dash.page
    expect(page.locator("#pick-atom")).to_have_text(re.compile(r"^index \d+$"))
    expect(page.locator("#pick-element")).to_have_text(re.compile(r"^[A-Z][a-z]?$"))
    expect(page.locator("#pick-name")).not_to_have_text("–")
    expect(page.locator("#pick-residue")).to_have_text(re.compile(r"^\S+ -?\d+$"))
    expect(page.locator("#pick-position")).to_have_text(
        re.compile(r"^\(-?[\d.]+, -?[\d.]+, -?[\d.]+\) Å$")
    )
    # the details are those of the atom index the server named
    index = int(page.locator("#pick-atom").text_content().split()[1])
    topo = session(live_server).topology
    assert page.locator("#pick-element").text_content() == topo.elements[index]
    assert page.locator("#pick-name").text_content() == topo.names[index]
    assert page.locator("#pick-chain").text_content() == (topo.chain_ids[index] or "–")
    # clicking the background clears it; Escape clears the selection too
    box = page.locator("#view").bounding_box()
    assert box is not None
    page.mouse.click(box["x"] + 3, box["y"] + 3)
    expect(page.locator("#pick-atom")).to_have_text("background (no atom here)")
    page.keyboard.press("Escape")
    expect(page.locator("#pick-atom")).to_have_text("click an atom")


def test_ctrl_drag_pulls_an_atom_and_release_stops_the_force(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    # paused, so the atom stays where it was picked: the spring's plane goes through the atom
    # as it is when each pull is sent (the dashboard follows a moving atom)
    expect(page.locator("#sim-state")).to_have_text("running")
    page.click("#sim-play")
    expect(page.locator("#sim-state")).to_have_text("paused")
    wait_for_full_view(dash)
    x, y = front_atom_on_page(dash, live_server)
    page.keyboard.down("Control")
    page.mouse.move(x, y)
    page.mouse.down()
    expect(page.locator("#pull-hint")).to_be_visible()
    page.mouse.move(x + 80, y - 30, steps=6)
    pulls = wait_until(lambda: dict(session(live_server).forces.pulls), "the server holds the pull")
    (atom, (_owner, pull)), *_ = pulls.items()
    target = np.asarray(pull.target)
    picked = np.asarray(
        [float(v) for v in page.locator("#pick-position").text_content()[1:-3].split(",")]
    )
    assert np.linalg.norm(target - picked) > 1.0, "the spring pulls away from the atom"
    # the target lies in the plane through the atom parallel to the view
    back = np.asarray(dash.evaluate("() => window.scalesteer.camera.orientation"))
    w, qx, qy, qz = back
    normal = np.array([2 * (qx * qz + w * qy), 2 * (qy * qz - w * qx), 1 - 2 * (qx * qx + qy * qy)])
    assert abs(float(np.dot(target - picked, normal))) < 0.05
    arrow = dash.evaluate(
        """() => { const o = document.getElementById('overlay');
          const d = o.getContext('2d').getImageData(0, 0, o.width, o.height).data;
          let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }"""
    )
    assert arrow > 50, "the pull arrow is drawn"
    expect(page.locator("#pulling-list")).to_contain_text(f"atom {atom}")
    page.mouse.up()
    page.keyboard.up("Control")
    expect(page.locator("#pull-hint")).to_be_hidden()
    wait_until(lambda: not session(live_server).forces.pulls, "the pull was released")
    expect(page.locator("#pulling-list")).to_have_text("no active pulls")


# ---------------------------------------------------------------------- simulation steering


def test_temperature_change_is_pending_until_acknowledged_with_its_step(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    page = dash.page
    expect(page.locator("#sim-state")).to_have_text("running")
    record_text(dash, "#ack-temperature_K")
    page.fill("#sim-temperature", "350")
    page.press("#sim-temperature", "Enter")
    expect(page.locator("#ack-temperature_K")).to_have_text(re.compile(r"^applied at step [\d,]+"))
    texts = dash.evaluate("() => window.__texts")
    assert "pending…" in texts, texts
    assert texts.index("pending…") < len(texts) - 1
    step = int(page.locator("#ack-temperature_K").text_content().split()[3].replace(",", ""))
    assert step > 0
    # a value outside the engine's range is not sent: the field shows the value in effect again
    # and its line says so (it had kept the refused value over the old "applied at step")
    page.fill("#sim-temperature", "5000")
    page.press("#sim-temperature", "Enter")
    expect(page.locator("#ack-temperature_K")).to_have_text("5000 not sent: outside the range")
    expect(page.locator("#sim-temperature")).to_have_value("350")
    expect(page.locator("#notices")).to_contain_text("outside")
    # refused while another value is on its way: the field shows that value, not the older one
    # the session still holds
    page.fill("#sim-temperature", "300")
    page.press("#sim-temperature", "Enter")
    page.fill("#sim-temperature", "5000")
    page.press("#sim-temperature", "Enter")
    expect(page.locator("#sim-temperature")).to_have_value("300")
    expect(page.locator("#ack-temperature_K")).to_have_text(re.compile(r"^applied at step [\d,]+"))
    expect(page.locator("#sim-temperature")).to_have_value("300")
    # run control: pause, then resume, each acknowledged
    record_text(dash, "#ack-control")
    page.click("#sim-play")
    expect(page.locator("#ack-control")).to_have_text(re.compile(r"^pause: applied at step"))
    expect(page.locator("#sim-state")).to_have_text("paused")
    expect(page.locator("#sim-play")).to_have_text("Resume")
    assert any("pending" in t for t in dash.evaluate("() => window.__texts"))
    page.click("#sim-play")
    expect(page.locator("#ack-control")).to_have_text(re.compile(r"^resume: applied at step"))
    expect(page.locator("#sim-state")).to_have_text("running")


def test_killing_the_simulation_shows_disconnected_and_it_recovers(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    page = dash.page
    first = wait_for_frame(dash)
    simulation.stop()
    expect(page.locator("#sim-state")).to_have_text("disconnected")
    expect(page.locator("#sim-play")).to_be_disabled()
    # steering without a simulation: a readable notice with the server's code and message
    page.fill("#sim-temperature", "310")
    page.press("#sim-temperature", "Enter")
    expect(page.locator("#ack-temperature_K")).to_contain_text("failed: not_ready")
    notice = page.locator('.notice[data-code="not_ready"]')
    expect(notice).to_be_visible()
    expect(notice).to_contain_text("no simulation is connected")
    simulation.start()
    expect(page.locator("#sim-state")).to_have_text("running")
    wait_for_frame(dash, first + 1)


def test_viewer_page_has_steering_disabled_with_a_reason(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard("viewer")
    page = dash.page
    expect(page.locator("#role-badge")).to_have_text("viewer (read-only)")
    for selector in (
        "#sigma-slider",
        "#sigma-number",
        "#iso-slider",
        "#color-by",
        "#sim-temperature",
        "#sim-play",
        "#tf-add",
        "#pull-k",
    ):
        expect(page.locator(selector)).to_be_disabled()
    reason = page.locator("#render-reason")
    expect(reason).to_be_visible()
    expect(reason).to_contain_text("Read-only")
    expect(page.locator("#tf-editor")).to_have_attribute("aria-disabled", "true")
    # viewing still works: images arrive and the camera turns
    wait_for_frame(dash)
    expect(page.locator("#btn-reset-view")).to_be_enabled()
    # the session lists both the simulation and this viewer
    expect(page.locator("#clients li[data-role=simulation]")).to_have_count(1)
    expect(page.locator("#clients li[data-role=viewer] .you")).to_have_count(1)


def test_steerer_link_with_a_viewer_token_falls_back_to_viewing(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard("steerer-with-viewer-token")
    page = dash.page
    expect(page.locator("#role-badge")).to_have_text("viewer (read-only)")
    # the server says why: the viewer token is read-only (it had said "wrong token")
    notice = page.locator('.notice[data-code="forbidden"]').first
    expect(notice).to_contain_text("viewer token is read-only")
    expect(page.locator("#sigma-slider")).to_be_disabled()
    wait_for_frame(dash)


# ---------------------------------------------------------------------- render controls


def test_transfer_function_editor_steers_the_session(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    from server.render.transfer import PRESETS

    dash = open_dashboard()
    page = dash.page
    # the editor shows the server's presets exactly
    presets = dash.evaluate("() => import('./src/transfer.js').then(m => m.PRESETS)")
    for name, rows in PRESETS.items():
        assert [(p["x"], tuple(p["color"]), p["alpha"]) for p in presets[name]] == [
            (x, tuple(c), a) for x, c, a in rows
        ], name
    expect(page.locator("#color-by")).to_be_enabled()
    page.locator("label", has_text="Volume").click()
    wait_until(lambda: session(live_server).render_params.mode == "volume", "volume mode")
    # volume draws the transfer function's colours: the legend says so, Colour by rests
    expect(page.locator("#legend")).to_contain_text("Transfer function")
    expect(page.locator("#color-by")).to_be_disabled()
    points = page.locator("#tf-editor circle.point")
    expect(points).to_have_count(len(PRESETS["cloud"]))
    page.locator("#tf-editor").scroll_into_view_if_needed()
    # the editor redraws its points when the session's state arrives: take a settled one
    box = wait_until(lambda: points.nth(3).bounding_box(), "the fourth point on screen")
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x, y - 40, steps=5)
    page.mouse.up()

    def dragged() -> bool:
        tf = session(live_server).render_params.transfer_function
        return len(tf) == len(PRESETS["cloud"]) and tf[3].alpha > PRESETS["cloud"][3][2] + 0.1

    wait_until(dragged, "the dragged opacity reached the server")
    # keyboard: next point, raise it, add one, colour it
    editor = page.locator("#tf-editor")
    editor.focus()
    editor.press("PageDown")
    expect(page.locator("#tf-selected")).to_contain_text("point 5/6")
    editor.press("Insert")
    wait_until(
        lambda: len(session(live_server).render_params.transfer_function) == 7, "a point added"
    )
    page.locator("#tf-color").fill("#ff0000")
    wait_until(
        lambda: any(
            p.color == (1.0, 0.0, 0.0) for p in session(live_server).render_params.transfer_function
        ),
        "the colour reached the server",
    )
    # the density histogram of a still image is drawn behind the curve
    expect(page.locator("#tf-editor rect.hist").first).to_be_attached(timeout=60_000)
    page.locator("#tf-preset").select_option("shells")
    wait_until(
        lambda: (
            session(live_server).render_params.tf_preset == "shells"
            and not session(live_server).render_params.transfer_function
        ),
        "the preset replaced the points",
    )
    expect(points).to_have_count(len(PRESETS["shells"]))


def test_shared_link_sets_render_params_and_camera(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    first = open_dashboard(hash="#v=1&sigma=3.2&color=chain&bg=ffffff")
    wait_until(
        lambda: (
            session(live_server).render_params.sigma_A == 3.2
            and session(live_server).render_params.color_by == "chain"
        ),
        "the link's render params reached the session",
    )
    expect(first.page.locator("#sigma-number")).to_have_value("3.2")
    expect(first.page.locator("#color-by")).to_have_value("chain")
    first.page.keyboard.press("o")  # orthographic, through the shortcut
    expect(first.page.locator("#btn-projection")).to_have_attribute("aria-pressed", "true")
    wait_until(lambda: "proj=o" in first.evaluate("() => location.hash"), "the hash names it")
    time.sleep(0.4)  # the hash is written at most every 300 ms
    shared = first.evaluate("() => location.hash")
    camera = first.evaluate("() => window.scalesteer.camera")
    second = open_dashboard("viewer", hash=shared)
    got = second.evaluate("() => window.scalesteer.camera")
    assert got["projection"] == "orthographic"
    assert np.allclose(got["orientation"], camera["orientation"], atol=1e-4)
    assert np.allclose(got["target"], camera["target"], atol=1e-3)
    expect(second.page.locator("#sigma-number")).to_have_value("3.2")


def test_screenshot_downloads_a_full_resolution_png(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation
) -> None:
    dash = open_dashboard()
    wait_for_frame(dash)
    page = dash.page
    page.select_option("#resolution", "0.5")
    wait_until(
        lambda: (
            page.locator("#viewport").get_attribute("data-image-size")
            == "{}x{}".format(*dash.evaluate("() => [view.width, view.height]"))
        ),
        "half-resolution images",
    )
    full = dash.evaluate("() => window.scalesteer.viewport.fullSize()")
    with page.expect_download(timeout=120_000) as info:
        page.click("#btn-screenshot")
    download = info.value
    assert download.suggested_filename.endswith(".png")
    data = Path(download.path()).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    image = Image.open(io.BytesIO(data))
    assert list(image.size) == full
    assert np.asarray(image.convert("L")).std() > 5.0


# ---------------------------------------------------------------------- plots, session, layout


def test_plots_receive_points_and_export_csv(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page

    def points(plot: str) -> int:
        return int(page.locator(f"#{plot}").get_attribute("data-points") or 0)

    reported = session(live_server).status.observables
    wait_until(
        lambda: (
            points("plot-fps") >= 2
            and points("plot-latency") >= 1
            and (points("plot-temperature") >= 3 or "temperature_K" not in reported)
            and (points("plot-energy") >= 3 or "potential_kJmol" not in reported)
        ),
        "every plot has points",
    )
    with page.expect_download() as info:
        page.click("#btn-export-csv")
    rows = list(csv.reader(io.StringIO(Path(info.value.path()).read_text())))
    assert rows[0] == [
        "time_unix_s",
        "temperature_K",
        "target_temperature_K",
        "potential_kJmol",
        "render_fps",
        "shown_fps",
        "latency_ms",
    ]
    if "temperature_K" in reported:
        expect(page.locator("#plot-temperature .plot-last")).to_have_text(re.compile(r"^[\d.]+ K$"))
        temperatures = [float(r[1]) for r in rows[1:] if r[1]]
        assert len(temperatures) >= 3 and all(t > 0 for t in temperatures)
    latencies = [float(r[6]) for r in rows[1:] if r[6]]
    assert latencies and all(v >= 0 for v in latencies)


def test_help_overlay_and_keyboard_operation(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    dash = open_dashboard()
    page = dash.page
    page.keyboard.press("?")
    dialog = page.locator("#help-dialog")
    expect(dialog).to_be_visible()
    expect(dialog.locator("tbody tr").first).to_be_visible()
    assert dialog.locator("tbody tr").count() >= 10
    page.keyboard.press("Escape")
    expect(dialog).to_be_hidden()
    # shortcuts steer: larger sigma, volume mode
    before = session(live_server).render_params.sigma_A
    page.keyboard.press("]")
    wait_until(lambda: session(live_server).render_params.sigma_A > before, "] raised sigma")
    page.keyboard.press("m")
    wait_until(lambda: session(live_server).render_params.mode == "volume", "m switched mode")
    # the view is focusable and turns with the arrow keys
    wait_for_frame(dash)
    q0 = dash.evaluate("() => window.scalesteer.camera.orientation")
    page.locator("#view").focus()
    page.keyboard.press("ArrowRight")
    q1 = dash.evaluate("() => window.scalesteer.camera.orientation")
    assert np.abs(np.subtract(q0, q1)).max() > 0.05
    # every form control has an accessible name
    unnamed = dash.evaluate(
        """() => [...document.querySelectorAll('input, select, button, [role=application]')]
          .filter(n => !(n.labels && n.labels.length) && !n.getAttribute('aria-label')
            && !n.getAttribute('aria-labelledby') && !n.textContent.trim() && !n.title)
          .map(n => n.id || n.outerHTML.slice(0, 60))"""
    )
    assert unnamed == []


def test_page_reconnects_after_a_server_restart(
    open_dashboard: OpenDashboard, simulation: OpenMMSimulation, live_server: LiveServer
) -> None:
    # while the server is down the browser logs the page's failed requests (its WebSocket, and
    # the Session panel's poll of what runs on the server) as console errors
    dash = open_dashboard(
        allow=(
            r"WebSocket connection to .* failed",
            r"Failed to load resource: net::ERR_CONNECTION_REFUSED",
        )
    )
    page = dash.page
    wait_for_frame(dash)
    simulation.stop()
    restarted = live_server.restart()
    try:
        expect(page.locator("#conn-text")).to_have_text("connected", timeout=60_000)
        expect(page.locator('.notice[data-code="connection"]').first).to_be_attached()
        simulation.url = restarted.ws_url
        simulation.start()
        expect(page.locator("#sim-state")).to_have_text("running")
        wait_for_frame(dash)
    finally:
        simulation.stop()
        restarted.stop()


@pytest.mark.parametrize("size", [(1280, 800), (800, 900)], ids=["1280x800", "800-wide"])
def test_layout_has_no_overlapping_controls(
    open_dashboard: OpenDashboard,
    simulation: OpenMMSimulation,
    artifacts: Path,
    size: tuple[int, int],
) -> None:
    dash = open_dashboard(size=size)
    wait_for_full_view(dash)
    dash.page.screenshot(path=str(artifacts / f"dashboard-{size[0]}.png"))
    dash.evaluate("() => document.querySelectorAll('details').forEach(d => d.open = true)")
    overlaps = dash.evaluate(
        """() => {
          const sel = 'input, select, button, label, summary, output, .plot, #view, #tf-editor, '
            + '.status-grid dt, .status-grid dd, .param-grid .unit, .ack, h1, .badge';
          const nodes = [...document.querySelectorAll(sel)].filter(n => {
            const r = n.getBoundingClientRect();
            return r.width > 0 && r.height > 0 && getComputedStyle(n).visibility !== 'hidden';
          });
          const out = [];
          for (let i = 0; i < nodes.length; i++) {
            for (let j = i + 1; j < nodes.length; j++) {
              const a = nodes[i], b = nodes[j];
              if (a.contains(b) || b.contains(a)) continue;
              const r = a.getBoundingClientRect(), s = b.getBoundingClientRect();
              const w = Math.min(r.right, s.right) - Math.max(r.left, s.left);
              const h = Math.min(r.bottom, s.bottom) - Math.max(r.top, s.top);
              const name = (n) => n.id || n.outerHTML.slice(0, 50);
              if (w > 1 && h > 1) out.push([name(a), name(b)]);
            }
          }
          return out;
        }"""
    )
    assert overlaps == []
    scroll_width = dash.evaluate("() => document.documentElement.scrollWidth")
    assert scroll_width <= size[0], "the page scrolls sideways"
