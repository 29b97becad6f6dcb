"""The demo on a machine without a GPU: frame rate, steer-to-photon, pick and pull latency.

Runs what `make demo` runs on the CPU (the villin headpiece in OpenMM's CPU platform, reported
every 50 steps, and the render server on warp's CPU device, in one process) and measures it from
a dashboard stand-in in a process of its own, holding an 800x600 canvas:

    fps           images a viewer receives per second while dragging the camera
    steer         render_params sent -> the first image that reflects it (image.ref)
    pick          pick sent -> picked received
    pull          pull sent -> the session's `pulling` state naming it (what the dashboard
                  draws once the server has it; the pull line itself is drawn at once)
    pull_ack      pull sent -> the simulation's acknowledgement (the next MD report)

Each configuration runs in the same invocation: `baseline` renders every image at the size the
canvas asks for (no frame budget), `budget` is the default (images shrink to what renders in
`frame_budget_ms`, refined when still), `two_devices` is the budget with each image rendered
across two CPU devices (`serve --gpus cpu,cpu`, two bands on two threads). Ratios are budget /
baseline, and two_devices / budget.

    python benchmarks/cpu_interactive_bench.py            # writes results/cpu_interactive_*.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

import protocol as p
from server.commands.serve import ServerThread
from server.settings import ServerSettings

RESULTS = ROOT / "benchmarks" / "results"
CANVAS = (800, 600)


def _dashboard(url: str, token: str, seconds: float, out: Any) -> None:
    """The measuring client (its own process): a steerer with an 800x600 canvas, looking at
    the molecule the way the dashboard does (the session's camera)."""
    import math

    from tests.server.peers import Peer

    peer = Peer(url, "steerer", token, "default")
    state = peer.expect(p.State, 60, where=lambda m: m.camera is not None)
    camera = state.camera
    assert camera is not None
    seq = peer.send(p.View(camera=camera, width=CANVAS[0], height=CANVAS[1]))
    peer.expect(p.Image, 60, where=lambda m: m.ref == seq)

    def turned(angle: float) -> p.Camera:
        half = angle / 2  # a turn about the view's y axis, as a mouse drag does
        q = (math.cos(half), 0.0, math.sin(half), 0.0)
        return camera.model_copy(update={"orientation": q})

    # frame rate while the user drags the camera (30 view messages a second)
    frames = 0
    start = last_sent = time.monotonic()
    step = 0
    while time.monotonic() - start < seconds:
        now = time.monotonic()
        if now - last_sent >= 1 / 30:
            step += 1
            peer.send(
                p.View(
                    camera=turned(0.02 * step),
                    width=CANVAS[0],
                    height=CANVAS[1],
                    interacting=True,
                )
            )
            last_sent = now
        try:
            if isinstance(peer.recv(0.01), p.Image):
                frames += 1
        except TimeoutError:
            continue
    fps = frames / (time.monotonic() - start)
    peer.send(p.View(camera=camera, width=CANVAS[0], height=CANVAS[1]))
    peer.drain(1.5)
    steer: list[float] = []
    for i in range(16):
        sent = time.monotonic()
        seq = peer.send(p.SetRenderParams(params={"sigma_A": 1.5 + 0.1 * (i % 2 + 1)}))
        peer.expect(p.Image, 30, where=lambda m, s=seq: m.ref is not None and m.ref >= s)
        steer.append((time.monotonic() - sent) * 1000)
        time.sleep(0.3)
    pick: list[float] = []
    for i in range(10):
        sent = time.monotonic()
        seq = peer.send(p.Pick(x=CANVAS[0] // 2 + 4 * i, y=CANVAS[1] // 2))
        peer.expect(p.Picked, 30, where=lambda m, s=seq: m.ref == s)
        pick.append((time.monotonic() - sent) * 1000)
        time.sleep(0.2)
    pull: list[float] = []
    pull_ack: list[float] = []
    for i in range(8):
        sent = time.monotonic()
        seq = peer.send(p.Pull(atom=10 + i, target=(0.0, 0.0, 0.0), spring_k=1.0))
        peer.expect(
            p.State,
            30,
            where=lambda m, a=10 + i: m.pulling is not None and any(q.atom == a for q in m.pulling),
        )
        pull.append((time.monotonic() - sent) * 1000)
        peer.expect(p.ParamsAck, 30, where=lambda m, s=seq: m.ref == s)
        pull_ack.append((time.monotonic() - sent) * 1000)
        peer.send(p.Pull(atom=10 + i, release=True))
        time.sleep(0.3)
    peer.close()
    out.put({"fps": fps, "steer": steer, "pick": pick, "pull": pull, "pull_ack": pull_ack})


def summary(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "median": statistics.median(ordered),
        "p90": ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))],
        "max": ordered[-1],
    }


def run(config: str, seconds: float) -> dict[str, Any]:
    from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
    from simulation_adapters.openmm_systems import build_villin_simulation

    budget = config in ("budget", "two_devices")
    defaults = ServerSettings(token="bench")
    with tempfile.TemporaryDirectory() as tmp:
        settings = ServerSettings(
            port=0,
            device="cpu",
            token="bench",
            state_dir=Path(tmp),
            default_size=(400, 300),
            render_defaults=p.RenderParams(sigma_A=1.5, quality=0.45),
            frame_budget_ms=defaults.frame_budget_ms if budget else 0.0,
            refine_budget_ms=defaults.refine_budget_ms if budget else 0.0,
            stats_interval_s=5.0,
            gpus="cpu,cpu" if config == "two_devices" else None,
        )
        server = ServerThread(settings)
        simulation = build_villin_simulation(platform="CPU", properties={"Threads": "1"})
        reporter = SteeringReporter(
            f"ws://127.0.0.1:{server.port}/ws/sim", token="bench", interval=50
        )
        simulation.reporters.append(reporter)
        stop = threading.Event()

        def md() -> None:
            while not stop.is_set():
                run_steered(simulation, 500, reporter=reporter)

        runner = threading.Thread(target=md, name="md")
        runner.start()
        ctx = mp.get_context("spawn")
        out = ctx.Queue()
        client = ctx.Process(
            target=_dashboard, args=(f"ws://127.0.0.1:{server.port}/ws/view", "bench", seconds, out)
        )
        client.start()
        result = out.get(timeout=600)
        client.join(30)
        stop.set()
        reporter.stop_requested = True
        runner.join(60)
        reporter.close()
        server.stop()
    return {
        "config": config,
        "fps": result["fps"],
        **{k: summary(result[k]) for k in ("steer", "pick", "pull", "pull_ack")},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=15.0, help="frame-rate window")
    ap.add_argument("--out", type=Path, default=RESULTS / "cpu_interactive_2core.json")
    args = ap.parse_args(argv)
    rows = [run(config, args.seconds) for config in ("baseline", "budget", "two_devices")]
    base, new, two = rows
    ratios = {
        "fps": new["fps"] / base["fps"],
        **{k: new[k]["median"] / base[k]["median"] for k in ("steer", "pick", "pull")},
    }
    report = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, no GPU",
        "canvas": list(CANVAS),
        "system": "villin headpiece (582 atoms), OpenMM CPU platform, frames every 50 steps",
        "rows": rows,
        "ratios_budget_over_baseline": ratios,
        "ratios_two_devices_over_budget": {
            "fps": two["fps"] / new["fps"],
            **{k: two[k]["median"] / new[k]["median"] for k in ("steer", "pick", "pull")},
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    print(f"{'config':<12}{'fps':>7}{'steer ms':>10}{'pick ms':>9}{'pull ms':>9}{'ack ms':>8}")
    for r in rows:
        print(
            f"{r['config']:<12}{r['fps']:>7.1f}{r['steer']['median']:>10.0f}"
            f"{r['pick']['median']:>9.0f}{r['pull']['median']:>9.0f}{r['pull_ack']['median']:>8.0f}"
        )
    print("ratios (budget / baseline):", {k: round(v, 2) for k, v in ratios.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
