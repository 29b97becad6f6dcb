"""Steer-to-photon latency and per-viewer throughput of the render server, over loopback.

Latency: a steerer sends `render_params` (sigma alternating) and waits for the first image that
reflects it (`image.ref` == its seq), decodes the JPEG, and records the stages:

    queue  = server_time - send_time - render_ms - encode_ms   (receive, decode, wait for the GPU)
    render = image.render_ms;  encode = image.encode_ms
    send   = receive_time - server_time                        (queue slot, socket, client receive)
    decode = client JPEG decode

Throughput: a simulation streams frames of an N-atom system as fast as the server takes them;
1, 10 and 50 viewers share one view (one render feeds all), then 4 viewers each hold their own
camera (four renders per frame). Frames/s delivered per viewer are counted over a fixed window.
The simulation and the viewers run in two processes of their own, so the server's process
(and its GIL) holds only the server.

    python benchmarks/latency_bench.py                      # GPU run (results JSON + table)
    python benchmarks/latency_bench.py --jpeg-control --no-throughput  # each JPEG path in turn
    python benchmarks/latency_bench.py --quick --device cpu # smoke test on the CPU device
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import multiprocessing as mp
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image as PILImage

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

import latency_stages
from render_bench import build_system, topology_of
from viewer_rate import throughput

import protocol as p
from server.commands.serve import ServerThread
from server.pipeline.encoder import PILLOW
from server.settings import ServerSettings
from tests.server.peers import Peer, frame

RESULTS = ROOT / "benchmarks" / "results"


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def gpu_name(device: str) -> str:
    if not device.startswith("cuda"):
        return f"CPU ({platform.processor() or platform.machine()})"
    import warp as wp

    return str(wp.get_device(device).name)


def start(
    device: str,
    size: tuple[int, int],
    tmp: Path,
    interactive_scale: float | None = None,
    stream_atoms: int = 0,
) -> ServerThread:
    limits = p.Limits(
        max_message_bytes=max(512 << 20, 16 * stream_atoms + (1 << 20)),
        max_atoms=max(12_000_000, stream_atoms),
        max_steer_per_s=1000,
    )
    settings = ServerSettings(
        port=0,
        device=device,
        token="bench",
        viewer_token="bench-view",
        state_dir=tmp,
        default_size=size,
        limits=limits,
        stats_interval_s=5.0,
    )
    if interactive_scale is not None:
        settings = dataclasses.replace(settings, interactive_scale=interactive_scale)
    return ServerThread(settings)


def _steer(url: str, n_atoms: int, changes: int, out: Any) -> None:
    """Child process: a simulation (one frame) and a steerer timing each change to the
    decoded image; puts the per-change rows on `out`."""
    sim = Peer(f"{url}/ws/sim", "simulation", "bench", "latency")
    pos, elements, bonds = build_system(n_atoms)
    sim.send(topology_of(elements, bonds))
    sim.send(frame(pos, 0))
    steer = Peer(f"{url}/ws/view", "steerer", "bench", "latency")
    steer.expect(p.Image, 300)
    rows: list[dict[str, float]] = []
    for i in range(changes + 10):
        t_send = time.time()
        seq = steer.send(p.SetRenderParams(params={"sigma_A": 1.4 + 0.2 * (i % 2)}))
        img = steer.expect(p.Image, 60, where=lambda m, s=seq: m.ref == s)
        t_recv = time.time()
        t0 = time.perf_counter()
        PILImage.open(io.BytesIO(img.data)).load()
        decode_ms = (time.perf_counter() - t0) * 1000
        if i < 10:
            continue  # warm-up
        total = (t_recv - t_send) * 1000 + decode_ms
        rows.append(
            {
                "total": total,
                "queue": max(
                    0.0, (img.server_time - t_send) * 1000 - img.render_ms - img.encode_ms
                ),
                "render": img.render_ms,
                "encode": img.encode_ms,
                "send": max(0.0, (t_recv - img.server_time) * 1000),
                "decode": decode_ms,
                "width": img.width,
                "height": img.height,
            }
        )
    sim.close()
    steer.close()
    out.put(rows)


def _steer_rows(server: ServerThread, n_atoms: int, changes: int) -> list[dict[str, float]]:
    """The per-change stages; the clients run in a process of their own."""
    url = f"ws://127.0.0.1:{server.port}"
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    child = ctx.Process(target=_steer, args=(url, n_atoms, changes, out))
    child.start()
    rows: list[dict[str, float]] = out.get(timeout=600)
    child.join(30)
    return rows


def latency(server: ServerThread, n_atoms: int, changes: int) -> dict[str, Any]:
    """Steer-to-photon percentiles."""
    return summarise(_steer_rows(server, n_atoms, changes), n_atoms)


def jpeg_paths(server: ServerThread) -> dict[str, Callable[[], None]]:
    """How the server can make a viewer's JPEG, each a switch to it: encoded on the render
    device (the `gpu-jpeg` extra on a CUDA device), by that encoder from the host's copy, and
    by Pillow (the default install; the control)."""
    gpu = server.app_state.gpu
    encoder = server.app_state.services.encoder
    lane, chosen = gpu.jpeg, encoder.backend

    def use(on_device: Any, host: Any) -> Callable[[], None]:
        def switch() -> None:
            gpu.jpeg = on_device
            encoder.backend = host

        return switch

    paths: dict[str, Callable[[], None]] = {}
    if lane is not None:
        paths[f"on the device ({lane.name})"] = use(lane, chosen)
    if chosen is not None:
        paths[f"host copy ({chosen.name})"] = use(None, chosen)
    paths[PILLOW] = use(None, None)
    return paths


def latency_by_encoder(
    server: ServerThread, n_atoms: int, changes: int, rounds: int = 2
) -> list[dict[str, Any]]:
    """Steer-to-photon for each way of making the JPEG, taking turns in `rounds` (the
    server's own choice restored after)."""
    paths = jpeg_paths(server)
    rows: dict[str, list[dict[str, float]]] = {label: [] for label in paths}
    try:
        for _ in range(rounds):
            for label, switch in paths.items():
                switch()
                rows[label] += _steer_rows(server, n_atoms, max(1, changes // rounds))
    finally:
        next(iter(paths.values()))()
    return [{"encoder": label, **summarise(r, n_atoms)} for label, r in rows.items()]


def summarise(rows: list[dict[str, float]], n_atoms: int) -> dict[str, Any]:
    result: dict[str, Any] = {
        "n_atoms": n_atoms,
        "changes": len(rows),
        "image": [rows[0]["width"], rows[0]["height"]],
    }
    for key in ("total", "queue", "render", "encode", "send", "decode"):
        vals = [r[key] for r in rows]
        result[key] = {
            "p50": percentile(vals, 50),
            "p95": percentile(vals, 95),
            "p99": percentile(vals, 99),
            "mean": statistics.fmean(vals),
        }
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--latency-atoms", type=int, default=10_000)
    ap.add_argument("--stream-atoms", type=int, default=1_000_000)
    ap.add_argument("--changes", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--quick", action="store_true", help="tiny sizes for a smoke test")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--interactive-scale",
        type=float,
        default=None,
        help="image scale while steering (server default 0.5; 1 = full size at once)",
    )
    ap.add_argument("--no-throughput", action="store_true", help="the latency part only")
    ap.add_argument(
        "--jpeg-control",
        action="store_true",
        help="the latency again for each way of making the JPEG, taking turns (on the device, "
        "from the host's copy, Pillow); each throughput case runs with each of them",
    )
    ap.add_argument(
        "--viewers",
        default="1,10,50,4own",
        help="throughput cases: viewers sharing the view, or N'own' holding cameras of their own",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run the latency part this many times: each run's percentiles, and all pooled",
    )
    ap.add_argument(
        "--stages",
        action="store_true",
        help="also time the stages of each change inside the server (latency_stages.py)",
    )
    ap.add_argument(
        "--prefetch-control",
        action="store_true",
        help="each throughput case also without the next frame's upload overlapped (the control)",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.latency_atoms, args.changes, args.seconds = "96x64", 500, 20, 1.0
        args.stream_atoms = min(args.stream_atoms, 2000)
    w, h = (int(x) for x in args.size.lower().split("x"))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        server = start(args.device, (w, h), Path(tmp), args.interactive_scale, args.stream_atoms)
        try:
            device = server.app_state.gpu.device
            result: dict[str, Any] = {
                "benchmark": "latency_bench",
                "gpu": gpu_name(args.device),
                "device": args.device,
                "size": [w, h],
                "encoder": server.app_state.encoder.describe(),
                "encode_workers": server.settings.encode_workers,
                "date": time.strftime("%Y-%m-%d"),
            }
            print(
                f"latency: {args.changes} changes, {args.latency_atoms} atoms, "
                f"{w}x{h}, {result['gpu']}",
                flush=True,
            )
            runs: list[list[dict[str, float]]] = []
            # the marks only with --stages: the runs without them are the ones quoted
            tracing = latency_stages.traced() if args.stages else contextlib.nullcontext()
            with tracing as marks:
                for _ in range(max(1, args.repeats)):
                    runs.append(_steer_rows(server, args.latency_atoms, args.changes))
            result["latency"] = summarise([row for run in runs for row in run], args.latency_atoms)
            if len(runs) > 1:
                result["latency_runs"] = [summarise(run, args.latency_atoms) for run in runs]
            if marks is not None:
                result["latency_stages"] = latency_stages.summarise(marks.changes())
            print(json.dumps(result["latency"], indent=1), flush=True)
            for run in result.get("latency_runs", []):
                print("run total p50 / p99", run["total"]["p50"], run["total"]["p99"], flush=True)
            if marks is not None:
                print(json.dumps(result["latency_stages"], indent=1), flush=True)
            if args.jpeg_control:
                by = latency_by_encoder(server, args.latency_atoms, args.changes)
                result["latency_by_encoder"] = by
                for row in by:
                    stages = {k: round(row[k]["p50"], 2) for k in ("total", "queue", "encode")}
                    print(row["encoder"], stages, flush=True)
            result["interactive_scale"] = server.settings.interactive_scale
            result["throughput"] = []
            cases = [] if args.no_throughput else [
                (int(c.removesuffix("own")), c.endswith("own")) for c in args.viewers.split(",")
            ]  # fmt: skip
            queue = server.app_state.gpu
            # with --jpeg-control each case also takes turns over the ways of making the JPEG
            paths = jpeg_paths(server) if args.jpeg_control else {}
            for viewers, own in cases:
                for label, switch in paths.items() or [("", lambda: None)]:
                    switch()
                    for prefetch in (False, True) if args.prefetch_control else (True,):
                        queue.prefetch = prefetch
                        row = throughput(server, args.stream_atoms, viewers, own, args.seconds)
                        row["prefetch"] = prefetch
                        if label:
                            row["jpeg"] = label
                        print(json.dumps(row), flush=True)
                        result["throughput"].append(row)
            if paths:
                next(iter(paths.values()))()  # the server's own choice again
            queue.prefetch = True
            del device
        finally:
            server.stop()
    out = args.out or RESULTS / ("latency_quick.json" if args.quick else "latency.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
