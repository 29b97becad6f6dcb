"""One image across several devices (`server/render/multi.py`) against one device, same frames,
same run: the frame time of a session's render with `--gpus`, where its time goes, and what the
host's links between memory and devices allow.

    python benchmarks/multi_device_bench.py --devices cpu,cpu \\
        --out benchmarks/results/multi_device_cpu_2core.json
    python benchmarks/multi_device_bench.py --devices all --atoms 1000000,10000000 \\
        --sizes 1920x1080,3840x2160 --out benchmarks/results/multi_device_h200x4.json
    python benchmarks/multi_device_bench.py --devices all --atoms 1000000,10000000 \\
        --sizes 3840x2160 --frames 9 --warm 3 --sections profile \\
        --out benchmarks/results/multi_device_h200x4_profile.json

Sections (`--sections`, default links and frames):
  links   page-locked host -> device copies, one device alone and every device at once (each on
          a stream of its own, issued from one thread), device -> host, and device -> device
          (peer) copies: the ceilings a frame's upload and gather live under
  profile every kernel and copy of a frame, per device (CUDA) (warp's activity timing, graphs off so
          each launch is timed; median ms per frame over the frames), one device against all:
          where the time goes that does not shrink with more devices
  frames  each system and image size on one device, then on 2, 4, ... (powers of two up to
          --devices) in the same run, each count with the frame's upload split across the
          devices (1/N each from the host, the rest device to device) and, as its control,
          every device uploading all of it (`whole_upload`); per frame the host wall time of
          the three phases a session's render goes through (set_positions on every device,
          the render, the gather of the image), each device's own stage times and the host
          time each device's render took to queue. Frames are written into the
          renderer's page-locked buffer before the clock starts, and images are read into
          page-locked buffers of the benchmark's, for one device as for several

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
from server.render.tuning import Tuning

wp: Any = warp


def frames_of(pos: np.ndarray, count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(2)
    shift = rng.normal(scale=0.05, size=(4, *pos.shape)).astype(np.float32)
    return [pos + shift[i % 4] for i in range(count)]


def frame_phases(
    renderer: Any, frames: list[np.ndarray], topo: Any, size: tuple[int, int], warm: int
) -> dict[str, Any]:
    """Median host wall ms of a frame and of its phases; the devices' own stage times."""
    cam = fit_camera(frames[0], *size)
    renderer.set_topology(topo)
    w, h = size
    # images are read into page-locked buffers the caller keeps (a DMA, no host copy)
    pinned = bool(wp.is_cuda_available())
    images = [wp.empty(w * h, dtype=wp.uint32, device="cpu", pinned=pinned) for _ in range(2)]
    views = [im.numpy().view(np.uint8).reshape(h, w, 4) for im in images]
    rows: list[dict[str, float]] = []
    devices: list[dict[str, float]] = []
    for i, x in enumerate(frames):
        # the frame is in page-locked memory before its render (a live session's frames are
        # staged as they arrive): the one device and the several alike
        staged = renderer.host_positions()
        np.copyto(staged, x)
        t0 = time.perf_counter()
        renderer.set_positions(staged, check_finite=False)
        t1 = time.perf_counter()
        renderer.render(RenderParams(), cam, *size)
        t2 = time.perf_counter()
        renderer.read_rgba_into(views[i % 2])
        t3 = time.perf_counter()
        if i >= warm:
            rows.append(
                {
                    "frame": (t3 - t0) * 1e3,
                    "set_positions": (t1 - t0) * 1e3,
                    "render": (t2 - t1) * 1e3,
                    "gather": (t3 - t2) * 1e3,
                }
            )
            inner = getattr(renderer, "renderers", [renderer])
            stages = {
                f"{k}:{j}": float(r.timings.get(k, 0.0))
                for j, r in enumerate(inner)
                for k in ("upload", "grid", "raycast", "total")
            }
            # the host time each device's render took to queue (several devices)
            issue = getattr(renderer, "issue_ms", [])
            devices.append({**stages, **{f"issue:{j}": float(t) for j, t in enumerate(issue)}})
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    dev = {k: float(np.median([r[k] for r in devices])) for k in devices[0]}
    return {**{f"{k}_ms": v for k, v in med.items()}, "device_stage_ms": dev}


def profile(
    devices: tuple[str, ...], n: int, size: tuple[int, int], count: int, warm: int
) -> dict[str, Any]:
    """Median ms per frame of each kernel and copy on each device, one device against all."""
    pos, elements, bonds = build_system(n)
    topo = topology_of(elements, bonds)
    frames = frames_of(pos, count + warm)
    cam = fit_camera(frames[0], *size)
    untimed = Tuning(graphs=False)  # a captured graph's kernels are not timed one by one
    out: dict[str, Any] = {"atoms": n, "size": list(size), "by_devices": {}}
    for k in sorted({1, len(devices)}):
        r: Any = (
            Renderer(devices[0], max_atoms=n, tuning=untimed)
            if k == 1
            else MultiRenderer(devices[:k], max_atoms=n, tuning=untimed)
        )
        r.set_topology(topo)
        sums: list[dict[str, dict[str, float]]] = []
        for i, x in enumerate(frames):
            np.copyto(r.host_positions(), x)
            if i >= warm:
                wp.timing_begin(cuda_filter=wp.TIMING_ALL)
            r.set_positions(r.host_positions(), check_finite=False)
            r.render(RenderParams(), cam, *size)
            r.read_rgba()
            if i >= warm:
                frame: dict[str, dict[str, float]] = {}
                for t in wp.timing_end():
                    per = frame.setdefault(str(t.device), {})
                    per[t.name] = per.get(t.name, 0.0) + float(t.elapsed)
                sums.append(frame)
        table: dict[str, dict[str, float]] = {}
        for dev in sorted({d for f in sums for d in f}):
            names = {name for f in sums for name in f.get(dev, {})}
            med = {
                name: float(np.median([f.get(dev, {}).get(name, 0.0) for f in sums]))
                for name in names
            }
            ranked = sorted(med.items(), key=lambda kv: -kv[1])
            table[dev] = {"total_ms": float(sum(med.values())), **dict(ranked[:16])}
        out["by_devices"][str(k)] = table
        if k > 1:
            r.close()
        del r
    return out


def links(devices: tuple[str, ...], mbytes: int) -> dict[str, Any]:
    """Copy rates in GB/s (median of 5) between page-locked host memory and the devices."""
    cuda = [d for d in devices if d.startswith("cuda")]
    if not cuda:
        return {}
    n = mbytes * (1 << 20) // 4
    host = wp.empty(n, dtype=float, device="cpu", pinned=True)
    host.numpy()[:] = np.random.default_rng(0).random(n, dtype=np.float32)
    back = {d: wp.empty(n, dtype=float, device="cpu", pinned=True) for d in cuda}
    dev = {d: wp.empty(n, dtype=float, device=d) for d in cuda}
    streams = {d: wp.Stream(d) for d in cuda}
    nbytes = n * 4

    def timed(copies: list[tuple[Any, Any, str]]) -> float:
        times = []
        for _ in range(6):
            wp.synchronize()
            t0 = time.perf_counter()
            for dst, src, d in copies:
                wp.copy(dst, src, stream=streams[d])
            for d in {d for _, _, d in copies}:
                wp.synchronize_stream(streams[d])
            times.append(time.perf_counter() - t0)
        return float(np.median(times[1:]))

    out: dict[str, Any] = {"bytes": nbytes}
    out["h2d_one_GBps"] = nbytes / timed([(dev[cuda[0]], host, cuda[0])]) / 1e9
    t = timed([(dev[d], host, d) for d in cuda])
    out["h2d_all_GBps_each"] = nbytes / t / 1e9
    out["d2h_one_GBps"] = nbytes / timed([(back[cuda[0]], dev[cuda[0]], cuda[0])]) / 1e9
    t = timed([(back[d], dev[d], d) for d in cuda])
    out["d2h_all_GBps_each"] = nbytes / t / 1e9
    peers: dict[str, Any] = {}
    for a in cuda:
        for b in cuda:
            if a != b:
                ok = bool(wp.is_peer_access_supported(a, b))
                peers[f"{a}->{b}"] = {"peer_access": ok}
    if len(cuda) > 1:
        a, b = cuda[1], cuda[0]
        if peers[f"{a}->{b}"]["peer_access"]:
            for x, y in ((a, b), (b, a)):
                wp.set_peer_access_enabled(x, y, True)
                if wp.is_mempool_access_supported(x, y):
                    wp.set_mempool_access_enabled(x, y, True)
        peers[f"{a}->{b}"]["GBps"] = nbytes / timed([(dev[b], dev[a], b)]) / 1e9
    out["peers"] = peers
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", default="cpu,cpu")
    ap.add_argument("--atoms", default="5684")
    ap.add_argument("--sizes", default="480x270")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sections", default="links,frames")
    ap.add_argument("--link-mb", type=int, default=256)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument(
        "--upload",
        default="split,whole",
        help="how several CUDA devices get a frame: split (each uploads 1/N from the host, the "
        "rest device to device; the default) and/or whole (each uploads all: the control)",
    )
    ap.add_argument(
        "--warm",
        type=int,
        default=10,
        help="frames before the clock starts (bands balance and graphs are captured in them)",
    )
    args = ap.parse_args(argv)
    devices = resolve_many(args.devices)
    uploads = [u.strip() for u in args.upload.split(",") if u.strip()]
    if not uploads or not set(uploads) <= {"split", "whole"}:
        ap.error("--upload takes split and/or whole")
    sections = {s.strip() for s in args.sections.split(",") if s.strip()}
    unknown = sections - {"links", "profile", "frames"}
    if unknown:
        ap.error(f"unknown sections: {', '.join(sorted(unknown))} (links, profile, frames)")
    names = [str(warp.get_device(d).name) for d in devices]
    counts = [k for k in (1, 2, 4, 8, 16) if k <= len(devices)]
    out: dict[str, Any] = {
        "benchmark": "multi_device",
        "devices": list(devices),
        "gpus": names,
        "host": platform.node(),
        "runs": [],
    }
    if "links" in sections:
        out["links"] = links(devices, args.link_mb)
        print(json.dumps({"links": out["links"]}), flush=True)
    if "profile" in sections:
        out["profile"] = []
        for n in [int(a) for a in args.atoms.split(",")]:
            for text in args.sizes.split(","):
                size = (int(text.split("x")[0]), int(text.split("x")[1]))
                found = profile(devices, n, size, max(args.frames // 3, 3), args.warm)
                out["profile"].append(found)
                print(json.dumps(found), flush=True)
                args.out.write_text(json.dumps(out, indent=1))
    if "frames" in sections:
        for n in [int(a) for a in args.atoms.split(",")]:
            pos, elements, bonds = build_system(n)
            topo = topology_of(elements, bonds)
            frames = frames_of(pos, args.frames + args.warm)
            for text in args.sizes.split(","):
                size = (int(text.split("x")[0]), int(text.split("x")[1]))
                cap = max(n, 1)
                row: dict[str, Any] = {"atoms": n, "size": list(size), "by_devices": {}}
                for k in counts:
                    for upload in ["one"] if k == 1 else uploads:
                        r: Any = (
                            Renderer(devices[0], max_atoms=cap)
                            if k == 1
                            else MultiRenderer(devices[:k], upload=upload, max_atoms=cap)
                        )
                        phases = frame_phases(r, frames, topo, size, args.warm)
                        if upload in ("one", "split"):
                            row["by_devices"][str(k)] = phases
                        else:  # every device uploading all of every frame: the control
                            row.setdefault("whole_upload", {})[str(k)] = phases
                        if k > 1:
                            r.close()
                        del r
                one = row["by_devices"]["1"]["frame_ms"]
                row["speedup"] = {
                    k: one / v["frame_ms"] for k, v in row["by_devices"].items() if k != "1"
                }
                out["runs"].append(row)
                print(json.dumps(row), flush=True)
                args.out.write_text(json.dumps(out, indent=1))
    args.out.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
