"""One-off renders (`POST /api/render`) drawn whole, as one turn on the device, against drawn in
bands of rows (`GpuQueue.render_bands`, `server/pipeline/bands.py`), in the same run: how long
each takes, and how long a live session's render submitted while one is under way waits.

    python benchmarks/oneoff_bench.py --device cpu --cases 496@640x480@classical \\
        --out benchmarks/results/latency_cpu_2core_oneoff_bands.json
    python benchmarks/oneoff_bench.py --device cuda:0 \\
        --out benchmarks/results/latency_h200_oneoff_bands.json

A case is ATOMS@WxH@SPACE (the render benchmark's systems: villin at 496 atoms, the adk
lattice above). Each repetition draws the one-off image whole, then in bands (alternating which
goes first), each once alone and once with a live render (a 640x360 image of the same system on
a slot of its own) submitted `--live-after` seconds after the device began the one-off's work
(its footprint, weighed on the host first, not counted); the live render's time from its
submission to its image is its wait.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import platform
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import warp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.render_bench import build_system, topology_of
from protocol import RenderParams
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.render.camera import fit_camera

LIVE_SIZE = (640, 360)


async def one_off(
    queue: GpuQueue, request: RenderRequest, banded: bool, live: RenderRequest | None, after: float
) -> dict[str, float]:
    """One one-off image (whole or banded), with a live render `after` s into it if given."""
    slot = f"rest:{time.perf_counter_ns()}"
    req = dataclasses.replace(request, slot=slot)
    started = threading.Event()  # the device began the one-off's work
    render_sync = queue.render_sync

    def marked(r: RenderRequest) -> Any:
        if r.slot == slot:
            started.set()
        return render_sync(r)

    queue.render_sync = marked  # type: ignore[method-assign]
    t0 = time.perf_counter()
    job = asyncio.ensure_future(
        queue.render_bands(req, float("inf")) if banded else queue.render(req)
    )
    out: dict[str, float] = {}
    if live is not None:
        while not started.is_set():
            await asyncio.sleep(0.0002)
        await asyncio.sleep(after)
        t_live = time.perf_counter()
        await queue.render(live)
        out["live_wait_ms"] = (time.perf_counter() - t_live) * 1e3
    await job
    out["one_off_ms"] = (time.perf_counter() - t0) * 1e3
    queue.render_sync = render_sync  # type: ignore[method-assign]
    await queue.release(slot)
    return out


async def case(
    queue: GpuQueue, n: int, size: tuple[int, int], space: str, reps: int, after: float
) -> dict[str, Any]:
    pos, elements, bonds = build_system(n)
    topo = topology_of(elements, bonds)
    params = RenderParams(scale_space=space)  # type: ignore[arg-type]
    request = RenderRequest("rest:x", Snapshot(topo, pos), params, fit_camera(pos, *size), *size)
    live = RenderRequest(
        "session:live", Snapshot(topo, pos), params, fit_camera(pos, *LIVE_SIZE), *LIVE_SIZE
    )
    await queue.render(live)  # the live slot's renderer and kernels exist
    for banded in (False, True):  # unmeasured: kernels compiled, graphs of both captured
        await one_off(queue, request, banded, None, after)
    rows: dict[str, list[dict[str, float]]] = {"whole": [], "bands": []}
    for i in range(reps):
        for banded in (i % 2 == 0, i % 2 != 0):
            key = "bands" if banded else "whole"
            alone = await one_off(queue, request, banded, None, after)
            mixed = await one_off(queue, request, banded, live, after)
            rows[key].append({"alone_ms": alone["one_off_ms"], **mixed})
    await queue.release("session:live")

    def med(key: str, field: str) -> float:
        return statistics.median(r[field] for r in rows[key])

    summary = {
        f"{key}_{field}": med(key, field)
        for key in rows
        for field in ("alone_ms", "one_off_ms", "live_wait_ms")
    }
    return {
        "n_atoms": n,
        "size": list(size),
        "scale_space": space,
        "reps": reps,
        **summary,
        "bands_over_whole_alone": summary["bands_alone_ms"] / summary["whole_alone_ms"],
        "live_wait_whole_over_bands": summary["whole_live_wait_ms"] / summary["bands_live_wait_ms"],
        "rows": rows,
    }


async def run(args: argparse.Namespace) -> list[dict[str, Any]]:
    queue = GpuQueue(device=args.device)
    results = []
    try:
        for text in args.cases.split(","):
            n, size, space = text.split("@")
            w, h = (int(v) for v in size.split("x"))
            r = await case(queue, int(n), (w, h), space, args.reps, args.live_after)
            results.append(r)
            print(
                f"{int(n):>9,} atoms {size} {space}: whole {r['whole_alone_ms']:.1f} ms, bands "
                f"{r['bands_alone_ms']:.1f} ms ({r['bands_over_whole_alone']:.2f}x); a live "
                f"render waits {r['whole_live_wait_ms']:.1f} ms behind it whole, "
                f"{r['bands_live_wait_ms']:.1f} ms in bands",
                flush=True,
            )
    finally:
        queue.close()
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument(
        "--cases",
        default="496@1920x1080@classical,496@1920x1080@geodesic,100000@1920x1080@classical,"
        "1000000@3840x2160@classical",
    )
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--live-after", type=float, default=0.002, help="s into the one-off render")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    results = asyncio.run(run(args))
    device = warp.get_device(args.device)
    result = {
        "benchmark": "oneoff",
        "device": args.device,
        "gpu": str(device.name) if device.is_cuda else "cpu",
        "warp": warp.config.version,
        "host": platform.node(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "live_size": list(LIVE_SIZE),
        "live_after_s": args.live_after,
        "cases": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
