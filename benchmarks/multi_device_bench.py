"""One image across several devices (`server/render/multi.py`) against one device, same frames,
same run: the frame time of a session's render with `--gpus`.

    python benchmarks/multi_device_bench.py --devices cpu,cpu \\
        --out benchmarks/results/multi_device_cpu_2core.json
    python benchmarks/multi_device_bench.py --devices all --atoms 1000000,10000000 \\
        --sizes 1920x1080,3840x2160 --out benchmarks/results/multi_device_h200x2.json

Systems: the render benchmark's adk lattice (`benchmarks/render_bench.py`), positions moved a
little every frame (the grid is rebuilt on every device each frame), iso with shading.
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
import warp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.render_bench import build_system, topology_of
from protocol import RenderParams
from server.render import Renderer
from server.render.camera import fit_camera
from server.render.device import resolve_many
from server.render.multi import MultiRenderer


def frame_ms(
    renderer: Any, pos: np.ndarray, topo: Any, size: tuple[int, int], frames: int
) -> float:
    rng = np.random.default_rng(2)
    cam = fit_camera(pos, *size)
    renderer.set_topology(topo)
    times = []
    for i in range(frames + 2):
        x = pos + rng.normal(scale=0.05, size=pos.shape).astype(np.float32)
        t0 = time.perf_counter()
        renderer.set_positions(x, check_finite=False)
        renderer.render(RenderParams(), cam, *size)
        renderer.read_rgba()
        if i >= 2:
            times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", default="cpu,cpu")
    ap.add_argument("--atoms", default="5684")
    ap.add_argument("--sizes", default="480x270")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    devices = resolve_many(args.devices)
    names = [str(warp.get_device(d).name) for d in devices]
    runs: list[dict[str, Any]] = []
    for n in [int(a) for a in args.atoms.split(",")]:
        pos, elements, bonds = build_system(n)
        topo = topology_of(elements, bonds)
        for text in args.sizes.split(","):
            size = tuple(int(v) for v in text.split("x"))
            cap = max(n, 1)
            one = frame_ms(Renderer(devices[0], max_atoms=cap), pos, topo, size, args.frames)
            multi = MultiRenderer(devices, max_atoms=cap)
            many = frame_ms(multi, pos, topo, size, args.frames)  # type: ignore[arg-type]
            row = {
                "atoms": n,
                "size": list(size),
                "one_device_ms": one,
                "devices_ms": many,
                "speedup": one / many,
                "per_device_ms": multi.device_ms,
            }
            multi.close()
            runs.append(row)
            print(json.dumps(row), flush=True)
            out = {"benchmark": "multi_device", "devices": list(devices), "gpus": names,
                   "host": platform.node(), "runs": runs}  # fmt: skip
            args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
