"""The live path's frame rate (`server/pipeline/gpu.py`): one session streaming new positions
through the GPU queue as the server does (frames staged in page-locked memory as they arrive,
rendered, read back), with the next frame's upload overlapped with the render and without
(the control), in the same run.

    python benchmarks/pipeline_bench.py --device cuda:0 --atoms 1000000,100000000 \\
        --size 1920x1080 --out benchmarks/results/pipeline_h200.json

The simulation side is a thread that offers a new frame as soon as the last one was taken, so
a frame is always waiting: what the queue delivers is its own rate.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import warp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.render_bench import build_system, topology_of
from protocol import RenderParams
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.render.camera import fit_camera


async def stream(
    queue: GpuQueue, frames: list[np.ndarray], topo: Any, size: tuple[int, int], seconds: float
) -> dict[str, Any]:
    cam = fit_camera(frames[0], *size)
    params = RenderParams()
    k = 1
    done = 0
    stages: list[dict[str, float]] = []
    warm: float | None = None
    queue.stage("session:s", k, frames[k % len(frames)])
    while True:
        now = time.perf_counter()
        if warm is None and done >= 4:
            warm, done, stages = now, 0, []
        if warm is not None and now - warm >= seconds:
            break
        snap = Snapshot(topo, frames[k % len(frames)], positions_id=k)
        queue.stage("session:s", k + 1, frames[(k + 1) % len(frames)])  # the next one arrives
        out = await queue.render(RenderRequest("session:s", snap, params, cam, *size))
        stages.append(out.timings)
        k += 1
        done += 1
    assert warm is not None
    elapsed = time.perf_counter() - warm
    keys = ("upload", "grid", "raycast", "total")
    med = {key: float(np.median([s.get(key, 0.0) for s in stages])) for key in keys}
    return {"fps": done / elapsed, "frames": done, "median_stage_ms": med}


def run(
    device: str, prefetch: bool, frames: list[np.ndarray], topo: Any, size: Any, s: float
) -> Any:
    queue = GpuQueue(device=device, max_atoms=max(len(frames[0]), 1), prefetch=prefetch)
    try:
        return asyncio.run(stream(queue, frames, topo, size, s))
    finally:
        queue.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--atoms", default="1000000")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    size = (int(args.size.split("x")[0]), int(args.size.split("x")[1]))
    rows: list[dict[str, Any]] = []
    for n in [int(v) for v in args.atoms.split(",")]:
        pos, elements, bonds = build_system(n)
        topo = topology_of(elements, bonds if n <= 10_000_000 else None)
        rng = np.random.default_rng(3)
        frames = [pos + rng.normal(scale=0.05, size=pos.shape).astype(np.float32) for _ in range(3)]
        row: dict[str, Any] = {"atoms": n, "size": list(size)}
        for prefetch in (False, True):
            row["overlapped" if prefetch else "serial"] = run(
                args.device, prefetch, frames, topo, size, args.seconds
            )
        row["overlapped_over_serial"] = row["overlapped"]["fps"] / row["serial"]["fps"]
        rows.append(row)
        print(
            f"{n:,} atoms {args.size}: serial {row['serial']['fps']:.1f} fps, overlapped "
            f"{row['overlapped']['fps']:.1f} fps ({row['overlapped_over_serial']:.2f}x)",
            flush=True,
        )
        result = {
            "benchmark": "pipeline",
            "device": args.device,
            "gpu": str(warp.get_device(args.device).name),
            "host": platform.node(),
            "rows": rows,
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
