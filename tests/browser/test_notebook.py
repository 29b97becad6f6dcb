"""The widget in a real JupyterLab, driven through Debian's Chromium: a notebook makes a live
view of the MDAnalysisTests GRO/XTC universe in three lines (a server of the kernel's own), steers
sigma from Python and sees the picture change, orbits and picks with the mouse, shows a second
widget of the same session, and after a kernel restart says so, its server gone, while running
the cell again brings a live view back."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.browser.jupyter import (
    KERNEL_IDLE,
    RESTART,
    JupyterLab,
    open_notebook,
    run_cell,
    write_notebook,
)
from tests.server.processes import wait_gone

pytestmark = pytest.mark.browser

CELLS = [
    # the README's three-line start
    "import scalesteer, MDAnalysis as mda\n"
    "from MDAnalysisTests.datafiles import GRO, XTC\n"
    "view = scalesteer.show(mda.Universe(GRO, XTC), 320, 240)\n"
    "view",
    "view.sigma = 4.0",
    "second = view.session.view(200, 150)\nsecond",
    "import json, os\n"
    "print(json.dumps({'sigma': second.sigma, 'camera': view.camera is not None,\n"
    "                  'picked': view.picked.get('atom'),\n"
    "                  'server': view.session.client.local.process.pid}))",
]
SNAPSHOT = """(index) => {
  const canvas = document.querySelectorAll('.scalesteer-canvas')[index];
  const small = document.createElement('canvas');
  small.width = 64; small.height = 48;
  const g = small.getContext('2d');
  g.drawImage(canvas, 0, 0, 64, 48);
  const px = g.getImageData(0, 0, 64, 48).data;
  const grey = [];
  for (let i = 0; i < px.length; i += 4) grey.push((px[i] + px[i + 1] + px[i + 2]) / 3);
  return grey;
}"""
VIEW = "(index) => ({...(document.querySelectorAll('.scalesteer-view')[index]?.dataset ?? {})})"


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[JupyterLab]:
    write_notebook(tmp_path / "view.ipynb", CELLS)
    server = JupyterLab(tmp_path)
    yield server
    server.stop()


def snapshot(page: Any, index: int = 0) -> np.ndarray:
    return np.asarray(page.evaluate(SNAPSHOT, index), dtype=np.float64)


def wait_still(page: Any, after: int = -1, index: int = 0) -> int:
    """Wait for a full-quality picture newer than frame `after` in widget `index`."""
    page.wait_for_function(
        """([after, index]) => {
          const v = document.querySelectorAll('.scalesteer-view')[index]?.dataset;
          return v && Number(v.frameId ?? -1) > after && v.still === 'true';
        }""",
        arg=[after, index],
        timeout=120_000,
        polling=100,
    )
    return int(page.evaluate(VIEW, index)["frameId"])


def wait_changed(
    page: Any, before: np.ndarray, after: int, seconds: float = 60.0
) -> tuple[int, np.ndarray]:
    """Full-quality pictures newer than frame `after` until one differs from `before` by more
    than 2 grey levels on average, or `seconds` pass; the last one seen. Under load a still
    picture rendered before the drag's last camera reached the server can come first: the
    camera's message may trail more than the one picture in flight."""
    deadline = time.monotonic() + seconds
    while True:
        after = wait_still(page, after)
        shown = snapshot(page)
        if np.abs(shown - before).mean() > 2 or time.monotonic() > deadline:
            return after, shown


def test_a_notebook_widget_streams_steers_and_survives_a_kernel_restart(
    lab: JupyterLab, chromium: Any, artifacts: Path
) -> None:
    page = open_notebook(chromium, lab, "view.ipynb")
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))

    run_cell(page, 0)
    wait_still(page)
    # the kernel says how its link is once a second (its first word may precede the view)
    page.wait_for_function(
        "() => document.querySelector('.scalesteer-view')?.dataset.status !== undefined",
        timeout=30_000,
    )
    shown = page.evaluate(VIEW, 0)
    assert shown.get("status") == "connected", (shown, errors)
    assert "h264" in shown["codecs"].split()
    before = snapshot(page)
    assert before.std() > 5, "the molecule is drawn"

    run_cell(page, 1)  # view.sigma = 4.0, from Python: the cell ends once the server took it
    page.wait_for_function(KERNEL_IDLE, timeout=60_000, polling=100)
    # a picture already on its way when the server took sigma may still come (frame ids grow
    # by one a picture, one render at a time): wait for a still after that one
    current = int(page.evaluate(VIEW, 0)["frameId"])
    steered = wait_still(page, current + 1)
    after = snapshot(page)
    # mean grey difference of the 64x48 snapshots (0-255): 1.99 to 5 seen; an unchanged
    # picture gives 0
    assert np.abs(after - before).mean() > 1, "a larger sigma draws a smoother, larger surface"

    box = page.locator(".scalesteer-canvas").first.bounding_box()
    assert box is not None
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(cx + 80, cy + 10, steps=6)
    page.mouse.up()
    turned, shown = wait_changed(page, after, steered)
    page.screenshot(path=str(artifacts / "notebook-widget-turned.png"))
    assert shown.std() > 5, f"the turned molecule is drawn: {page.evaluate(VIEW, 0)}"
    assert np.abs(shown - after).mean() > 2, "the drag turns the molecule"
    page.mouse.click(cx, cy)  # a pick in the middle of the molecule
    page.wait_for_function(
        "() => document.querySelector('.scalesteer-hud').textContent.includes('atom')",
        timeout=60_000,
    )

    run_cell(page, 2)  # a second widget of the same session
    wait_still(page, -1, index=1)
    assert turned >= 0
    run_cell(page, 3)
    page.wait_for_function(
        "() => [...document.querySelectorAll('.jp-OutputArea-output')]"
        ".some(o => o.textContent.includes('\"server\"'))",
        timeout=60_000,
    )
    printed = page.locator(".jp-OutputArea-output", has_text='"server"').inner_text()
    told = json.loads(printed.strip().splitlines()[-1])
    assert told["sigma"] == 4.0, "the second widget shows the session's sigma"
    assert told["camera"] and told["picked"] is not None

    assert not errors, errors
    page.evaluate(RESTART)
    page.wait_for_function(
        "() => [...document.querySelectorAll('.scalesteer-view')]"
        ".every(v => v.dataset.status === 'kernel-gone')",
        timeout=60_000,
    )
    assert wait_gone([told["server"]], timeout=30) == [], "the kernel's server ended with it"

    run_cell(page, 0)  # the same cell again: a new server, a new live view
    page.wait_for_function(
        "() => { const v = document.querySelector('.scalesteer-view').dataset;"
        " return v.status === 'connected' && Number(v.frames) >= 1; }",
        timeout=120_000,
    )
    # the dying kernel's last messages may reach JupyterLab after it dropped their widgets
    late = [e for e in errors if not e.startswith("Comm not found for comm id")]
    assert not late, late
