"""Sessions on the devices of one host (`server/pipeline/gpu.py`): the frames per second each
live session renders when it is alone on one device, alone on all of them (drawn across them),
and when N sessions share N devices (one each), in the same run.

    python benchmarks/multi_session_bench.py --devices cpu,cpu --atoms 5684 --size 480x270 \\
        --seconds 5 --out benchmarks/results/multi_session_cpu_2core.json
    python benchmarks/multi_session_bench.py --devices all --atoms 1000000 --size 1920x1080 \\
        --out benchmarks/results/multi_session_h200x4.json

Each session streams its own copy of the render benchmark's adk lattice: every frame has new
positions (the queue stages them in page-locked memory as a live session's frames are, and the
render uploads the newest while the last one draws) and is rendered, shaded and read back.
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
from server.render.device import resolve_many


async def stream(
    queue: GpuQueue, slot: str, pos: np.ndarray, topo: Any, size: tuple[int, int], seconds: float
) -> dict[str, float]:
    """Frames rendered per second by one session streaming new positions for `seconds`."""
    rng = np.random.default_rng(abs(hash(slot)) % 1000)
    shifts = rng.normal(scale=0.05, size=(4, *pos.shape)).astype(np.float32)
    cam = fit_camera(pos, *size)
    params = RenderParams()
    frames = [pos + shifts[i] for i in range(4)]
    k = 1
    done = 0
    start = time.perf_counter()
    warm = None
    while True:
        now = time.perf_counter()
        if warm is None and done >= 3:  # after the first frames: graphs captured, kernels loaded
            warm, done = now, 0
        if warm is not None and now - warm >= seconds:
            break
        queue.stage(slot, k, frames[k % 4])
        snap = Snapshot(topo, frames[k % 4], positions_id=k)
        await queue.render(RenderRequest(slot, snap, params, cam, *size))
        k += 1
        done += 1
    assert warm is not None
    elapsed = time.perf_counter() - warm
    return {"fps": done / elapsed, "frames": done, "seconds": elapsed, "warmup_s": warm - start}


async def sessions(
    devices: tuple[str, ...],
    count: int,
    pos: np.ndarray,
    topo: Any,
    size: tuple[int, int],
    s: float,
) -> list[dict[str, float]]:
    queue = GpuQueue(devices=devices, max_atoms=max(len(pos), 1))
    try:
        if count > 1:  # place every session before any streams (the first would spread)
            for i in range(count):
                await queue.render(
                    RenderRequest(
                        f"session:{i}",
                        Snapshot(topo, pos),
                        RenderParams(),
                        fit_camera(pos, *size),
                        *size,
                    )
                )
        runs = [stream(queue, f"session:{i}", pos, topo, size, s) for i in range(count)]
        out = list(await asyncio.gather(*runs))
        for i, row in enumerate(out):
            row["device"] = queue.lane_device(f"session:{i}") or ""
        return out
    finally:
        await asyncio.to_thread(queue.close)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", default="cpu,cpu")
    ap.add_argument("--atoms", type=int, default=5684)
    ap.add_argument("--size", default="480x270")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    devices = resolve_many(args.devices)
    if len(devices) < 2:
        ap.error("name at least two devices")
    size = (int(args.size.split("x")[0]), int(args.size.split("x")[1]))
    pos, elements, bonds = build_system(args.atoms)
    topo = topology_of(elements, bonds)
    n = len(devices)
    one = asyncio.run(sessions(devices[:1], 1, pos, topo, size, args.seconds))[0]
    spread = asyncio.run(sessions(devices, 1, pos, topo, size, args.seconds))[0]
    many = asyncio.run(sessions(devices, n, pos, topo, size, args.seconds))
    result = {
        "benchmark": "multi_session",
        "devices": list(devices),
        "gpus": [str(warp.get_device(d).name) for d in devices],
        "host": platform.node(),
        "atoms": args.atoms,
        "size": list(size),
        "one_session_one_device": one,
        "one_session_all_devices": spread,
        "sessions_one_device_each": many,
        "spread_over_one": spread["fps"] / one["fps"],
        "each_over_one": [m["fps"] / one["fps"] for m in many],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(
        f"{args.atoms:,} atoms {args.size}: one session on one device {one['fps']:.1f} fps, "
        f"across {n} devices {spread['fps']:.1f} fps ({result['spread_over_one']:.2f}x); "
        f"{n} sessions, one device each: "
        + ", ".join(
            f"{m['fps']:.1f} fps ({r:.2f}x)"
            for m, r in zip(many, result["each_over_one"], strict=True)
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
