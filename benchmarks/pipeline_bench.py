"""The live path's frame rate (`server/pipeline/gpu.py`): one session streaming new positions
through the GPU queue as the server does (frames staged in page-locked memory as they arrive,
rendered, read back), with the next frame's upload overlapped with the render and without
(the control), in the same run.

    python benchmarks/pipeline_bench.py --device cuda:0 --atoms 1000000,100000000 \\
        --size 1920x1080 --out benchmarks/results/pipeline_h200.json

The simulation offers the next frame as each render starts, as a live session's newest frame
arrives while the last one renders, so a frame is always waiting: what the queue delivers is its
own rate. Each render takes the frame offered before it (a session draws its newest frame).

`--staging-control` adds a third run, without the overlap, of staging as it was before the copy
was sliced (2026-11-29): one thread copying a frame into page-locked memory and a render waiting
at most 5 ms for that copy before uploading from the frame itself.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import warp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.render_bench import build_system, jittered_frames, topology_of
from protocol import RenderParams
from server.pipeline import staging
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


def copy_times(frame: np.ndarray, repeats: int = 3) -> dict[str, Any] | None:
    """Staging's own step, copying one frame into page-locked memory: on one thread and in
    slices (`copy_rows`), median ms of `repeats` after one unmeasured; None where no page-locked
    memory is to be had (no CUDA driver)."""
    try:
        _owner, dst = staging.pinned(len(frame))
    except Exception:
        return None
    out: dict[str, Any] = {"threads": staging.COPY_THREADS}
    for key, step in (
        ("one_thread_ms", lambda: np.copyto(dst, frame)),
        ("sliced_ms", lambda: staging.copy_rows(dst, frame)),
    ):
        times = []
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            step()
            times.append((time.perf_counter() - t0) * 1e3)
        out[key] = float(np.median(times[1:]))
    return out


def run(
    device: str,
    prefetch: bool,
    frames: list[np.ndarray],
    topo: Any,
    size: Any,
    s: float,
    staging_before: bool = False,
) -> Any:
    # the control: one thread copies a frame, and a render waits 5 ms for it at most
    policy = (
        staging.Staging(copy_threads=1, pageable_bytes_per_s=math.inf)
        if staging_before
        else staging.Staging()
    )
    queue = GpuQueue(
        device=device, max_atoms=max(len(frames[0]), 1), prefetch=prefetch, staging=policy
    )
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
    ap.add_argument("--staging-control", action="store_true")
    args = ap.parse_args(argv)
    size = (int(args.size.split("x")[0]), int(args.size.split("x")[1]))
    rows: list[dict[str, Any]] = []
    for n in [int(v) for v in args.atoms.split(",")]:
        t0 = time.perf_counter()
        pos, elements, bonds = build_system(n)
        topo = topology_of(elements, bonds if n <= 10_000_000 else None)
        frames = jittered_frames(pos, 3, seed=3)
        print(f"{n:,} atoms: system built in {time.perf_counter() - t0:.1f} s", flush=True)
        row: dict[str, Any] = {"atoms": n, "size": list(size), "copy_ms": copy_times(frames[0])}
        for prefetch in (False, True):
            row["overlapped" if prefetch else "serial"] = run(
                args.device, prefetch, frames, topo, size, args.seconds
            )
        row["overlapped_over_serial"] = row["overlapped"]["fps"] / row["serial"]["fps"]
        if args.staging_control:
            before = run(args.device, False, frames, topo, size, args.seconds, staging_before=True)
            row["serial_staging_before"] = before
            row["serial_over_staging_before"] = row["serial"]["fps"] / before["fps"]
            print(f"{n:,} atoms: staging as before {before['fps']:.1f} fps", flush=True)
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
