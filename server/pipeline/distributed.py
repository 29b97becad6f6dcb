"""Batch jobs on Ray: a job's frames cut into chunks and rendered by a pool of Ray actors, one per
GPU of the cluster (or per CPU worker where there is none), the images coming back in order.

Ray is an extra (`pip install 'scalesteer[ray]'`); without it jobs render in the server's own
process (`server.pipeline.jobs`). With it, by default a local Ray instance starts on the first
job and uses the host's GPUs; `--ray-address` (or `SCALESTEER_RAY_ADDRESS`) joins a cluster.

Each actor owns a Renderer and reads its chunks with the project's reader (MDAnalysis): files
named on the server (`--data-dir` datasets) are read from the same path, which every worker must
reach (a shared filesystem); uploaded files travel through Ray's object store and are written to
the worker's temporary directory once per job. Every frame is rendered exactly as the
in-process path renders it (the same reference frame for the warped density, the same temporal
window, the same PNG encoder), so a zip of PNGs is identical bit for bit.

Faults: an actor whose process dies is restarted by Ray and its chunk retried
(`MAX_RESTARTS`); a chunk whose actor is gone for good goes to another actor; a job whose
chunks cannot be rendered fails with the reason. Images are assembled by frame index, so
every frame is written exactly once.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import tempfile
import threading
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p

log = logging.getLogger("scalesteer.batch")

CHUNK_FRAMES = 8
"""Frames per Ray task: small enough to balance and retry cheaply, large enough to amortise."""
MAX_RESTARTS = 2
"""Times Ray restarts a dead actor (and retries its task) before the chunk moves elsewhere."""
MAX_CHUNK_TRIES = 3
IN_FLIGHT = 2


def available() -> bool:
    """Whether Ray can be imported here."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True)
class ChunkInputs:
    """What every chunk of one job needs (sent once per job to each actor)."""

    job: str
    topology: Any
    """A path (str) workers can reach, or (name, ObjectRef of the bytes) of an upload."""
    trajectories: tuple[Any, ...]
    params: dict[str, Any]
    camera: dict[str, Any]
    width: int
    height: int
    png: bool
    n_frames: int
    reference: int
    """The job's first frame: the warped density's bond lengths come from it, as in-process."""
    overlay: dict[str, Any] | None = None


def _render_chunk_impl(state: dict[str, Any], inputs: ChunkInputs, indices: Sequence[int]) -> Any:
    """Render `indices` on this actor (body of `RenderWorker.render`, kept importable)."""
    from server.pipeline.encoder import encode_image
    from server.pipeline.jobs import time_window
    from server.pipeline.overlay import draw_overlay
    from server.pipeline.selections import FrameLayers
    from server.render import Renderer
    from server.render.layers import LayeredRenderer
    from structures.reader import load

    if state.get("job") != inputs.job:
        state.clear()
        files = [_local(f, inputs.job) for f in (inputs.topology, *inputs.trajectories)]
        structure = load(files[0], files[1:])
        device = state_device_name()
        renderer = Renderer(device)
        renderer.set_topology(structure.topology)
        renderer.set_positions(structure.positions(inputs.reference))
        layered = LayeredRenderer(lambda: Renderer(device))
        state.update(
            job=inputs.job, structure=structure, renderer=renderer, layered=layered, cache={}
        )
    structure, renderer, cache = state["structure"], state["renderer"], state["cache"]
    params = p.RenderParams.model_validate(inputs.params)
    layers = state.get("layers")
    if layers is None or layers.params != params:  # one per job: selections and helices kept
        reference = structure.positions(inputs.reference)
        layers = state["layers"] = FrameLayers(params, structure.topology, reference)
    camera = p.Camera.model_validate(inputs.camera)
    window = time_window(params, inputs.n_frames)

    def frame(i: int) -> Any:
        if i not in cache:
            if len(cache) > 256:
                cache.clear()
            cache[i] = np.ascontiguousarray(structure.positions(i), dtype=np.float32)
        return cache[i]

    out: list[tuple[int, bytes | None, bytes | None]] = []
    for index in indices:
        positions = frame(index)
        history: list[tuple[int, Any]] = []
        lag = None
        if window is not None:
            first, last = window(index)
            history = [(i + 1, frame(i)) for i in range(first, last + 1)]
            lag = last - index
        plans = layers.plans(positions, index)
        if plans is not None:
            layered = state["layered"]
            layered.render(
                plans, structure.topology, 1, positions, index + 1, camera, inputs.width,
                inputs.height, history=history, history_epoch=index, live=False, lag=lag,
            )  # fmt: skip
            rgba = layered.read_rgba()
        else:
            renderer.set_positions(positions, check_finite=False)
            if history:
                renderer.set_history(history, index, params, live=False, lag=lag)
            renderer.render(params, camera, inputs.width, inputs.height)
            rgba = renderer.read_rgba()
        if inputs.overlay is not None:
            rgba = draw_overlay(rgba, index, inputs.overlay, camera, positions)
        if inputs.png:
            png, _ms = encode_image(rgba, "png")
            out.append((index, None, png))
        else:
            out.append((index, np.ascontiguousarray(rgba).tobytes(), None))
    return out


def state_device_name() -> str:
    """The render device of this actor: its GPU when Ray gave it one, else the CPU."""
    import ray

    gpus = ray.get_gpu_ids()
    return "cuda:0" if gpus else "cpu"  # Ray sets CUDA_VISIBLE_DEVICES to the actor's GPU


def _local(ref: Any, job: str) -> str:
    """A path for one input: itself, or an upload written to this worker's temporary folder."""
    if isinstance(ref, str):
        return ref
    import ray

    name, obj = ref
    folder = Path(tempfile.gettempdir()) / f"scalesteer-{job}"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    if not path.exists():
        data = ray.get(obj)
        # a name of its own: two actors of one host may fetch the same upload at once, and
        # the one that renames second must not find its file gone
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.part")
        tmp.write_bytes(data)
        os.replace(tmp, path)
    return str(path)


def _worker_class() -> Any:
    import ray

    # `info` has a thread of its own, so /healthz answers while the actor renders a chunk
    @ray.remote(  # type: ignore[call-overload]
        max_restarts=MAX_RESTARTS,
        max_task_retries=MAX_RESTARTS,
        concurrency_groups={"info": 1, "render": 1},
    )
    class RenderWorker:
        def __init__(self) -> None:
            self.state: dict[str, Any] = {}

        @ray.method(concurrency_group="info")
        def info(self) -> dict[str, Any]:
            ctx = ray.get_runtime_context()
            return {"pid": os.getpid(), "node": ctx.get_node_id(), "device": state_device_name()}

        @ray.method(concurrency_group="render")
        def render(self, inputs: ChunkInputs, indices: list[int]) -> Any:
            return _render_chunk_impl(self.state, inputs, indices)

    return RenderWorker


@dataclass
class RayBatch:
    """The Ray side of batch jobs: the connection, the actor pool and the chunk scheduler."""

    address: str | None = None
    workers: int | None = None
    """Actors at most (default: one per GPU of the cluster, else one per CPU)."""
    _actors: list[Any] = field(default_factory=list)
    _started: bool = False
    _lock: asyncio.Lock | None = None

    def _start(self) -> None:
        import ray

        if not ray.is_initialized():
            ray.init(
                address=self.address,
                include_dashboard=False,
                log_to_driver=False,
                namespace="scalesteer",
                configure_logging=False,
            )
        resources = ray.cluster_resources()  # type: ignore[no-untyped-call]
        gpus = int(resources.get("GPU", 0))
        count = gpus or max(1, int(resources.get("CPU", 1)))
        if self.workers:
            count = min(count, self.workers)
        worker = _worker_class().options(num_gpus=1 if gpus else 0, num_cpus=0 if gpus else 1)
        self._actors = [worker.remote() for _ in range(count)]
        self._started = True
        log.info("Ray batch engine: %d actor(s) (%s)", count, "GPU" if gpus else "CPU")

    async def ensure(self) -> None:
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            if not self._started:
                await asyncio.to_thread(self._start)

    def describe(self) -> dict[str, Any]:
        """For /healthz: the engine and, once started, its workers."""
        out: dict[str, Any] = {"engine": "ray", "address": self.address or "local"}
        if not self._started:
            out["started"] = False
            return out
        import ray

        infos = []
        for actor in self._actors:
            try:
                infos.append(ray.get(actor.info.remote(), timeout=2))
            except Exception as exc:  # a dead or restarting actor
                infos.append({"alive": False, "error": type(exc).__name__})
        out.update(started=True, workers=infos, nodes=len(ray.nodes()))  # type: ignore[no-untyped-call]
        return out

    def worker_pids(self) -> list[int]:
        import ray

        return [int(ray.get(a.info.remote())["pid"]) for a in self._actors]

    async def render(
        self,
        inputs: ChunkInputs,
        indices: Sequence[int],
        write: Callable[[int, Any, bytes | None], Awaitable[None]],
        cancel: Any,
    ) -> bool:
        """Render `indices` on the pool, calling `write(index, rgba, png)` in frame order;
        False when cancelled (outstanding tasks are cancelled too)."""
        import ray

        await self.ensure()
        chunks = [list(indices[i : i + CHUNK_FRAMES]) for i in range(0, len(indices), CHUNK_FRAMES)]
        pending = list(range(len(chunks)))
        tries = [0] * len(chunks)
        # two chunks in flight per actor: it renders the next while this process encodes
        idle = [a for a in self._actors for _ in range(IN_FLIGHT)]
        running: dict[asyncio.Future[Any], tuple[int, Any, Any]] = {}
        done: dict[int, Any] = {}
        next_chunk = 0
        shape = (inputs.height, inputs.width, 4)

        def dispatch() -> None:
            while pending and idle:
                c = pending.pop(0)
                actor = idle.pop(0)
                tries[c] += 1
                ref = actor.render.remote(inputs, chunks[c])
                running[asyncio.wrap_future(ref.future())] = (c, actor, ref)

        try:
            while next_chunk < len(chunks):
                dispatch()
                if cancel.is_set():
                    return False
                finished, _ = await asyncio.wait(
                    running, timeout=0.5, return_when=asyncio.FIRST_COMPLETED
                )
                for fut in finished:
                    c, actor, _ref = running.pop(fut)
                    try:
                        done[c] = fut.result()
                        idle.append(actor)
                    except ray.exceptions.ActorDiedError as exc:
                        log.warning("chunk %d: its worker is gone (%s); trying elsewhere", c, exc)
                        if tries[c] >= MAX_CHUNK_TRIES or not (idle or running):
                            where = f"frames {chunks[c][0]}-{chunks[c][-1]}"
                            raise RuntimeError(
                                f"{where}: no worker could render them ({exc})"
                            ) from None
                        pending.insert(0, c)
                    except ray.exceptions.RayTaskError as exc:
                        raise RuntimeError(
                            f"frames {chunks[c][0]}-{chunks[c][-1]}: {exc.cause!r}"
                        ) from None
                dispatch()  # before writing: the actors work while this process encodes
                while next_chunk in done:
                    for index, rgba, png in done.pop(next_chunk):
                        image = (
                            None if rgba is None else np.frombuffer(rgba, np.uint8).reshape(shape)
                        )
                        await write(index, image, png)
                    next_chunk += 1
            return True
        finally:
            for fut, (_c, _actor, ref) in running.items():
                fut.add_done_callback(_consume)  # the outcome of a chunk nobody waits for
                with contextlib.suppress(Exception):
                    ray.cancel(ref)

    def close(self) -> None:
        if not self._started:
            return
        import ray

        for actor in self._actors:
            with contextlib.suppress(Exception):
                ray.kill(actor)
        self._actors = []
        self._started = False


def _consume(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()


def upload_refs(paths: Sequence[Path]) -> list[Any]:
    """Uploaded files as (name, ObjectRef) for workers that may not share the disk."""
    import ray

    return [(path.name, ray.put(path.read_bytes())) for path in paths]
