"""Sort-last (`server/render/sortlast.py`) against one device, same frames, same run: the frame
time, where it goes (the split and each part's upload, the mean density of relative levels,
the parts' renders and their blend), the atoms and device bytes each part holds against one
device's, and how far the image is from one device's.

    python benchmarks/sort_last_bench.py --devices cpu,cpu --atoms 5684 --sizes 320x240 \\
        --out benchmarks/results/sort_last_cpu_2core.json
    python benchmarks/sort_last_bench.py --devices cuda:0,cuda:0 --atoms 1000000 \\
        --sizes 1920x1080 --out benchmarks/results/sort_last_h200_one_device.json

Sort-last runs twice, the parts' atoms picked on the devices (`--gathers device`, each device
from the 1/N of the frame it uploads) and on the host (the control), each against one device.

Several parts on one device (`cuda:0,cuda:0`) render one after another: that run measures
what sort-last adds (the host's split and gathers, the mean's synchronisation, the blend) and
the bytes each part holds, not a speed-up, which needs a device per part.

Systems: the render benchmark's adk lattice (`benchmarks/render_bench.py`), positions moved a
little every frame, iso with shading (and volume with `--modes iso,volume`).
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

from benchmarks.multi_device_bench import frames_of
from benchmarks.render_bench import build_system, topology_of
from protocol import RenderParams
from server.render import Renderer
from server.render.camera import fit_camera
from server.render.device import resolve_many
from server.render.sortlast import SortLastRenderer
from server.render.tuning import Tuning


def timed_frames(
    renderer: Any, frames: list[np.ndarray], params: RenderParams, size: tuple[int, int], warm: int
) -> tuple[dict[str, float], np.ndarray]:
    """Median host wall ms of a frame (positions in, image read back) and of the renderer's
    own stages, and the first frame's ms (for sort-last: the split, each part's topology and
    colours); the last image."""
    cam = fit_camera(frames[0], *size)
    rows: list[dict[str, float]] = []
    image = np.zeros(0)
    first = 0.0
    for i, x in enumerate(frames):
        t0 = time.perf_counter()
        renderer.set_positions(x, check_finite=False)
        renderer.render(params, cam, *size)
        image = renderer.read_rgba()
        t1 = time.perf_counter()
        if i == 0:
            first = (t1 - t0) * 1e3
        if i >= warm:
            stages = {
                k if k.endswith("_ms") else f"{k}_ms": float(v) for k, v in renderer.timings.items()
            }
            for j, part in enumerate(getattr(renderer, "renderers", [])):
                stages.update({f"part{j}_{k}_ms": float(v) for k, v in part.timings.items()})
            rows.append({"frame_ms": (t1 - t0) * 1e3, **stages})
    keys = rows[0].keys()
    found = {k: float(np.median([r.get(k, 0.0) for r in rows])) for k in keys}
    return {**found, "first_frame_ms": first}, image


def page_locked(x: np.ndarray) -> np.ndarray:
    """A copy of `x` (n, 3) float32 in page-locked host memory (where CUDA is)."""
    pinned = bool(warp.is_cuda_available())
    buf = warp.empty(len(x), dtype=warp.vec3, device="cpu", pinned=pinned)
    view: np.ndarray = buf.numpy().view(np.float32).reshape(-1, 3)
    view[:] = x
    _keep.append(buf)
    return view


_keep: list[Any] = []
"""The page-locked buffers behind the frames' views."""


def bytes_of(memory: dict[str, int]) -> int:
    return int(sum(memory.values()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", default="cpu,cpu", help="one per part (a device may repeat)")
    ap.add_argument("--atoms", default="5684")
    ap.add_argument("--sizes", default="320x240")
    ap.add_argument("--modes", default="iso")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--warm", type=int, default=5)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--no-graphs", action="store_true", help="launch one by one (both sides)")
    ap.add_argument(
        "--gathers",
        default="device,host",
        help="where sort-last picks the parts' atoms: device (each device from its 1/N of the "
        "frame), host (the control); the first is the row's ratio",
    )
    ap.add_argument(
        "--pinned",
        action="store_true",
        help="frames in page-locked host memory, as a live session stages them (both sides)",
    )
    args = ap.parse_args(argv)
    tuning = Tuning(graphs=False) if args.no_graphs else None
    devices = list(resolve_many(args.devices))
    if len(devices) < 2:
        ap.error("--devices names at least two parts")
    out: dict[str, Any] = {
        "benchmark": "sort_last",
        "devices": devices,
        "gpus": [str(warp.get_device(d).name) for d in dict.fromkeys(devices)],
        "date": time.strftime("%Y-%m-%d"),
        "warp": str(warp.config.version),
        "host": platform.node(),
        "graphs": not args.no_graphs,
        "runs": [],
    }
    for n in [int(a) for a in args.atoms.split(",")]:
        pos, elements, bonds = build_system(n)
        topo = topology_of(elements, bonds)
        frames = frames_of(pos, args.frames + args.warm)
        if args.pinned:  # as a live session's frames are staged (`server.pipeline.staging`)
            _keep.clear()  # the last system's page-locked frames
            frames = [page_locked(x) for x in frames]
        for text in args.sizes.split(","):
            size = (int(text.split("x")[0]), int(text.split("x")[1]))
            for mode in args.modes.split(","):
                params = RenderParams(mode=mode, sigma_A=1.5 if mode == "iso" else 2.5)
                one = Renderer(devices[0], max_atoms=n, tuning=tuning)
                one.set_topology(topo)
                control, want = timed_frames(one, frames, params, size, args.warm)
                one_bytes = bytes_of(one.memory_bytes())
                del one
                row: dict[str, Any] = {
                    "atoms": n,
                    "size": list(size),
                    "mode": mode,
                    "one_device": {**control, "bytes": one_bytes},
                }
                for gather in args.gathers.split(","):
                    s = SortLastRenderer(devices, gather=gather, max_atoms=n, tuning=tuning)
                    s.set_topology(topo)
                    found, got = timed_frames(s, frames, params, size, args.warm)
                    diff = np.abs(got.astype(np.int16) - want.astype(np.int16)).max(axis=-1)
                    key = "sort_last" if gather == "device" else f"sort_last_{gather}_gather"
                    row[key] = {
                        **found,
                        "atoms_held": s.atoms_held(),
                        "bytes": [bytes_of(m) for m in s.memory_bytes()],
                        "ratio_to_one_device": control["frame_ms"] / found["frame_ms"],
                        "image_vs_one_device": {
                            "max_levels": int(diff.max()),
                            "mean_levels": float(diff.mean()),
                        },
                    }
                    del s
                first = row[next(k for k in row if k.startswith("sort_last"))]
                row["ratio_to_one_device"] = first["ratio_to_one_device"]
                row["image_vs_one_device"] = first["image_vs_one_device"]
                out["runs"].append(row)
                print(json.dumps(row), flush=True)
                args.out.write_text(json.dumps(out, indent=1))
    args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
