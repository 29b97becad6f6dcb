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

    python benchmarks/latency_bench.py                      # GPU run (results JSON + table)
    python benchmarks/latency_bench.py --quick --device cpu # smoke test on the CPU device
"""

from __future__ import annotations

import argparse
import io
import json
import platform
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image as PILImage

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from render_bench import build_system, topology_of

import protocol as p
from server.serve import ServerThread
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


def start(device: str, size: tuple[int, int], tmp: Path) -> ServerThread:
    limits = p.Limits(
        max_message_bytes=512 * 1024 * 1024, max_atoms=12_000_000, max_steer_per_s=1000
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
    return ServerThread(settings)


def latency(server: ServerThread, n_atoms: int, changes: int) -> dict[str, Any]:
    url = f"ws://127.0.0.1:{server.port}"
    sim = Peer(f"{url}/ws/sim", "simulation", "bench", "latency")
    pos, elements = build_system(n_atoms)
    sim.send(topology_of(elements))
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
        PILImage.open(io.BytesIO(img.data)).convert("RGB").load()
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
    out: dict[str, Any] = {
        "n_atoms": n_atoms,
        "changes": len(rows),
        "image": [rows[0]["width"], rows[0]["height"]],
    }
    for key in ("total", "queue", "render", "encode", "send", "decode"):
        vals = [r[key] for r in rows]
        out[key] = {
            "p50": percentile(vals, 50),
            "p95": percentile(vals, 95),
            "p99": percentile(vals, 99),
            "mean": statistics.fmean(vals),
        }
    return out


def throughput(
    server: ServerThread, n_atoms: int, viewers: int, own_camera: bool, seconds: float
) -> dict[str, Any]:
    url = f"ws://127.0.0.1:{server.port}"
    session = f"tp-{viewers}-{int(own_camera)}"
    sim = Peer(f"{url}/ws/sim", "simulation", "bench", session)
    pos, elements = build_system(n_atoms)
    sim.send(topology_of(elements))
    rng = np.random.default_rng(0)
    frames = [(pos + rng.normal(0, 0.05, pos.shape)).astype(np.float32) for _ in range(4)]
    sim.send(frame(frames[0], 0))
    peers = [
        Peer(f"{url}/ws/view", "viewer", "bench-view", session, max_queue=4) for _ in range(viewers)
    ]
    base = peers[0].expect(p.State, 60, where=lambda m: m.camera is not None).camera
    assert base is not None
    if own_camera:
        for k, peer in enumerate(peers):
            angle = 0.4 * (k + 1)
            q = (float(np.cos(angle / 2)), 0.0, float(np.sin(angle / 2)), 0.0)
            w, h = server.settings.default_size
            peer.send(p.View(camera=base.model_copy(update={"orientation": q}), width=w, height=h))
    for peer in peers:
        peer.expect(p.Image, 300)
    stop = threading.Event()
    counts = [0] * viewers

    def read(k: int) -> None:
        while not stop.is_set():
            try:
                raw = peers[k].ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:
                return
            if isinstance(raw, bytes) and b"\xa5image" in raw[:16]:
                counts[k] += 1

    def stream() -> None:
        step = 0
        while not stop.is_set():
            step += 1
            sim.send(frame(frames[step % len(frames)], step))

    readers = [threading.Thread(target=read, args=(k,), daemon=True) for k in range(viewers)]
    for t in readers:
        t.start()
    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    time.sleep(2.0)  # reach steady state
    start_counts = list(counts)
    t0 = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - t0
    per_viewer = [(c - s) / elapsed for c, s in zip(counts, start_counts, strict=True)]
    stop.set()
    streamer.join(10)
    for t in readers:
        t.join(5)
    state = server.app_state.sessions.get(session)
    for peer in [*peers, sim]:
        peer.close()
    return {
        "n_atoms": n_atoms,
        "viewers": viewers,
        "own_camera": own_camera,
        "fps_per_viewer_mean": statistics.fmean(per_viewer),
        "fps_per_viewer_min": min(per_viewer),
        "render_timings_ms": state.last_timings if state else {},
        "encode_ms": state.last_encode_ms if state else None,
    }


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
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.latency_atoms, args.changes, args.seconds = "96x64", 500, 20, 1.0
        args.stream_atoms = min(args.stream_atoms, 2000)
    w, h = (int(x) for x in args.size.lower().split("x"))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        server = start(args.device, (w, h), Path(tmp))
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
            result["latency"] = latency(server, args.latency_atoms, args.changes)
            print(json.dumps(result["latency"], indent=1), flush=True)
            result["throughput"] = []
            for viewers, own in ((1, False), (10, False), (50, False), (4, True)):
                row = throughput(server, args.stream_atoms, viewers, own, args.seconds)
                print(json.dumps(row), flush=True)
                result["throughput"].append(row)
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
