"""Frames per second delivered to each viewer of a live stream (the throughput part of
`latency_bench.py`): a simulation streams frames of an N-atom system as fast as the server takes
them, and viewers sharing one view or holding cameras of their own count the images they get.
The simulation and the viewers run in processes of their own, so the server's process (and its
GIL) holds only the server.
"""

from __future__ import annotations

import asyncio
import itertools
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from render_bench import build_system, topology_of

import protocol as p
from server.commands.serve import ServerThread
from tests.server.peers import Peer, frame


def send_cycle(sim: Peer, raw: list[bytes], stop: Any, fps: float | None = None) -> int:
    """Send the encoded frames `raw` round and round until `stop` is set, as fast as the
    server reads them or at `fps`; returns how many were sent."""
    k = 0
    t0 = time.monotonic()
    while not stop.is_set():
        k += 1
        sim.send_raw(raw[k % len(raw)])
        if fps is not None and (wait := t0 + k / fps - time.monotonic()) > 0:
            time.sleep(wait)
    return k


def _stream(url: str, session: str, n_atoms: int, ready: Any, stop: Any, rate: Any) -> None:
    """Child process: a simulation sending frames of an N-atom system as fast as the server
    takes them (messages encoded once beforehand, as a fast adapter would)."""
    sim = Peer(f"{url}/ws/sim", "simulation", "bench", session)
    pos, elements, bonds = build_system(n_atoms)
    sim.send(topology_of(elements, bonds))
    rng = np.random.default_rng(0)
    raw = [
        p.encode(frame((pos + rng.normal(0, 0.05, pos.shape)).astype(np.float32), k))
        for k in range(4)
    ]
    sim.send_raw(raw[0])
    ready.set()
    t0 = time.monotonic()
    k = send_cycle(sim, raw, stop)
    rate.put(k / (time.monotonic() - t0))
    sim.close()


async def _count_images(
    url: str, session: str, viewers: int, own_camera: bool, size: tuple[int, int], seconds: float
) -> list[float]:
    from websockets.asyncio.client import connect

    conns = []
    for _ in range(viewers):
        ws = await connect(f"{url}/ws/view", max_size=None, compression=None, max_queue=4)
        hello = p.Hello(role="viewer", token="bench-view", client="bench", session=session, seq=1)
        await ws.send(p.encode(hello))
        conns.append(ws)
    limits = p.Limits(max_message_bytes=1 << 30)
    if own_camera:  # the session's camera, turned about y by a different angle per viewer
        base = None
        while base is None:
            msg = p.decode(await conns[0].recv(), limits)
            if isinstance(msg, p.State) and msg.camera is not None:
                base = msg.camera
        for k, ws in enumerate(conns):
            angle = 0.4 * (k + 1)
            q = (float(np.cos(angle / 2)), 0.0, float(np.sin(angle / 2)), 0.0)
            view = p.View(camera=base.model_copy(update={"orientation": q}), width=size[0],
                          height=size[1], seq=2)  # fmt: skip
            await ws.send(p.encode(view))
    counts = [0] * viewers

    async def read(k: int) -> None:
        async for raw in conns[k]:
            if isinstance(raw, bytes) and b"\xa5image" in raw[:16]:
                counts[k] += 1

    tasks = [asyncio.create_task(read(k)) for k in range(viewers)]
    while min(counts) == 0:  # every viewer has its first image
        await asyncio.sleep(0.05)
    await asyncio.sleep(2.0)  # steady state
    start = list(counts)
    t0 = time.monotonic()
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - t0
    per_viewer = [(c - s) / elapsed for c, s in zip(counts, start, strict=True)]
    for t in tasks:
        t.cancel()
    for ws in conns:
        await ws.close()
    return per_viewer


def _viewers(
    url: str,
    session: str,
    viewers: int,
    own_camera: bool,
    size: tuple[int, int],
    seconds: float,
    out: Any,
) -> None:
    """Child process: all viewer connections on one asyncio loop, counting images."""
    out.put(asyncio.run(_count_images(url, session, viewers, own_camera, size, seconds)))


_RUNS = itertools.count()


def throughput(
    server: ServerThread, n_atoms: int, viewers: int, own_camera: bool, seconds: float
) -> dict[str, Any]:
    """Frames/s delivered per viewer. The simulation and the viewers run in processes of
    their own, so the server's process holds only the server."""
    url = f"ws://127.0.0.1:{server.port}"
    session = f"tp-{viewers}-{int(own_camera)}-{next(_RUNS)}"
    ctx = mp.get_context("spawn")
    ready, stop, out, rate = ctx.Event(), ctx.Event(), ctx.Queue(), ctx.Queue()
    streamer = ctx.Process(target=_stream, args=(url, session, n_atoms, ready, stop, rate))
    streamer.start()
    try:
        if not ready.wait(300):
            raise TimeoutError("the simulation process did not start streaming")
        size = server.settings.default_size
        args = (url, session, viewers, own_camera, size, seconds, out)
        counter = ctx.Process(target=_viewers, args=args)
        counter.start()
        per_viewer: list[float] = out.get(timeout=300)
        counter.join(30)
    finally:
        stop.set()
        sent = rate.get(timeout=60) if streamer.is_alive() else None
        streamer.join(30)
        if streamer.is_alive():
            streamer.terminate()
    state = server.app_state.sessions.get(session)
    return {
        "n_atoms": n_atoms,
        "viewers": viewers,
        "own_camera": own_camera,
        "fps_per_viewer_mean": statistics.fmean(per_viewer),
        "fps_per_viewer_min": min(per_viewer),
        "render_timings_ms": state.last_timings if state else {},
        "encode_ms": state.delivery.last_encode_ms if state else None,
        "sim_frames_per_s": sent,
    }
