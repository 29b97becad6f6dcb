"""Temporal scale on the render device: the per-atom filter's time per frame, and the frame it
belongs to, with smoothing off as the baseline in the same run.

For each system size (100k and 1M atoms of the render benchmark's adk lattice) and window W
(16, 32, 64): frames with a small random displacement stream into a Renderer (positions
uploaded, the frame pushed into the ring, the grid rebuilt, iso with shading at 1920x1080), and
three figures are taken frame by frame:

* `smooth_ms`: the filter alone (`TemporalSmoother.smooth`, classical and warped), timed with
  a device synchronisation around it;
* `frame_ms`: the whole frame (upload, ring push, filter, grid, ray cast) with smoothing on;
* `baseline_frame_ms`: the same frames with smoothing off (the ring is not fed).

Memory: the ring holds W frames of 12 bytes per atom plus 4 bytes of warp rate; the server
keeps the last W frames on the host too (references to the decoded frames).

    python benchmarks/temporal_bench.py --device cuda:0 --out benchmarks/results/temporal_h100.json
    python benchmarks/temporal_bench.py --quick --device cpu --out /tmp/temporal_quick.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import warp as wp

from benchmarks.render_bench import build_system, topology_of
from protocol import RenderParams
from server.render import Renderer
from server.render.camera import fit_camera
from server.render.temporal import TemporalSmoother


def median(xs: list[float]) -> float:
    return float(np.median(xs)) if xs else float("nan")


def bench_size(
    device: str, n: int, windows: list[int], frames: int, size: tuple[int, int]
) -> dict[str, Any]:
    pos, elements, bonds = build_system(n)
    topo = topology_of(elements, bonds)
    rng = np.random.default_rng(1)
    jitter = [rng.normal(scale=0.05, size=pos.shape).astype(np.float32) for _ in range(8)]
    cam = fit_camera(pos, *size)
    out: dict[str, Any] = {"atoms": n, "windows": []}

    def frame_times(params: RenderParams, count: int) -> list[float]:
        r = Renderer(device)
        r.set_topology(topo)
        times = []
        history: list[tuple[int, np.ndarray]] = []
        for i in range(count + 3):
            x = pos + jitter[i % len(jitter)]
            t0 = time.perf_counter()
            r.set_positions(x, check_finite=False)
            history = [*history, (i + 1, x)][-params.time_window :]
            r.set_history(history, 0, params)
            r.render(params, cam, *size)
            wp.synchronize_device(device)
            if i >= 3:
                times.append((time.perf_counter() - t0) * 1e3)
        return times

    base = RenderParams()
    out["baseline_frame_ms"] = median(frame_times(base, frames))
    for w in windows:
        row: dict[str, Any] = {"window": w, "ring_bytes_per_atom": w * 12 + 4}
        s = TemporalSmoother(device, n, w)
        for i in range(w):
            s.push(pos + jitter[i % len(jitter)])
        target = wp.zeros(n, dtype=wp.vec3, device=device)
        for name, strength in (("classical", 0.0), ("warped", 1.0)):
            times = []
            for k in range(frames + 3):
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                s.smooth(target, 3.0, strength, "causal", 0)
                wp.synchronize_device(device)
                if k >= 3:
                    times.append((time.perf_counter() - t0) * 1e3)
            row[f"smooth_ms_{name}"] = median(times)
        del s, target
        params = RenderParams(time_smoothing="warped", time_window=w, tau_frames=3.0)
        row["frame_ms"] = median(frame_times(params, frames))
        row["frame_ratio"] = row["frame_ms"] / out["baseline_frame_ms"]
        out["windows"].append(row)
        print(json.dumps({"atoms": n, **row}), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    args = parser.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    if args.quick:
        sizes, windows, frames, size = [5_000], [4, 16], 3, (160, 120)
    else:
        sizes, windows, frames, size = [100_000, 1_000_000], [16, 32, 64], 20, (1920, 1080)
    dev = wp.get_device(args.device)
    result = {
        "benchmark": "temporal",
        "device": args.device,
        "gpu": dev.name if dev.is_cuda else platform.processor() or "cpu",
        "warp": wp.config.version,
        "image": list(size),
        "tau_frames": 3.0,
        "sizes": [bench_size(args.device, n, windows, frames, size) for n in sizes],
    }
    args.out.write_text(json.dumps(result, indent=1))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
