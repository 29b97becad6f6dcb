"""JPEG against video for the live stream, side by side in one run: bit rate, encode time and CPU,
image quality against the raw render, and steer-to-photon latency on loopback and through an
emulated 50 Mbit/s link with 40 ms round trip (`linkemu.py`, a throttling proxy on loopback).

Two systems: villin (a recorded OpenMM trajectory of the demo's villin headpiece, 582 atoms,
`data/villin_traj.npz`, made by `--record-villin`) and a 1,000,000-atom protein-like system
whose atoms move smoothly (0.3 A breathing, 120 frames per cycle). Frames come at 60 per second.

- **quality**: 120 consecutive frames rendered at the stream size; each encoded as the server
  would (JPEG at the default quality 85; H.264 at the bit rate the server gives a 1080p canvas,
  frames stamped at 60 fps, on CUDA from the device's I420 planes, with a swscale row beside
  it), decoded, and compared with the raw render (PSNR over RGB). Encode time per frame and
  CPU cores used while encoding (process CPU time / wall time).
- **live**: the real server (its process holds nothing else), a simulation streaming 60 frames/s
  and a steerer that decodes every image (PyAV, Pillow), acknowledges each as the dashboard
  does, and changes the iso level 4 times a second, timing each change to the decoded
  image that shows it. Delivered bit rate and frames/s over the window; the server's CPU.
  `--steer orbit` turns the steerer's own camera instead (2 degrees a change, as a drag on the
  dashboard does), `--change-hz` sets how often; rows then count keyframes too.

    python benchmarks/video_bench.py --device cuda:0            # GPU run, results JSON + table
    python benchmarks/video_bench.py --quick --device cpu       # smoke test
    python benchmarks/video_bench.py --record-villin            # (re)make the villin frames

Kept whole: one benchmark is one file that runs on its own on a GPU host, and its quality and live
rows share the systems, the encoders and the trace of the server they measure.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import io
import json
import multiprocessing as mp
import platform
import socket
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from linkemu import run as run_link
from render_bench import build_system, topology_of
from viewer_rate import send_cycle

import protocol as p
from server.commands.serve import ServerThread
from server.settings import ServerSettings
from tests.server.peers import Peer, frame

RESULTS = ROOT / "benchmarks" / "results"
VILLIN = ROOT / "benchmarks" / "data" / "villin_traj.npz"
CYCLE = 120


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


# ---------------------------------------------------------------- systems


def record_villin(frames: int = CYCLE, steps: int = 25) -> None:
    """A real villin trajectory from the demo's OpenMM system: `frames` frames `steps` steps
    apart (50 fs), after a short equilibration."""
    from simulation_adapters.openmm_systems import build_villin_simulation
    from simulation_adapters.openmm_topology import topology_message

    sim = build_villin_simulation(platform="CPU")
    sim.step(500)
    out = []
    for _ in range(frames):
        sim.step(steps)
        state = sim.context.getState(getPositions=True)
        out.append(np.asarray(state.getPositions(asNumpy=True)._value, np.float32) * 10.0)
    topo = topology_message(sim.topology, sim.system)
    np.savez_compressed(
        VILLIN,
        positions=np.stack(out),
        elements=np.asarray(topo.elements),
        bonds=topo.bonds.to_numpy().astype(np.int32),
    )
    print(f"wrote {VILLIN}: {len(out)} frames of {out[0].shape[0]} atoms")


class System:
    """Frames of one benchmark system, k = 0, 1, ... (cyclic, smooth across the wrap)."""

    def __init__(self, name: str, n_atoms: int = 1_000_000) -> None:
        self.name = name
        if name == "villin":
            data = np.load(VILLIN)
            self.traj = data["positions"]
            # there and back: no jump where the cycle wraps
            self.traj = np.concatenate([self.traj, self.traj[::-1]])
            self.elements = data["elements"]
            self.bonds = data["bonds"]
            self.base = self.traj[0]
        else:
            self.base, self.elements, self.bonds = build_system(n_atoms)
            rng = np.random.default_rng(1)
            self.phase = rng.uniform(0, 2 * np.pi, len(self.base)).astype(np.float32)
            d = rng.normal(size=self.base.shape).astype(np.float32)
            self.direction = 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)

    @property
    def n_atoms(self) -> int:
        return len(self.base)

    def topology(self) -> p.Topology:
        return topology_of(self.elements, self.bonds)

    def positions(self, k: int) -> np.ndarray:
        if self.name == "villin":
            return self.traj[k % len(self.traj)]
        s = np.sin(self.phase + np.float32(2 * np.pi * k / CYCLE))
        return self.base + self.direction * s[:, None]


# ---------------------------------------------------------------- quality and encode cost


def warm_kernels(system: System, device: str, size: tuple[int, int]) -> None:
    """Render the system once at the stream size and at the interactive size, so that the
    live rows never wait for a kernel to compile (the quality section does this otherwise)."""
    from protocol import RenderParams
    from server.render import Renderer
    from server.render.camera import fit_camera

    renderer = Renderer(device, max_atoms=max(system.n_atoms, 1))
    renderer.set_topology(system.topology())
    renderer.set_positions(system.positions(0))
    for w, h in (size, (size[0] // 2, size[1] // 2)):
        renderer.render(RenderParams(), fit_camera(system.base, w, h), w, h)
        renderer.read_rgba()


def quality(system: System, device: str, size: tuple[int, int], frames: int) -> dict[str, Any]:
    """Encode `frames` raw renders both ways and compare the decoded images with them."""
    import av

    from protocol import RenderParams
    from server.pipeline.encoder import select_encoder
    from server.pipeline.video import VideoEncoder, VideoEncoders
    from server.render import Renderer
    from server.render.camera import fit_camera
    from server.settings import ServerSettings as S

    renderer = Renderer(device)
    renderer.set_topology(system.topology())
    cam = fit_camera(system.base, *size)
    jpeg = select_encoder(device)
    codec_name = VideoEncoders(("h264",)).chosen()["h264"]
    kbps = max(S.video_min_kbps, S.video_kbps_per_mpixel * size[0] * size[1] / 1e6)
    variants = [(None, None)]  # the server's own choice first
    on_cuda = device.startswith("cuda")
    if on_cuda:  # the server's choice converts on the device; this row converts with swscale
        variants += [("swscale", None)]
    if codec_name == "libx264":
        variants += [(pr, th) for pr in ("superfast", "veryfast", "faster") for th in (8, 16)]
        variants += [("ultrafast", 8)]
    videos = {
        "h264" if pr is None else "h264-swscale" if pr == "swscale" else f"h264-{pr}-{th}t": (
            VideoEncoder(
                "h264", codec_name, *size, kbps, preset=None if pr == "swscale" else pr, threads=th
            )
        )
        for pr, th in variants
    }
    decoders: dict[str, Any] = {k: av.CodecContext.create("h264", "r") for k in videos}
    rows: dict[str, dict[str, list[float]]] = {
        k: {"bytes": [], "ms": [], "psnr": [], "cpu": [], "wall": []} for k in ["jpeg", *videos]
    }
    from PIL import Image

    for k in range(frames):
        renderer.set_positions(system.positions(k), check_finite=False)
        renderer.render(RenderParams(), cam, *size)
        rgba = renderer.read_rgba()
        raw = rgba[..., :3]
        i420 = renderer.read_i420(size) if on_cuda else None  # as the server's device thread
        c0, w0 = time.process_time(), time.perf_counter()
        data, _ = jpeg.encode(rgba, "jpeg", 85)
        c1, w1 = time.process_time(), time.perf_counter()
        r = rows["jpeg"]
        r["bytes"].append(len(data))
        r["ms"].append((w1 - w0) * 1e3)
        r["cpu"].append(c1 - c0)
        r["wall"].append(w1 - w0)
        r["psnr"].append(psnr(np.asarray(Image.open(io.BytesIO(data)).convert("RGB")), raw))
        for name, video in videos.items():
            c0, w0 = time.process_time(), time.perf_counter()
            planes = i420 if name == "h264" else None
            enc = video.encode(rgba, pts_ms=round(k * 1000 / 60), i420=planes)
            c1, w1 = time.process_time(), time.perf_counter()
            r = rows[name]
            r["bytes"].append(len(enc.data))
            r["ms"].append((w1 - w0) * 1e3)
            r["cpu"].append(c1 - c0)
            r["wall"].append(w1 - w0)
            (decoded,) = decoders[name].decode(av.Packet(enc.data))
            rgb = decoded.reformat(format="rgb24", src_colorspace="ITU709").to_ndarray()
            r["psnr"].append(psnr(rgb[: size[1], : size[0]], raw))
    out: dict[str, Any] = {"frames": frames, "size": list(size), "h264_encoder": codec_name,
                           "jpeg_encoder": jpeg.describe(), "h264_target_kbps": kbps}  # fmt: skip
    for name, r in rows.items():
        out[name] = {
            "mbit_per_s_at_60fps": sum(r["bytes"]) * 8 / (frames / 60) / 1e6,
            "bytes_per_frame_mean": float(np.mean(r["bytes"])),
            "encode_ms_p50": percentile(r["ms"], 50),
            "encode_ms_p99": percentile(r["ms"], 99),
            "cores_while_encoding": sum(r["cpu"]) / sum(r["wall"]),
            "psnr_db_mean": float(np.mean(r["psnr"])),
            "psnr_db_min": float(np.min(r["psnr"])),
        }
    return out


# ---------------------------------------------------------------- live stream


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _simulate(
    url: str,
    system_name: str,
    n_atoms: int,
    session: str,
    ready: Any,
    stop: Any,
    fragment: bool = True,
) -> None:
    """Child process: a simulation sending 60 frames/s (large frames in fragments, as the
    adapters send them, unless `fragment` is False)."""
    system = System(system_name, n_atoms)
    # encoded beforehand, as a fast adapter would: the benchmark measures the server's stream
    cycle = len(system.traj) if system_name == "villin" else CYCLE
    raw = [p.encode(frame(system.positions(k), k)) for k in range(cycle)]
    sim = Peer(f"{url}/ws/sim", "simulation", "bench", session)
    sim.fragment = fragment
    sim.send(system.topology())
    sim.send_raw(raw[0])
    ready.set()
    send_cycle(sim, raw, stop, fps=60.0)
    sim.close()


def turned(camera: p.Camera, degrees: float) -> p.Camera:
    """`camera` orbited by `degrees` about the world's y axis (quaternions are (w, x, y, z))."""
    half = np.radians(degrees) / 2
    rw, ry = float(np.cos(half)), float(np.sin(half))
    w, x, y, z = camera.orientation
    q = (rw * w - ry * y, rw * x + ry * z, rw * y + ry * w, rw * z - ry * x)
    n = sum(c * c for c in q) ** 0.5
    return camera.model_copy(update={"orientation": tuple(c / n for c in q)})


def _steer(
    url: str,
    session: str,
    video: bool,
    size: tuple[int, int],
    seconds: float,
    out: Any,
    steer: str = "iso",
    change_hz: float = 4.0,
) -> None:
    """Child process: a steerer decoding every image (and acknowledging each), timing
    iso-level changes (or turns of its camera) to the decoded image that shows them."""
    import av
    from PIL import Image

    peer = Peer(f"{url}/ws/view", "steerer", "bench", session)
    # the session's camera, which frames the molecule, as the dashboard takes it on joining
    camera = None
    deadline = time.monotonic() + 60
    while camera is None and time.monotonic() < deadline:
        with contextlib.suppress(TimeoutError):
            got = peer.recv(0.5)
            if isinstance(got, p.State) and got.camera is not None:
                camera = got.camera
    if camera is None:
        raise RuntimeError("the session sent no camera")
    codecs: list[p.VideoCodec] = ["h264"] if video else []
    peer.send(p.View(camera=camera, width=size[0], height=size[1], video=codecs))
    decoder: Any = None
    keyframes = 0
    stream = None
    pending: dict[int, tuple[float, float]] = {}
    latencies: list[float] = []
    changes: list[tuple[Any, ...]] = []
    decode_ms: list[float] = []
    encode_ms: list[float] = []
    got_bytes = 0
    got_frames = 0
    formats: set[str] = set()
    kbps: list[float] = []
    start = time.monotonic()
    measure_from = start + 3.0
    end = measure_from + seconds
    next_change = start + 0.5  # changes from the start: the first ones warm every path up
    k = 0
    while (now := time.monotonic()) < end:
        if now >= next_change:
            k += 1
            if steer == "orbit":
                camera = turned(camera, 2.0)
                view = p.View(
                    camera=camera, width=size[0], height=size[1], video=codecs, interacting=True
                )  # as a drag on the dashboard sends it
                seq = peer.send(view)
            else:
                seq = peer.send(p.SetRenderParams(params={"iso_level": 0.25 + 0.01 * (k % 2)}))
            if now >= measure_from:
                pending[seq] = (time.perf_counter(), time.time())
            next_change += 1.0 / change_hz
        try:
            # wait no longer than the next change: a change goes when it is due, not when an
            # image happens to arrive (that would tie every change to the server's passes)
            msg = peer.recv(max(0.0005, min(0.05, next_change - time.monotonic())))
        except TimeoutError:
            continue
        if not isinstance(msg, p.Image):
            continue
        t0, arrived = time.perf_counter(), time.time()
        if msg.format == "jpeg":
            Image.open(io.BytesIO(msg.data)).convert("RGB")
            peer.send(p.FrameAck(frame_id=msg.frame_id))  # the dashboard acknowledges images too
        else:
            if msg.stream != stream:
                decoder = av.CodecContext.create("h264", "r")
                stream = msg.stream
            for f in decoder.decode(av.Packet(msg.data)):
                f.to_ndarray(format="rgb24")
            peer.send(p.FrameAck(frame_id=msg.frame_id))
        t1 = time.perf_counter()
        if time.monotonic() < measure_from:
            continue
        got_frames += 1
        got_bytes += len(msg.data)
        keyframes += bool(msg.key)
        formats.add(msg.format)
        decode_ms.append((t1 - t0) * 1e3)
        encode_ms.append(msg.encode_ms)
        if msg.bitrate_kbps:
            kbps.append(msg.bitrate_kbps)
        if msg.ref in pending:
            sent, sent_wall = pending.pop(msg.ref)
            latencies.append((t1 - sent) * 1e3)
            # the image is stamped when packed, after its encode (one host, one clock)
            changes.append(
                (msg.ref, sent_wall, msg.frame_id, msg.server_time, msg.encode_ms, arrived, t1 - t0)
            )
            for s in [s for s in pending if s < (msg.ref or 0)]:
                pending.pop(s)  # superseded before it was shown: not a photon of its own
    peer.close()
    out.put(
        {
            "formats": sorted(formats),
            "delivered_fps": got_frames / seconds,
            "delivered_mbit_per_s": got_bytes * 8 / seconds / 1e6,
            "stream_target_kbps_median": percentile(kbps, 50) if kbps else None,
            "encode_ms_p50": percentile(encode_ms, 50),
            "client_decode_ms_p50": percentile(decode_ms, 50),
            "steer_to_photon_ms_p50": percentile(latencies, 50),
            "steer_to_photon_ms_p99": percentile(latencies, 99),
            "changes_timed": len(latencies),
            "keyframes": keyframes,
            "changes": changes,
        }
    )


def live(
    server: ServerThread,
    system_name: str,
    n_atoms: int,
    video: bool,
    link: str,
    size: tuple[int, int],
    seconds: float,
    trace: Trace | None = None,
    steer: str = "iso",
    change_hz: float = 4.0,
    fragment: bool = True,
) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    session = f"{system_name}-{'video' if video else 'jpeg'}-{link}"
    ready, stop, out, link_ready = ctx.Event(), ctx.Event(), ctx.Queue(), ctx.Event()
    direct = f"ws://127.0.0.1:{server.port}"
    sim = ctx.Process(
        target=_simulate, args=(direct, system_name, n_atoms, session, ready, stop, fragment)
    )
    sim.start()
    proxy = None
    url = direct
    if link == "emulated":
        port = _free_port()
        proxy = ctx.Process(target=run_link, args=(port, server.port, 50.0, 40.0, link_ready))
        proxy.start()
        link_ready.wait(30)
        url = f"ws://127.0.0.1:{port}"
    try:
        if not ready.wait(600):
            raise TimeoutError("the simulation did not start")
        steerer = ctx.Process(
            target=_steer, args=(url, session, video, size, seconds, out, steer, change_hz)
        )
        steerer.start()
        time.sleep(3.0)
        c0, w0 = time.process_time(), time.perf_counter()
        if trace is not None:
            trace.pauses.clear()
            if trace.stalls is not None:
                trace.stalls.reset()
        row: dict[str, Any] = out.get(timeout=600)
        cores = (time.process_time() - c0) / (time.perf_counter() - w0)
        steerer.join(30)
    finally:
        stop.set()
        sim.join(30)
        for proc in (sim, proxy):
            if proc is not None and proc.is_alive():
                proc.terminate()
    changes = row.pop("changes")
    if trace is not None:
        row["stages_ms"] = trace.breakdown(session, changes)
        row["timeline"] = trace.timeline(session, changes)
        row["gc_pauses_ms"] = trace.gc_summary()
        if trace.stalls is not None:
            row["loop_stalls"] = trace.stalls.summary()
    row.update(
        {
            "system": system_name,
            "transport": "h264" if video else "jpeg",
            "link": link,
            "steer": steer,
            "change_hz": change_hz,
            "server_cores": cores,
        }
    )
    return row


class LoopStalls:
    """Where the server's event loop is when it stalls (`--stalls`, a diagnostic): a task on
    the loop ticks every millisecond; a watchdog thread that sees no tick for `after_ms` takes
    the loop thread's stack (and the innermost frame of every other thread) each millisecond
    until the loop ticks again."""

    def __init__(self, after_ms: float = 3.0) -> None:
        self.after_s = after_ms / 1e3
        self.last_tick = time.perf_counter()
        self.loop_thread: int | None = None
        self.stalls: list[float] = []
        self.samples: collections.Counter[str] = collections.Counter()
        self.others: collections.Counter[str] = collections.Counter()
        self._stalled_since: float | None = None

    def start(self) -> None:
        """Called on the loop (the first render pass): starts the ticker and the watchdog."""
        if self.loop_thread is not None:
            return
        self.loop_thread = threading.get_ident()
        asyncio.get_running_loop().create_task(self._tick())
        threading.Thread(target=self._watch, daemon=True, name="stall-watch").start()

    def reset(self) -> None:
        self.stalls.clear()
        self.samples.clear()
        self.others.clear()

    async def _tick(self) -> None:
        while True:
            self.last_tick = time.perf_counter()
            await asyncio.sleep(0.001)

    def _watch(self) -> None:
        import traceback

        while True:
            time.sleep(0.001)
            now = time.perf_counter()
            late = now - self.last_tick
            if late < self.after_s:
                if self._stalled_since is not None:
                    self.stalls.append((now - self._stalled_since) * 1e3)
                    self._stalled_since = None
                continue
            if self._stalled_since is None:
                self._stalled_since = self.last_tick
            frames = sys._current_frames()
            loop_frame = frames.get(self.loop_thread or -1)
            if loop_frame is not None:
                stack = traceback.extract_stack(loop_frame)[-6:]
                self.samples[
                    " < ".join(
                        f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(stack)
                    )
                ] += 1
            for tid, other in frames.items():
                if tid not in (self.loop_thread, threading.get_ident()):
                    code = other.f_code
                    self.others[
                        f"{Path(code.co_filename).name}:{other.f_lineno} {code.co_name}"
                    ] += 1

    def summary(self) -> dict[str, Any]:
        return {
            "count": len(self.stalls),
            "total_ms": sum(self.stalls),
            "p50_ms": percentile(self.stalls, 50) if self.stalls else 0.0,
            "max_ms": max(self.stalls, default=0.0),
            "loop_stacks": self.samples.most_common(12),
            "other_threads": self.others.most_common(12),
        }


class Trace:
    """Server-side stamps (wall clock) of each timed change, for the latency breakdown: when
    the steer message (or view) was handled, and when the render that drew it was asked for
    and done. The server runs in this process, so its session methods are wrapped here."""

    def __init__(self) -> None:
        from server.pipeline.gpu import GpuQueue
        from server.session.render_loop import RenderLoop
        from server.session.session import Session

        self.steered: dict[tuple[str, int], float] = {}
        self.renders: dict[tuple[str, int], tuple[float, float, dict[str, float], int]] = {}
        self.device_calls: list[tuple[float, float]] = []
        self.last_request: Any = None
        steer, render, render_sync = Session.steer, RenderLoop._render, GpuQueue.render_sync
        set_view = Session.set_view
        render_group = RenderLoop._render_group
        self.groups: list[float] = []
        self.stalls: LoopStalls | None = None
        self.pauses: list[tuple[int, float, float]] = []
        """The server process's garbage collections: (generation, wall start, ms)."""
        self._gc_start = 0.0
        trace = self

        def on_gc(phase: str, info: dict[str, int]) -> None:
            if phase == "start":
                trace._gc_start = time.perf_counter()
            else:
                ms = (time.perf_counter() - trace._gc_start) * 1e3
                trace.pauses.append((info["generation"], time.time() - ms / 1e3, ms))

        import gc

        gc.callbacks.append(on_gc)

        async def traced_group(loop: Any, *args: Any) -> Any:
            trace.groups.append(time.time())
            if trace.stalls is not None:
                trace.stalls.start()
            return await render_group(loop, *args)

        def traced_sync(queue: Any, request: Any) -> Any:
            t0 = time.time()
            out = render_sync(queue, request)
            trace.device_calls.append((t0, time.time()))
            trace.last_request = request
            return out

        def traced_steer(session: Any, client: Any, message: Any) -> None:
            if message.seq is not None:
                trace.steered[(session.id, message.seq)] = time.time()
            steer(session, client, message)

        def traced_view(session: Any, client: Any, view: Any) -> None:
            if view.seq is not None:  # a turn of the camera (--steer orbit)
                trace.steered[(session.id, view.seq)] = time.time()
            set_view(session, client, view)

        async def traced_render(loop: Any, key: Any, snap: Any, *more: Any) -> Any:
            t0 = time.time()
            out = await render(loop, key, snap, *more)
            if out is not None:
                span = (t0, time.time(), dict(out.out.timings), out.width * out.height)
                trace.renders[(loop.session_id, out.image_id)] = span
            return out

        Session.steer = traced_steer  # type: ignore[method-assign,assignment]
        Session.set_view = traced_view  # type: ignore[method-assign]
        RenderLoop._render = traced_render  # type: ignore[method-assign,assignment]
        GpuQueue.render_sync = traced_sync  # type: ignore[method-assign]
        RenderLoop._render_group = traced_group  # type: ignore[method-assign]

    def gc_summary(self) -> dict[str, Any]:
        """Collections during the row by generation: count, total and longest pause (ms)."""
        out: dict[str, Any] = {}
        for gen in (0, 1, 2):
            ms = [p[2] for p in self.pauses if p[0] == gen]
            out[f"gen{gen}"] = {"count": len(ms), "total": sum(ms), "max": max(ms, default=0.0)}
        return out

    def breakdown(self, session: str, changes: list[tuple[Any, ...]]) -> dict[str, Any]:
        """Each change's path in ms, p50 and p99 per stage: up (the link and the event loop
        until the steer is handled), queued (until its render is asked for: the render in
        progress), render (the device queue, upload, render and read-back), encoder (waiting
        for the stream's encoder), encode, down (packing, sending, the link), decode. The
        render splits into to_device (until the device thread starts it), device_call (its
        call there: upload, render, read-back, and any wait for the interpreter lock), of
        which device_ms is the device's own time, and back (until the event loop has it)."""
        names = ("up", "queued", "render", "encoder", "encode", "down", "decode")
        more = (
            "to_device",
            "device_call",
            "device_ms",
            "back",
            "upload_ms",
            "grid_ms",
            "raycast_ms",
        )
        more += ("pixels", "loop_busy", "slot_wait")
        stages: dict[str, list[float]] = {k: [] for k in names + more}
        for seq, sent, image_id, packed, encode_ms, arrived, decode_s in changes:
            handled = self.steered.get((session, seq))
            span = self.renders.get((session, image_id))
            if handled is None or span is None:
                continue
            encode_start = packed - encode_ms / 1e3
            for k, v in (
                ("up", handled - sent),
                ("queued", span[0] - handled),
                ("render", span[1] - span[0]),
                ("encoder", encode_start - span[1]),
                ("encode", encode_ms / 1e3),
                ("down", arrived - packed),
                ("decode", decode_s),
            ):
                stages[k].append(v * 1e3)
            calls = [c for c in self.device_calls if span[0] <= c[0] and c[1] <= span[1]]
            if calls:
                call = calls[-1]
                stages["to_device"].append((call[0] - span[0]) * 1e3)
                stages["device_call"].append((call[1] - call[0]) * 1e3)
                stages["back"].append((span[1] - call[1]) * 1e3)
            stages["device_ms"].append(span[2].get("total", 0.0))
            stages["upload_ms"].append(span[2].get("upload", 0.0))
            stages["grid_ms"].append(span[2].get("grid", 0.0))
            stages["raycast_ms"].append(span[2].get("raycast", 0.0))
            stages["pixels"].append(span[3])
            starts = [g for g in self.groups if handled <= g <= span[0]]
            if starts:  # the render loop took up the change, then waited for an encode slot
                stages["loop_busy"].append((starts[0] - handled) * 1e3)
                stages["slot_wait"].append((span[0] - starts[-1]) * 1e3)
        return {k: {"p50": percentile(v, 50), "p99": percentile(v, 99)} for k, v in stages.items()}

    def timeline(self, session: str, changes: list[tuple[Any, ...]]) -> list[dict[str, Any]]:
        """Each timed change with what the server did around it, in ms from its handling:
        render-loop passes, device calls and the render that drew it."""
        out = []
        for seq, sent, image_id, packed, encode_ms, arrived, _decode in changes:
            handled = self.steered.get((session, seq))
            span = self.renders.get((session, image_id))
            if handled is None or span is None:
                continue

            def ms(t: float, at: float = handled) -> float:
                return round((t - at) * 1e3, 2)

            lo, hi = handled - 0.05, arrived
            out.append(
                {
                    "sent": ms(sent),
                    "render": [ms(span[0]), ms(span[1])],
                    "encode_start": ms(packed - encode_ms / 1e3),
                    "packed": ms(packed),
                    "arrived": ms(arrived),
                    "passes": [ms(g) for g in self.groups if lo <= g <= hi],
                    "device_calls": [[ms(a), ms(b)] for a, b in self.device_calls if lo <= a <= hi],
                }
            )
        return out


def gpu_name(device: str) -> str:
    if not device.startswith("cuda"):
        return f"CPU ({platform.processor() or platform.machine()})"
    import warp as wp

    return str(wp.get_device(device).name)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--frames", type=int, default=CYCLE)
    ap.add_argument("--systems", default="villin,1m")
    ap.add_argument("--quick", action="store_true", help="small sizes and short windows")
    ap.add_argument("--live-only", action="store_true", help="skip the quality section")
    ap.add_argument("--links", default="loopback,emulated")
    ap.add_argument("--transports", default="jpeg,h264")
    ap.add_argument(
        "--encode-every-frame",
        action="store_true",
        help="the baseline: video streams encode frames that show a waiting viewer nothing new",
    )
    ap.add_argument("--steer", choices=["iso", "orbit"], default="iso")
    ap.add_argument("--change-hz", type=float, default=4.0)
    ap.add_argument(
        "--stream-per-camera",
        action="store_true",
        help="the baseline: a viewer's video stream restarts (at a keyframe) on every camera move",
    )
    ap.add_argument(
        "--host-convert",
        action="store_true",
        help="the baseline: video frames converted to I420 (and scaled) by swscale on the host",
    )
    ap.add_argument(
        "--whole-frames",
        action="store_true",
        help="the baseline: the simulation sends each frame in one WebSocket frame, unfragmented",
    )
    ap.add_argument(
        "--no-settle",
        action="store_true",
        help="the baseline: a large topology leaves the heap to the collector (server.heap)",
    )
    ap.add_argument(
        "--always-rgba",
        action="store_true",
        help="the baseline: renders for video viewers only read the RGBA image back too",
    )
    ap.add_argument(
        "--no-stage",
        action="store_true",
        help="the baseline: frames upload from where they arrived (no page-locked staging)",
    )
    ap.add_argument(
        "--switch-interval",
        type=float,
        help="the interpreter's thread switch interval in seconds for the server (a variant)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a server setting for a variant run (repeatable), e.g. encode_workers=2",
    )
    ap.add_argument(
        "--stalls",
        action="store_true",
        help="a diagnostic: sample where the server's event loop is whenever it stalls 3 ms",
    )
    ap.add_argument("--record-villin", action="store_true")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    if args.record_villin:
        record_villin()
        return 0
    size = (640, 360) if args.quick else tuple(int(v) for v in args.size.split("x"))
    seconds = 3.0 if args.quick else args.seconds
    frames = 12 if args.quick else args.frames
    systems = args.systems.split(",")
    result: dict[str, Any] = {
        "benchmark": "video",
        "device": gpu_name(args.device),
        "host_cpus": mp.cpu_count(),
        "size": list(size),
        "link": "throttling proxy on loopback (benchmarks/linkemu.py): 50 Mbit/s each way, "
        "20 ms each way, 1.5 MB queue",
        "quality": {},
        "live": [],
    }
    from server.pipeline.video import VideoEncoders

    result["video_encoders"] = VideoEncoders(ServerSettings.video_codecs).describe()
    print(json.dumps(result["video_encoders"]), flush=True)
    n_big = 20_000 if args.quick else 1_000_000
    for name in systems if args.live_only else []:
        warm_kernels(System(name, n_big), args.device, size)
    for name in [] if args.live_only else systems:
        system = System(name, n_big)
        result["quality"][name] = quality(system, args.device, size, frames)  # type: ignore[arg-type]
        print(json.dumps({name: result["quality"][name]}, indent=1), flush=True)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        settings = ServerSettings(
            port=0,
            device=args.device,
            token="bench",
            viewer_token="bench-view",
            state_dir=Path(tmp),
            default_size=size,  # type: ignore[arg-type]
            limits=p.Limits(max_message_bytes=512 << 20, max_atoms=2_000_000, max_steer_per_s=1000),
            stats_interval_s=5.0,
            frame_budget_ms=0.0,
        )
        overrides = {}
        for item in args.set:
            name, _, value = item.partition("=")
            overrides[name] = type(getattr(settings, name))(value)
        settings = replace(settings, **overrides)
        result["settings_changed"] = overrides
        if args.encode_every_frame:
            from server.session.delivery import Delivery

            Delivery._nothing_new = staticmethod(lambda *_: False)  # type: ignore[method-assign]
            result["encode_every_frame"] = True
        if args.stream_per_camera:
            from server.session.streams import VideoStreams

            VideoStreams._follow = lambda *_: None  # type: ignore[method-assign]
            result["stream_per_camera"] = True
        if args.host_convert:
            from server.pipeline.gpu import GpuQueue

            GpuQueue._on_cuda = lambda _self: False  # type: ignore[method-assign]
            result["host_convert"] = True
        if args.whole_frames:
            result["whole_frames"] = True
        if args.no_settle:
            from server import heap

            heap.settle = lambda: 0.0
            result["no_settle"] = True
        if args.always_rgba:
            from server.pipeline.gpu import GpuQueue

            render_sync = GpuQueue.render_sync
            GpuQueue.render_sync = lambda q, r: render_sync(q, replace(r, rgba=True))  # type: ignore[method-assign]
            result["always_rgba"] = True
        if args.no_stage:
            from server.pipeline.gpu import GpuQueue

            GpuQueue.stage = lambda *_: None  # type: ignore[method-assign]
            result["no_stage"] = True
        if args.switch_interval:
            sys.setswitchinterval(args.switch_interval)
            result["switch_interval_s"] = args.switch_interval
        trace = Trace()
        if args.stalls:
            trace.stalls = LoopStalls()
        server = ServerThread(settings)
        try:
            for name in systems:
                for link in args.links.split(","):
                    for video in [t == "h264" for t in args.transports.split(",")]:
                        row = live(
                            server, name, n_big, video, link, size, seconds, trace,  # type: ignore[arg-type]
                            args.steer, args.change_hz, not args.whole_frames,
                        )  # fmt: skip
                        result["live"].append(row)
                        print(json.dumps(row), flush=True)
                        req = trace.last_request
                        if req is not None and args.live_only:
                            print(
                                "last request",
                                req.width,
                                req.height,
                                req.layers is not None,
                                req.params.model_dump_json(exclude_defaults=True),
                                req.camera.model_dump_json(),
                                flush=True,
                            )
        finally:
            server.stop()
    out = args.out or RESULTS / ("video_quick.json" if args.quick else "video.json")
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
