"""The CPU demo as a user sees it: `scalesteer demo` and the real dashboard in Chromium, on the
same cores.

Starts the demo exactly as `make demo` does on a machine without a GPU (a process of its own:
villin in OpenMM's CPU platform, the server on warp's CPU device), opens the dashboard in
Debian's Chromium (Playwright, headless, a 1240x739 view as on a laptop) and measures what the
page shows:

    shown/s        images the page drew per second, the simulation running, nobody touching it
    orbit/s        the same while the mouse orbits the camera (a drag round and round)
    steer          sigma changed with the keyboard ([ and ]) -> the first image drawn that
                   reflects it (the page's own steer-to-photon clock), p50 and p90
    orbit latency  a camera move -> the first image drawn with it, p50 and p90

and where the time goes, per image shown (the server's render and encode times, Chromium's
decode time, what the image took from the server to the screen) and per second of each phase
(the CPU each part takes, in cores, from /proc: the simulation, the renderer's thread, the
encoders, the server's event loop, Chromium's renderer and compositor processes), with the
simulation's steps per second. The machine's load average before and after is recorded: other
work on the same cores changes every figure.

    python benchmarks/cpu_demo_chromium.py                 # results/cpu_demo_chromium_2core.json
    python benchmarks/cpu_demo_chromium.py --baseline ../main   # that checkout's demo first
    python benchmarks/cpu_demo_chromium.py --transport jpeg     # the page asks for JPEG images
    python benchmarks/cpu_demo_chromium.py --demo-arg=--interval=100   # extra demo options

With `--baseline`, the other checkout's demo (its server and its dashboard) runs first in the
same invocation, under the same load, and the report gives this checkout's figures over it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]  # fmt: skip
VIEW = (1240, 739)
TOKEN = "bench"
HZ = os.sysconf("SC_CLK_TCK")

INSTRUMENT = """() => {
  const d = window.scalesteer;
  const rec = (window.__bench = { shown: [], acks: [], lat: [] });
  const drawn = d.drawn.bind(d);
  d.drawn = (m, t) => {
    rec.shown.push({ t, id: m.frame_id, step: m.step, format: m.format, w: m.width, h: m.height,
      still: m.still !== false, render: m.render_ms ?? null, encode: m.encode_ms ?? null,
      travel: m.server_time ? Date.now() - 1000 * m.server_time : null });
    drawn(m, t);
  };
  const ack = d.acknowledge.bind(d);
  d.acknowledge = (m, ms) => { rec.acks.push({ id: m.frame_id, decode: ms }); ack(m, ms); };
  const shown = d.latency.shown.bind(d.latency);
  d.latency.shown = (ref, t) => {
    const r = shown(ref, t);
    if (r) rec.lat.push({ kind: r.kind, ms: r.latency, t });
    return r;
  };
}"""


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _ticks(pid: int) -> dict[tuple[int, str], int]:
    """CPU ticks (user + system) of every thread of `pid`, by (tid, name)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            stat = (task / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        out[(int(task.name), name)] = int(fields[11]) + int(fields[12])
    return out


def _boost(pids: list[int], by: int, done: set[str]) -> None:
    """Lower the nice value of the scheduling groups (Linux autogroups: one per session) of
    `pids` by `by`, each group once: a process's own nice weighs only within its group, so on a
    shared machine the demo, its simulation and Chromium each compete group against group."""
    for pid in pids:
        try:
            group = Path(f"/proc/{pid}/autogroup")
            name, nice = group.read_text().split(" nice ")
            if name in done:
                continue
            group.write_text(str(max(-20, int(nice) - by)))
            done.add(name)
        except (OSError, ValueError):
            continue


def _child_part(cmdline: list[str]) -> str:
    line = " ".join(cmdline)
    if "server.supervisor" in line:
        return "supervisor"
    if "commands.villin" in line:
        return "simulation (its own process: OpenMM steps, reporting)"
    return "selection workers and file readers"


def _part(pid: int, tid: int, name: str) -> str:
    if name.startswith("gpu"):
        return "render (the GPU queue's thread)"
    if name.startswith("encode"):
        return "encode (JPEG / H.264 threads)"
    if name == "uvicorn":
        return "server event loop (WebSockets, sessions)"
    if tid == pid:
        return "simulation (the demo's main thread: OpenMM steps, reporting)"
    if name in ("python", "python3"):
        return "simulation (OpenMM's worker threads)"
    return f"server, other ({name})"


def _chromium_part(cmdline: list[str]) -> str:
    kind = next((a.split("=", 1)[1] for a in cmdline if a.startswith("--type=")), "browser")
    return {
        "renderer": "Chromium renderer (the page: JS, image decode, WebCodecs)",
        "gpu-process": "Chromium GPU process (compositing, software raster)",
        "utility": "Chromium utility processes (network, audio)",
    }.get(kind, "Chromium browser process")


class CpuMeter:
    """CPU seconds per part between `start()` and `stop()`, from /proc."""

    def __init__(self, demo_pid: int) -> None:
        self.demo_pid = demo_pid

    def _sample(self) -> dict[str, float]:
        import psutil

        parts: dict[str, float] = {}
        demo = psutil.Process(self.demo_pid)
        for (tid, name), ticks in _ticks(self.demo_pid).items():
            key = _part(self.demo_pid, tid, name)
            parts[key] = parts.get(key, 0.0) + ticks / HZ
        for child in demo.children(recursive=True):
            try:
                t = child.cpu_times()
                key = _child_part(child.cmdline())
            except psutil.Error:
                continue
            parts[key] = parts.get(key, 0.0) + t.user + t.system
        for proc in psutil.process_iter(["name", "cmdline"]):
            if "chrom" not in (proc.info["name"] or ""):
                continue
            try:
                t = proc.cpu_times()
            except psutil.Error:
                continue
            key = _chromium_part(proc.info["cmdline"] or [])
            parts[key] = parts.get(key, 0.0) + t.user + t.system
        return parts

    def start(self) -> None:
        self._t0, self._first = time.monotonic(), self._sample()

    def stop(self) -> dict[str, float]:
        last, seconds = self._sample(), time.monotonic() - self._t0
        used = {k: (v - self._first.get(k, 0.0)) / seconds for k, v in last.items()}
        return {k: round(v, 3) for k, v in sorted(used.items(), key=lambda kv: -kv[1]) if v > 0.005}


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def _stats(values: list[float]) -> dict[str, float | None]:
    clean = [v for v in values if v is not None]
    return {
        "p50": _pct(clean, 0.5),
        "p90": _pct(clean, 0.9),
        "mean": statistics.fmean(clean) if clean else None,
        "n": len(clean),
    }


def _phase(page: Any, meter: CpuMeter, seconds: float, act: Any = None) -> dict[str, Any]:
    """Run `act(deadline)` (or wait) for `seconds`; what the page drew meanwhile."""
    n0 = page.evaluate("() => [window.__bench.shown.length, window.__bench.acks.length, "
                       "window.__bench.lat.length]")  # fmt: skip
    meter.start()
    t0 = time.monotonic()
    if act is None:
        page.wait_for_timeout(seconds * 1000)
    else:
        act(t0 + seconds)
    elapsed = time.monotonic() - t0
    cpu = meter.stop()
    rec = page.evaluate(
        "([a, b, c]) => ({ shown: window.__bench.shown.slice(a),"
        " acks: window.__bench.acks.slice(b), lat: window.__bench.lat.slice(c),"
        " sim: window.scalesteer.sim, stats: window.scalesteer.stats })",
        n0,
    )
    shown = rec["shown"]
    decode = {a["id"]: a["decode"] for a in rec["acks"]}
    sizes = sorted({f"{s['w']}x{s['h']}" for s in shown})
    formats = sorted({s["format"] for s in shown})
    return {
        "seconds": round(elapsed, 2),
        "images_shown": len(shown),
        "images_per_s": round(len(shown) / elapsed, 2),
        "simulation_frames_shown_per_s": round(len({s["step"] for s in shown}) / elapsed, 2),
        "pixels_rendered": _stats([s["w"] * s["h"] for s in shown]),
        "formats": formats,
        "sizes": sizes[:6],
        "render_ms": _stats([s["render"] for s in shown]),
        "encode_ms": _stats([s["encode"] for s in shown]),
        "decode_ms": _stats([decode.get(s["id"]) for s in shown]),
        "server_to_screen_ms": _stats([s["travel"] for s in shown]),
        "latency_ms": {
            kind: _stats([x["ms"] for x in rec["lat"] if x["kind"] == kind])
            for kind in sorted({x["kind"] for x in rec["lat"]})
        },
        "sim_steps_per_s": (rec["sim"] or {}).get("steps_per_s"),
        "last_server_stats": {k: v for k, v in (rec["stats"] or {}).items() if k.endswith("_ms")},
        "cpu_cores": cpu,
    }


def _orbit(page: Any) -> Any:
    box = page.locator("#view").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2

    def act(deadline: float) -> None:
        page.mouse.move(cx, cy)
        page.mouse.down()
        angle = 0.0
        while time.monotonic() < deadline:  # about 60 pointer moves a second, as a hand drags
            angle += 0.05
            page.mouse.move(cx + 120 * math.cos(angle), cy + 60 * math.sin(angle))
            page.wait_for_timeout(16)
        page.mouse.up()

    return act


def _steer(page: Any, changes: int) -> Any:
    def act(deadline: float) -> None:
        page.locator("#view").focus()
        for i in range(changes):
            page.keyboard.press("[" if i % 2 else "]")  # sigma up and down by 15 %
            page.wait_for_timeout(700)

    return act


def run(
    root: Path,
    seconds: float,
    demo_args: list[str],
    transport: str,
    priority: int = 0,
    screenshot: Path | None = None,
) -> dict[str, Any]:
    """The demo of the checkout at `root`, its dashboard in Chromium, phase after phase."""
    from playwright.sync_api import sync_playwright

    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(root)}
    with tempfile.TemporaryDirectory() as tmp:
        command = [sys.executable, "-m", "server.commands.cli", "demo", "--port", str(port),
                   "--token", TOKEN, "--no-browser", "--state-dir", tmp, *demo_args]  # fmt: skip
        log = open(Path(tmp) / "demo.log", "wb")  # noqa: SIM115 (closed below)
        demo = subprocess.Popen(command, cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            url = f"http://127.0.0.1:{port}"
            deadline = time.monotonic() + 180
            while True:
                try:
                    got = httpx.get(f"{url}/api/sessions/default", params={"token": TOKEN})
                    if got.status_code == 200 and got.json()["status"]["state"] == "running":
                        break
                except httpx.HTTPError:
                    pass
                if demo.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError((Path(tmp) / "demo.log").read_text()[-3000:])
                time.sleep(0.5)
            meter = CpuMeter(demo.pid)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(
                    executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS
                )
                if priority:  # every group of ours: this one (the demo's), the simulation's,
                    import psutil  # Chromium's

                    ours = [os.getpid(), *[c.pid for c in psutil.Process().children(True)]]
                    _boost(ours, priority, set())
                page = browser.new_context(
                    viewport={"width": VIEW[0], "height": VIEW[1]}, device_scale_factor=1
                ).new_page()
                query = f"?token={TOKEN}" + ("&transport=jpeg" if transport == "jpeg" else "")
                page.goto(f"{url}/{query}")
                page.wait_for_function("() => window.scalesteer && window.scalesteer.lastImage",
                                       timeout=120_000)  # fmt: skip
                page.evaluate(INSTRUMENT)
                page.wait_for_timeout(4000)  # the first stills, the codec settled
                transport = page.evaluate("() => window.scalesteer.lastImage.format")
                phases = {
                    "running": _phase(page, meter, seconds),
                    "orbit": _phase(page, meter, seconds, _orbit(page)),
                    "steer": _phase(page, meter, 0.0, _steer(page, 16)),
                }
                if screenshot is not None:  # the view as the page shows it, to look at
                    page.screenshot(path=str(screenshot))
                browser.close()
        finally:
            demo.terminate()
            demo.wait(60)
            log.close()
    return {"transport": transport, "phases": phases}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0, help="length of each phase")
    ap.add_argument("--demo-arg", action="append", default=[], help="an extra demo option")
    ap.add_argument("--out", type=Path, default=RESULTS / "cpu_demo_chromium_2core.json")
    ap.add_argument("--baseline", type=Path, default=None, help="another checkout, run first")
    ap.add_argument(
        "--priority",
        type=int,
        default=0,
        help="run the demos and Chromium this much ahead of other work (their scheduling "
        "groups' nice lowered by it, as root): on a shared machine, nearly what the figures "
        "would be on a quiet one; the simulation keeps its place below the server",
    )
    ap.add_argument(
        "--transport",
        choices=["auto", "jpeg"],
        default="auto",
        help="auto: video where Chromium decodes it (the default page); jpeg",
    )
    args = ap.parse_args(argv)
    roots = ([("baseline", args.baseline.resolve())] if args.baseline else []) + [("now", ROOT)]
    runs = {}
    for name, root in roots:
        load = os.getloadavg()
        shot = args.out.with_name(f"{args.out.stem}_{name}.png")
        result = run(root, args.seconds, args.demo_arg, args.transport, args.priority, shot)
        runs[name] = {
            "checkout": str(root),
            "commit": _commit(root),
            "load_average_before": [round(x, 2) for x in load],
            "load_average_after": [round(x, 2) for x in os.getloadavg()],
            **result,
        }
        _print(name, runs[name])
    report: dict[str, Any] = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, no GPU",
        "view": list(VIEW),
        "demo": ["scalesteer", "demo", *args.demo_arg],
        "transport_asked": args.transport,
        "priority": args.priority,
        "runs": runs,
    }
    if "baseline" in runs:
        report["now_over_baseline"] = _ratios(runs["now"], runs["baseline"])
        print("now / baseline:", report["now_over_baseline"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    return 0


def _commit(root: Path) -> str:
    done = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    dirty = subprocess.run(
        ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
        capture_output=True,
        text=True,
        check=False,
    )
    return done.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def _figures(run: dict[str, Any]) -> dict[str, float | None]:
    ph = run["phases"]
    return {
        "running_images_per_s": ph["running"]["images_per_s"],
        "orbit_images_per_s": ph["orbit"]["images_per_s"],
        "steer_p50_ms": ph["steer"]["latency_ms"].get("render_params", {}).get("p50"),
        "orbit_latency_p50_ms": ph["orbit"]["latency_ms"].get("view", {}).get("p50"),
    }


def _ratios(now: dict[str, Any], base: dict[str, Any]) -> dict[str, float | None]:
    a, b = _figures(now), _figures(base)
    return {k: round(a[k] / b[k], 2) if a[k] and b[k] else None for k in a}


def _print(name: str, run: dict[str, Any]) -> None:
    ph = run["phases"]
    print(f"[{name}] {run['commit']} load average before {run['load_average_before']}, after "
          f"{run['load_average_after']}; transport {run['transport']}")  # fmt: skip
    for phase in ("running", "orbit"):
        p = ph[phase]
        print(f"  {phase:8} {p['images_per_s']:5.1f} images/s  render {p['render_ms']['p50']} ms"
              f"  encode {p['encode_ms']['p50']} ms  decode {p['decode_ms']['p50']} ms"
              f"  sizes {p['sizes']}  sim {p['sim_steps_per_s']} steps/s")  # fmt: skip
        print("           cores:", p["cpu_cores"])
    print("  figures:", _figures(run))


if __name__ == "__main__":
    raise SystemExit(main())
