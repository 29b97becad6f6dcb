"""The notebook widget as a user sees it: a real JupyterLab in Debian's Chromium, the kernel's
own server, a system of `--atoms` atoms replayed in a loop.

Measured by the page (the widget's canvas, `performance.now()`):

    first_picture_s   the cell `client.open(system).view()` asked to run -> its first picture
                      drawn (the server already running, as it is from a notebook's second
                      cell on), median of `--repeats` cells
    cold_s            the same for the three-line start in a fresh kernel: the cell that also
                      starts the server (`scalesteer.show(system)`)
    widget_fps        pictures the widget drew per second while the trajectory plays
    forwarded_fps     the control of widget_fps, in the same window: pictures the kernel
                      forwarded to the page (what the server sent the widget's link)
    dashboard_fps     the second control, in the same run: the browser dashboard on the same
                      session in the same Chromium (pictures straight from the server there,
                      through the kernel in the widget; its canvas is the dashboard's own, its
                      image size recorded); ratio = widget / dashboard

The system: copies of adenylate kinase (PSF/DCD of MDAnalysisTests, 3,341 atoms, its first
`--frames` frames) on a lattice, cut to `--atoms` atoms.

    python benchmarks/widget_bench.py --atoms 10000 --device cpu       # a 2-core CPU machine
    python benchmarks/widget_bench.py --atoms 1000000 --device cuda:0 --size 1280x720
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from tests.browser.conftest import CHROMIUM, CHROMIUM_ARGS
from tests.browser.jupyter import JupyterLab, open_notebook, run_cell, write_notebook

RESULTS = ROOT / "benchmarks" / "results"

SYSTEM = """
import warnings
import numpy as np
import MDAnalysis as mda
from MDAnalysis.coordinates.memory import MemoryReader
from MDAnalysisTests.datafiles import DCD, PSF


def lattice_system(n_atoms, n_frames):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        adk = mda.Universe(PSF, DCD)
        frames = np.stack([ts.positions.copy() for ts in adk.trajectory[:n_frames]])
    frames -= frames.mean(axis=(0, 1))
    copies = -(-n_atoms // adk.atoms.n_atoms)
    side = int(np.ceil(copies ** (1 / 3)))
    offsets = [(i, j, k) for i in range(side) for j in range(side) for k in range(side)][:copies]
    spacing = 50.0
    coords = np.concatenate([frames + spacing * np.asarray(o) for o in offsets], axis=1)
    merged = mda.Merge(*[adk.atoms] * copies)
    merged.load_new(coords.astype(np.float32), format=MemoryReader)
    return merged.atoms[:n_atoms]


system = lattice_system({atoms}, {frames})
"""


def page_time(page: Any) -> float:
    return float(page.evaluate("() => performance.now()"))


NEW_VIEW = ".scalesteer-view:not([data-old])"


def mark_old(page: Any) -> None:
    """Views on the page now are not the one the next cell makes."""
    page.evaluate(
        "() => document.querySelectorAll('.scalesteer-view').forEach(v => v.dataset.old = '1')"
    )


def widget_data(page: Any) -> dict[str, str]:
    """The newest view's data (see `mark_old`)."""
    data: dict[str, str] = page.evaluate(
        "(s) => ({...(document.querySelector(s)?.dataset ?? {})})", NEW_VIEW
    )
    return data


def wait_first_picture(page: Any, timeout_ms: int = 600_000) -> float:
    """The page clock when the newest view drew its first picture."""
    page.wait_for_function(
        "(s) => document.querySelector(s)?.dataset.firstFrameAt",
        arg=NEW_VIEW,
        timeout=timeout_ms,
        polling=20,
    )
    return float(widget_data(page)["firstFrameAt"])


def wait_idle(page: Any) -> None:
    page.wait_for_function(
        "() => window.jupyterapp.shell.currentWidget.sessionContext.session.kernel.status"
        " === 'idle'",
        timeout=600_000,
        polling=100,
    )


def shown_rate(page: Any, read_frames: str, seconds: float) -> float:
    """Pictures drawn per second over `seconds`, from a counter the page keeps."""
    start, t0 = int(page.evaluate(read_frames) or 0), time.monotonic()
    time.sleep(seconds)
    end = int(page.evaluate(read_frames) or 0)
    return (end - start) / (time.monotonic() - t0)


COUNT_DRAWS = """() => {
  window.drawnPictures = 0;
  const viewport = document.getElementById('viewport');
  new MutationObserver(() => { window.drawnPictures += 1; })
    .observe(viewport, { attributes: true, attributeFilter: ['data-frame'] });
}"""


def printed(page: Any, marker: str) -> str:
    """The last line of the cell output that holds `marker` (waiting for it)."""
    page.wait_for_function(
        "(m) => [...document.querySelectorAll('.jp-OutputArea-output')]"
        ".some(o => o.textContent.includes(m))",
        arg=marker,
        timeout=120_000,
    )
    text: str = page.locator(".jp-OutputArea-output", has_text=marker).last.inner_text()
    return text.strip().splitlines()[-1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--atoms", type=int, default=10_000)
    ap.add_argument("--frames", type=int, default=20, help="trajectory frames, played in a loop")
    ap.add_argument("--fps", type=float, default=30.0, help="replay speed (frames per second)")
    ap.add_argument("--device", default="cpu", help="the server's device: cpu, cuda:0, auto")
    ap.add_argument("--size", default="640x480", help="the widget's canvas")
    ap.add_argument("--seconds", type=float, default=10.0, help="frame-rate window")
    ap.add_argument("--repeats", type=int, default=3, help="first-picture cells in the warm kernel")
    ap.add_argument("--out", type=Path, help="JSON results (default: results/widget_<device>.json)")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    system = SYSTEM.format(atoms=args.atoms, frames=args.frames)
    opened = f"view = client.open(system, fps={args.fps}, loop=True).view({width}, {height})\nview"
    from playwright.sync_api import sync_playwright

    out: dict[str, Any] = {
        "atoms": args.atoms,
        "device": args.device,
        "size": [width, height],
        "replay_fps": args.fps,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        # the machine is shared: its load (1-minute average) as the run starts and ends
        "load_average": [os.getloadavg()[0]],
    }
    with tempfile.TemporaryDirectory(prefix="widget-bench-") as tmp:
        root = Path(tmp)
        write_notebook(
            root / "warm.ipynb",
            [
                system + f"import scalesteer\nclient = scalesteer.connect(device={args.device!r})",
                *[opened, "view.session.close()"] * (args.repeats - 1),
                opened,
                "import time\n"
                "a, t = view.images_sent, time.monotonic()\n"
                f"time.sleep({args.seconds})\n"
                "print('forwarded', (view.images_sent - a) / (time.monotonic() - t))",
                "print(client.dashboard_url(view.session.name))",
            ],
        )
        write_notebook(
            root / "cold.ipynb",
            [
                system,
                "import scalesteer\n"
                f"view = scalesteer.show(system, {width}, {height}, device={args.device!r},"
                f" fps={args.fps}, loop=True)\nview",
                "view.session.client.close()\nscalesteer.shutdown()\nprint('stopped')",
            ],
        )
        lab = JupyterLab(root)
        try:
            with sync_playwright() as pw:
                browser = pw.chromium.launch(
                    executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
                )
                cold = open_notebook(browser, lab, "cold.ipynb", (width + 600, height + 700))
                run_cell(cold, 0)
                wait_idle(cold)
                asked = run_cell(cold, 1)
                out["cold_s"] = (wait_first_picture(cold) - asked) / 1000
                run_cell(cold, 2)  # its server ends: the warm runs have the machine
                printed(cold, "stopped")
                cold.close()
                page = open_notebook(browser, lab, "warm.ipynb", (width + 600, height + 700))
                run_cell(page, 0)
                wait_idle(page)
                firsts = []
                for i in range(args.repeats):
                    mark_old(page)
                    asked = run_cell(page, 1 + 2 * i)
                    firsts.append((wait_first_picture(page) - asked) / 1000)
                    wait_idle(page)
                    if i < args.repeats - 1:  # its session closes before the next one opens
                        run_cell(page, 2 + 2 * i)
                        wait_idle(page)
                out["first_picture_s"] = statistics.median(firsts)
                out["first_picture_runs_s"] = firsts
                time.sleep(2.0)  # past the first pictures' start-up
                measure = 2 * args.repeats
                run_cell(page, measure)  # the kernel counts what it forwards meanwhile
                out["widget_fps"] = shown_rate(
                    page, f"() => document.querySelector('{NEW_VIEW}').dataset.frames", args.seconds
                )
                out["forwarded_fps"] = float(printed(page, "forwarded").split()[-1])
                out["widget_format"] = widget_data(page).get("format")
                out["widget_image_size"] = widget_data(page).get("imageSize")
                run_cell(page, measure + 1)
                link = printed(page, "?session=")
                page.close()
                dash = browser.new_context(viewport={"width": width + 400, "height": height + 200})
                board = dash.new_page()
                board.goto(link)
                board.wait_for_function(
                    "() => Number(document.getElementById('viewport')?.dataset.frame ?? -1) >= 0",
                    timeout=120_000,
                )
                board.evaluate(COUNT_DRAWS)
                time.sleep(2.0)
                out["dashboard_fps"] = shown_rate(board, "() => window.drawnPictures", args.seconds)
                out["dashboard_image_size"] = board.evaluate(
                    "() => document.getElementById('viewport').dataset.imageSize"
                )
                dash.close()
                out["ratio_widget_dashboard"] = (
                    out["widget_fps"] / out["dashboard_fps"] if out["dashboard_fps"] else None
                )
                browser.close()
        finally:
            lab.stop()
    out["load_average"].append(os.getloadavg()[0])
    target = args.out or RESULTS / f"widget_{args.device.replace(':', '')}.json"
    target.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
