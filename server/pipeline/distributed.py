"""Batch jobs on Ray: a job's frames cut into chunks and rendered by a pool of Ray actors, one per
GPU of the cluster (or per CPU worker where there is none), the images coming back in order.

Ray is an extra (`pip install 'scalesteer[ray]'`) and is used when asked (`--batch-engine ray`)
or when a cluster is configured (`--ray-address`, `SCALESTEER_RAY_ADDRESS` or `RAY_ADDRESS`);
otherwise jobs render in the server's own process (`server.pipeline.jobs`), as do small jobs
(`ray_min_frames`) unless Ray was asked for.

Asked for without a cluster, the server starts a Ray instance of its own (`LocalRay`): `ray
start --head` under the server's supervisor (`server.supervisor`), so that every Ray process ends
with the server, `kill -9` included, and none of them sees the terminal's Ctrl-C. Its node
address is loopback, which makes every Ray server (GCS, raylet, workers, object manager, agents,
the autoscaler's metrics) listen on 127.0.0.1 only, and it runs with Ray's token authentication
and a fresh random token each start, so that a local client without the token is refused too.
Its dashboard is off. Joining a cluster, the server authenticates with `RAY_AUTH_TOKEN`
when it is set (token authentication needs Ray 2.52 or later).

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

Kept whole: everything that touches Ray (the local instance, the actors, the chunks) is here, the
one module that imports Ray, and only when a job asks for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib
import importlib.metadata
import importlib.util
import logging
import os
import secrets
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p
from server.supervisor import Supervised

log = logging.getLogger("scalesteer.batch")

CHUNK_FRAMES = 8
"""Frames per Ray task: small enough to balance and retry cheaply, large enough to amortise."""
MAX_RESTARTS = 2
"""Times Ray restarts a dead actor (and retries its task) before the chunk moves elsewhere."""
MAX_CHUNK_TRIES = 3
IN_FLIGHT = 2


CONNECT_S = 90.0
"""How long a local Ray instance may take to accept the server's connection."""


def available() -> bool:
    """Whether Ray is installed here (without importing it: Ray reads its authentication
    settings when it is first imported)."""
    return importlib.util.find_spec("ray") is not None


AUTH_VARIABLES = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN")
LOOPBACK = "127.0.0.1"
"""The node address of the server's own Ray instance: Ray binds its servers to it."""
SINGLE_HOST = ("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
"""Ray's switch for a host that is no cluster (on by default only where clusters are not
supported): with it, a node address given as loopback stays loopback instead of being replaced
by the host's network address, for the instance's processes and for this one's calls (the
server never joins a cluster once it runs an instance of its own)."""
TOKEN_AUTH_RAY = (2, 52)
"""The first Ray release with token authentication."""


def _use_token(token: str | None, mode: str | None = "token") -> None:
    """Authenticate this process's Ray calls with `token` (Ray reads it from the environment;
    when Ray is already imported, its cached settings are read again, as `ray.init` does when it
    turns token authentication on). None values remove the variables."""
    for name, value in zip(AUTH_VARIABLES, (mode, token), strict=True):
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    if "ray" in sys.modules:
        raylet: Any = importlib.import_module("ray._raylet")
        raylet.Config.initialize("")
        raylet.AuthenticationTokenLoader.instance().reset_cache()


class LocalRay:
    """A Ray instance of this host for this server alone (see the module's docstring)."""

    def __init__(self, log_path: Path | None = None, cpus: int | None = None) -> None:
        installed = importlib.metadata.version("ray")
        if tuple(int(x) for x in installed.split(".")[:2]) < TOKEN_AUTH_RAY:
            raise RuntimeError(
                f"a Ray instance of the server's own needs Ray 2.52 or later, for its token "
                f"authentication (installed: {installed}); upgrade Ray or join a cluster "
                "with --ray-address"
            )
        with socket.socket() as s:
            s.bind((LOOPBACK, 0))
            self.port: int = s.getsockname()[1]
        self.address = f"{LOOPBACK}:{self.port}"
        self.log_path = log_path
        self.token = secrets.token_hex(32)
        # a folder of its own: `ray start` records its address in its temporary folder, where
        # another program's `ray.init()` on this host would find it and try to join. Ray makes
        # its folder writable by everyone (its sockets too): it goes inside one only this
        # user may enter (mkdtemp's 0700), so no other user of the host reaches them
        self.private_dir = Path(tempfile.mkdtemp(prefix="scalesteer-ray-"))
        self.temp_dir = self.private_dir / "ray"
        command = [
            sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block",
            f"--port={self.port}", f"--temp-dir={self.temp_dir}", "--include-dashboard=false",
            "--disable-usage-stats", f"--node-ip-address={LOOPBACK}",
        ]  # fmt: skip
        if cpus is not None:
            command.append(f"--num-cpus={cpus}")
        env = dict(os.environ, RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=self.token)
        env[SINGLE_HOST[0]] = SINGLE_HOST[1]
        env.pop("RAY_ADDRESS", None)
        if log_path is not None:
            log_path.parent.mkdir(parents=True, exist_ok=True)
            with open(log_path, "ab") as out:
                self.process = Supervised(command, env=env, output=out, remove=self.private_dir)
        else:
            self.process = Supervised(command, env=env, remove=self.private_dir)
        self._saved = [os.environ.get(name) for name in AUTH_VARIABLES]
        _use_token(self.token)

    def connect(self, **options: Any) -> None:
        """`ray.init` this process to the instance once it is up (its start takes seconds)."""
        import ray

        deadline = time.monotonic() + CONNECT_S
        while True:
            code = self.process.poll()
            if code is not None:
                raise RuntimeError(f"the local Ray instance exited with code {code}{self._tail()}")
            try:
                ray.init(
                    address=self.address,
                    _temp_dir=str(self.temp_dir),
                    _node_ip_address=LOOPBACK,
                    **options,
                )
                return
            except ConnectionError:
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the local Ray instance did not start in {CONNECT_S:.0f} s{self._tail()}"
                    ) from None
                time.sleep(0.5)

    def stop(self) -> None:
        """End every process of the instance; this process's Ray settings are as before."""
        self.process.stop()
        mode, token = self._saved
        _use_token(token, mode)

    def _tail(self) -> str:
        if self.log_path is None:
            return ""
        with contextlib.suppress(OSError):
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
            if lines:
                return f" ({lines[-1][:300]}; see {self.log_path})"
        return ""


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
    selection_limits: Any = None
    """The server's `structures.selection_pool.PoolLimits`: layers are evaluated by a
    selection worker of the actor's own, under the same limits as on the server."""


def _render_chunk_impl(state: dict[str, Any], inputs: ChunkInputs, indices: Sequence[int]) -> Any:
    """Render `indices` on this actor (body of `RenderWorker.render`, kept importable)."""
    from server.pipeline.encoder import encode_image
    from server.pipeline.history import time_window
    from server.pipeline.overlay import draw_cell, draw_overlay
    from server.pipeline.periodic import displayed_cell, needs_selections
    from server.pipeline.selections import FrameLayers
    from server.render import Renderer
    from server.render.layers import LayeredRenderer
    from structures.reader import load

    if state.get("job") != inputs.job:
        if state.get("held") is not None:
            state["held"].release()  # the last job's topology leaves the selection worker
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
        if state.get("held") is not None:
            state["held"].release()
        pool = _selection_pool(inputs.selection_limits)
        wanted = bool(params.layers) or needs_selections(params)
        held = state["held"] = pool.hold(structure.topology) if wanted else None
        layers = state["layers"] = FrameLayers(params, structure.topology, held, reference)
        state["periodic"] = _periodic_frames(structure, params, held, state_device_name())
        cache.clear()
    camera = p.Camera.model_validate(inputs.camera)
    window = time_window(params, inputs.n_frames)
    displayed = state["periodic"]

    def frame(i: int) -> tuple[Any, Any, Any, Any]:
        if i not in cache:
            if len(cache) > 256:
                cache.clear()
            raw, box = structure.frame(i)
            shown, how = displayed(raw, box)
            cache[i] = (raw, box, shown, how)
        found: tuple[Any, Any, Any, Any] = cache[i]
        return found

    out: list[tuple[int, bytes | None, bytes | None]] = []
    for index in indices:
        raw, box, positions, how = frame(index)
        history: list[tuple[int, Any]] = []
        lag = None
        if window is not None:
            first, last = window(index)
            history = [(i + 1, frame(i)[2]) for i in range(first, last + 1)]
            lag = last - index
        plans = layers.plans(raw, index, box)
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
        cell = displayed_cell(how, box) if params.show_cell else None
        if cell is not None:
            rgba = draw_cell(rgba, camera, cell)
        if inputs.overlay is not None:
            rgba = draw_overlay(rgba, index, inputs.overlay, camera, positions)
        if inputs.png:
            png, _ms = encode_image(rgba, "png")
            out.append((index, None, png))
        else:
            out.append((index, np.ascontiguousarray(rgba).tobytes(), None))
    return out


def _periodic_frames(
    structure: Any, params: p.RenderParams, held: Any, device: str
) -> Callable[[Any, Any], tuple[Any, Any]]:
    """(positions, box) -> (positions as displayed, how), on this actor's device, the fit's
    reference the file's first frame as on the server (jobs that unwrap stay there)."""
    from server.pipeline.periodic import REFERENCE_FRAME, PeriodicOptions, needs_display
    from server.render.periodic import PeriodicTransform

    options = PeriodicOptions(params, held)
    transform = PeriodicTransform(device)
    transform.set_topology(structure.topology)
    referenced = [False]

    def display(raw: Any, box: Any) -> tuple[Any, Any]:
        if not needs_display(params, box):
            return raw, None
        how = options.get(box)
        if how.fit != "off" and not referenced[0]:
            ref_raw, ref_box = structure.frame(REFERENCE_FRAME)
            transform.apply(ref_raw, ref_box, options.get(ref_box), reference=True)
            referenced[0] = True
        transform.restart()
        shown = transform.apply(raw, box, how)
        return shown.positions, shown

    return display


_POOLS: dict[Any, Any] = {}


def _selection_pool(limits: Any) -> Any:
    """This actor's selection worker (one per limits; it ends with the actor's process)."""
    from structures.selection_pool import PoolLimits, SelectionPool

    chosen = limits if limits is not None else PoolLimits()
    if chosen not in _POOLS:
        _POOLS[chosen] = SelectionPool(dataclasses.replace(chosen, workers=1))
    return _POOLS[chosen]


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
    """The cluster to join; None starts a `LocalRay` on the first job."""
    workers: int | None = None
    """Actors at most (default: one per GPU of the cluster, else one per CPU)."""
    min_frames: int = 0
    """Jobs of fewer frames render in the server's own process."""
    log_dir: Path | None = None
    """Where the output of a local Ray instance goes (`ray.log`)."""
    _actors: list[Any] = field(default_factory=list)
    _started: bool = False
    _lock: asyncio.Lock | None = None
    _local: LocalRay | None = None
    _connected: bool = False
    """Whether this pool connected this process to Ray (and disconnects it on close)."""

    def _start(self) -> None:
        # Ray's crash handler would take SIGTERM from the server's own graceful stop (a stack
        # dump, then the process killed before its jobs and recordings are closed)
        os.environ.setdefault("RAY_DISABLE_FAILURE_SIGNAL_HANDLER", "1")
        if self.address is None:  # an instance of our own: Ray reads this as it is imported
            os.environ[SINGLE_HOST[0]] = SINGLE_HOST[1]
        import ray

        if not ray.is_initialized():
            options: dict[str, Any] = {
                "log_to_driver": False,
                "namespace": "scalesteer",
                "configure_logging": False,
            }
            try:
                if self.address is None:
                    log_path = None if self.log_dir is None else self.log_dir / "ray.log"
                    self._local = LocalRay(log_path)
                    self._local.connect(**options)
                else:
                    token = os.environ.get("RAY_AUTH_TOKEN")
                    if token and not os.environ.get("RAY_AUTH_MODE"):
                        _use_token(token)
                    ray.init(address=self.address, **options)
            except BaseException:
                self._stop_local()
                raise
            self._connected = True
        resources = ray.cluster_resources()  # type: ignore[no-untyped-call]
        gpus = int(resources.get("GPU", 0))
        count = gpus or max(1, int(resources.get("CPU", 1)))
        if self.workers:
            count = min(count, self.workers)
        worker = _worker_class().options(num_gpus=1 if gpus else 0, num_cpus=0 if gpus else 1)
        self._actors = [worker.remote() for _ in range(count)]
        self._started = True
        log.info("Ray batch engine: %d actor(s) (%s)", count, "GPU" if gpus else "CPU")

    @property
    def started(self) -> bool:
        return self._started

    async def ensure(self) -> None:
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            if not self._started:
                await asyncio.to_thread(self._start)

    def describe(self) -> dict[str, Any]:
        """For /healthz: the engine and, once started, its workers."""
        out: dict[str, Any] = {
            "engine": "ray",
            "address": self.address or "local",
            "min_frames": self.min_frames,
            "auth": "token" if os.environ.get("RAY_AUTH_MODE") == "token" else "none",
        }
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
        """Kill the actors; a connection this pool made is closed and a local instance it
        started is stopped (every process of it)."""
        if self._started:
            import ray

            for actor in self._actors:
                with contextlib.suppress(Exception):
                    ray.kill(actor)
            self._actors = []
            self._started = False
            if self._connected:
                with contextlib.suppress(Exception):
                    ray.shutdown()
                self._connected = False
        self._stop_local()

    def _stop_local(self) -> None:
        if self._local is not None:
            self._local.stop()
            self._local = None


def _consume(fut: asyncio.Future[Any]) -> None:
    if not fut.cancelled():
        fut.exception()


def upload_refs(paths: Sequence[Path]) -> list[Any]:
    """Uploaded files as (name, ObjectRef) for workers that may not share the disk."""
    import ray

    return [(path.name, ray.put(path.read_bytes())) for path in paths]
