"""The FastAPI application factory: resources start with the app's lifespan and stop with it."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

from fastapi import FastAPI, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.staticfiles import StaticFiles

from server.metrics import Metrics
from server.pipeline.encoder import select_encoder
from server.pipeline.gpu import GpuQueue
from server.pipeline.jobs import JobManager
from server.pipeline.video import VideoEncoders

if TYPE_CHECKING:
    from server.pipeline.distributed import RayBatch
from server.pipeline.recordings import RecordingStore
from server.session.services import Services
from server.session.session import Session
from server.session.steering_log import SteeringLog
from server.settings import ServerSettings
from server.threads import name_thread
from server.web import ws as ws_endpoints
from server.web.apidocs import add_docs
from server.web.auth import RateLimiter
from server.web.middleware import (
    FORM_BYTES,
    HostCheck,
    OriginCheck,
    SecurityHeaders,
    StopAnswer,
    UploadLimit,
)
from server.web.owners import Owners
from server.web.recordings import router as recordings_router
from server.web.replays import router as replays_router
from server.web.rest import router
from server.web.spool import Spool
from server.web.state import AppState, SessionRegistry
from server.web.validation import validation_failed
from structures.selection_pool import SelectionPool

log = logging.getLogger("scalesteer.app")


def batch_engine(settings: ServerSettings, log_dir: Path | None = None) -> RayBatch | None:
    """The Ray pool for trajectory jobs, or None to render them in this process: Ray when asked
    (`ray`: a cluster, or an instance of this server's own), or (`auto`) when a cluster is
    configured and Ray is installed, for jobs of `ray_min_frames` frames or more."""
    if settings.batch_engine == "local":
        return None
    from server.pipeline.distributed import RayBatch, available

    if settings.batch_engine == "ray":
        if not available():
            raise RuntimeError("--batch-engine ray needs Ray: pip install 'scalesteer[ray]'")
        return RayBatch(settings.ray_address, settings.ray_workers, log_dir=log_dir)
    if settings.ray_address is None:
        return None
    if not available():
        log.warning("Ray cluster %s configured but Ray is not installed: jobs render here",
                    settings.ray_address)  # fmt: skip
        return None
    return RayBatch(
        settings.ray_address,
        settings.ray_workers,
        min_frames=settings.ray_min_frames,
        log_dir=log_dir,
    )


def _load_selections() -> None:
    # without MDAnalysis the layers' selections fail later with their own message
    with contextlib.suppress(ImportError):
        import MDAnalysis.core.selection  # noqa: F401


def clean_spool(directory: Path) -> Path:
    """The spool directory, emptied: scratch folders of file reads a killed server left."""
    directory.mkdir(parents=True, exist_ok=True)
    for entry in directory.iterdir():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
    return directory


async def _closing(
    what: str, step: Awaitable[object] | Callable[[], object], deadline: float | None = None
) -> None:
    """One step of the server's stop: a failure is logged and the next steps still run. A
    callable runs here, on the loop; an awaitable is awaited, and with a `deadline`
    (monotonic) waited for until then, then cancelled without waiting further
    (`asyncio.wait_for` would wait for its cancellation, which may wait on a device)."""
    try:
        if callable(step):
            step()
        elif deadline is None:
            await step
        else:
            task = asyncio.ensure_future(step)
            done, _ = await asyncio.wait({task}, timeout=max(0.0, deadline - time.monotonic()))
            if not done:
                task.cancel()
                log.warning("stopping: %s still waited on the devices at the deadline", what)
            elif not task.cancelled():  # one cancelled already has nothing to report
                task.result()
    except Exception:
        log.exception("closing %s failed; the rest is closed still", what)


def create_app(settings: ServerSettings) -> FastAPI:
    """Build the app; resources start with the app's lifespan and stop with it."""
    state_dir = settings.state_dir
    state_dir.mkdir(parents=True, exist_ok=True)
    spool = Spool(
        clean_spool(settings.spool_dir),
        settings.max_upload_bytes + FORM_BYTES,  # the form's own bytes around the files
        settings.max_spool_bytes,
        settings.viewer_spool_bytes,
    )

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        metrics = Metrics()
        devices: tuple[str, ...] = ()
        if settings.gpus:
            from server.render.device import resolve_many

            devices = resolve_many(settings.gpus)
        gpu = GpuQueue(
            device=settings.device,
            devices=devices,
            max_atoms=settings.limits.max_atoms,
            max_pixels=settings.limits.max_image_pixels,
            device_atoms=settings.device_atoms,
        )
        encoders = ThreadPoolExecutor(
            max_workers=settings.encode_workers,
            thread_name_prefix="encode",
            initializer=name_thread,
        )
        encoder = await asyncio.to_thread(select_encoder, settings.device)
        gpu.jpeg = encoder.on_device()  # the render lanes of its device encode their JPEGs
        # shared by all sessions: encodes in flight never outnumber the encoder threads
        encode_slots = asyncio.Semaphore(settings.encode_workers)
        steering_log = SteeringLog(state_dir / "logs")
        upload_dir = state_dir / "uploads"
        upload_dir.mkdir(parents=True, exist_ok=True)

        video = VideoEncoders(settings.video_codecs, settings.max_video_streams)
        await asyncio.to_thread(video.chosen)  # probe once, before the first viewer waits on it
        # the selection language loads while the server starts (its texts are parsed here,
        # before a worker evaluates them)
        asyncio.get_running_loop().run_in_executor(None, _load_selections)
        selections = SelectionPool(settings.selection_limits())
        selections.start(settings.selection_prestart)
        services = Services(
            gpu,
            encoders,
            encoder,
            encode_slots,
            metrics,
            steering_log,
            video=video,
            video_kbps_per_mpixel=settings.video_kbps_per_mpixel,
            video_min_kbps=settings.video_min_kbps,
            video_streams_per_session=settings.max_video_streams_per_session,
            selections=selections,
        )
        batch = batch_engine(settings, state_dir / "ray")

        def new_session(name: str) -> Session:
            return Session(name, settings, services)

        state = AppState(
            settings=settings,
            gpu=gpu,
            services=services,
            sessions=SessionRegistry(
                new_session,
                settings.max_sessions,
                tuple(t for t in (settings.token, settings.viewer_token) if t),
            ),
            jobs=JobManager(
                state_dir / "jobs",
                gpu,
                encoders,
                metrics,
                settings.spooled_read_limits(),
                retention_s=settings.job_retention_s,
                max_bytes=settings.job_max_bytes,
                max_running=settings.max_running_jobs,
                upload_dir=upload_dir,
                batch=batch,
                selections=selections,
            ),
            recordings=RecordingStore(state_dir / "recordings", steering_log.read),
            upload_dir=upload_dir,
            owners=Owners(settings.owner_grace_s),
            readers=asyncio.Semaphore(settings.max_readers),
            viewer_renders=RateLimiter(
                settings.viewer_renders_per_min / 60.0,
                max(1.0, settings.viewer_renders_per_min / 6),
            ),
        )
        app.state.scalesteer = state
        interrupted = await asyncio.to_thread(state.recordings.restore)
        for rec in interrupted:
            log.warning("recording %s was interrupted; kept %d frame(s)", rec.id, rec.frames)
        resumed = state.jobs.restore()
        if resumed:
            log.info("started again %d job(s) a previous run left unfinished", len(resumed))
        await state.sessions.get_or_create("default")

        async def reaper() -> None:
            while True:
                await asyncio.sleep(min(30.0, settings.session_idle_s / 4))
                await state.sessions.reap(settings.session_idle_s)

        reaping = asyncio.create_task(reaper(), name="session-reaper")
        warming = (
            asyncio.create_task(gpu.warm_up(), name="warm-up-render")
            if settings.warm_up_render
            else None
        )
        try:
            yield
        finally:
            reaping.cancel()
            # what waits on the devices (the warm-up, the sessions' last steps, the devices'
            # threads) takes `close_wait_s` in all: a render there may run for minutes, and the
            # server then stops without it (`server.commands.serve`); each step is taken even
            # when one before it failed
            deadline = time.monotonic() + settings.close_wait_s
            if warming is not None:
                await _closing("the warm-up render", warming, deadline)
            # on the loop: its timers are the loop's
            await _closing("the owners' leases", state.owners.close)
            await _closing("the replays", asyncio.to_thread(state.replays.close))
            await _closing("the recordings", asyncio.to_thread(state.recordings.close))
            await _closing("the jobs", state.jobs.close())
            if batch is not None:
                await _closing("the batch engine", asyncio.to_thread(batch.close))
            await _closing("the sessions", state.sessions.close(), deadline)
            await _closing("the selection workers", asyncio.to_thread(selections.close))
            left = max(0.0, deadline - time.monotonic())
            busy = await asyncio.to_thread(gpu.close, left)
            if busy:  # the process then exits without it (`server.commands.serve`)
                log.warning(
                    "stopping with work still running: %s",
                    ", ".join(f"{device} for {secs:.0f} s" for device, secs in busy),
                )
            encoders.shutdown(wait=True)
            steering_log.close()

    app = FastAPI(
        title="scalesteer",
        description="Interactive multiscale visualization and steering of molecular simulations.",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    app.add_exception_handler(RequestValidationError, validation_failed)
    app.include_router(router)
    app.include_router(replays_router)
    app.include_router(recordings_router)
    add_docs(app, settings.client_dir)

    @app.websocket("/ws/sim")
    async def ws_sim(websocket: WebSocket) -> None:
        await ws_endpoints.handle(websocket, app.state.scalesteer, "sim")

    @app.websocket("/ws/view")
    async def ws_view(websocket: WebSocket) -> None:
        await ws_endpoints.handle(websocket, app.state.scalesteer, "view")

    if (settings.client_dir / "index.html").is_file():
        app.mount("/", StaticFiles(directory=settings.client_dir, html=True), name="client")
    # the last added runs first: headers on every answer, a stop's answer, then Host, Origin,
    # the body limits
    app.add_middleware(UploadLimit, spool=spool, settings=settings)
    app.add_middleware(OriginCheck, settings=settings)
    app.add_middleware(HostCheck, settings=settings)
    app.add_middleware(StopAnswer)
    app.add_middleware(SecurityHeaders, settings=settings)
    return app
