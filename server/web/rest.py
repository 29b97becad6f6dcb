"""REST API: one-off renders, batch trajectory jobs, sessions, health and metrics.

Inputs are structures uploaded as files or named datasets under `--data-dir` (never any other
server path). Every failure is a 4xx naming what was wrong; server faults are logged, not leaked.

Kept whole: every HTTP route in one file, so the API's surface and the 4xx each route answers read
in one place beside docs/server.md's table of them.
"""

from __future__ import annotations

import asyncio
import json
import re
import shutil
import tempfile
import time
import uuid
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, ValidationError

import protocol as p
from protocol.fields import error_location, unknown_keys
from server.pipeline.gpu import DisplayRequest, RenderRequest, Snapshot
from server.pipeline.jobs import FINAL, JobSpec, JobState
from server.pipeline.livemovie import MovieFrame, MovieQueue
from server.pipeline.overlay import draw_cell
from server.pipeline.periodic import (
    PERIODIC_FIELDS,
    REFERENCE_FRAME,
    PeriodicError,
    PeriodicOptions,
    check_periodic,
    displayed_cell,
    needs_display,
    needs_selections,
)
from server.pipeline.selections import FrameLayers, LayerError, check_layers, opening_params
from server.render.boxes import Shown
from server.render.errors import RenderError
from server.web.access import (
    GatedRoute,
    app_state,
    render_access,
    steerer_access,
    viewer_access,
)
from server.web.auth import client_address
from server.web.forms import FormBody
from server.web.state import AppState
from server.web.validation import quoted
from structures.errors import StructureError
from structures.isolated import IsolatedStructure

router = APIRouter(route_class=GatedRoute)
State = Annotated[AppState, Depends(app_state)]
SKIP_NOTICE_S = 5.0
"""While a recording or a movie skips frames, how often the session is told."""


def check_layer_texts(state: AppState, params: p.RenderParams, field: str) -> None:
    """Every layer selection must parse and keep to the selection limits (its length and
    nesting, checked here before anything is read): a 422 naming the layer, the position
    and any limit."""
    try:
        check_layers(params, state.selections.limits.selection)
    except LayerError as exc:
        raise HTTPException(422, f"{field}.{exc}") from None


def _model(cls: type[BaseModel], raw: str | None, field: str) -> Any:
    """Parse a JSON form field into `cls`; every problem is a 422 naming the field, and so is a
    key the model does not know (a misspelt `sigma` must not fall back to the default)."""
    if raw is None or raw == "":
        return None
    try:
        data = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise HTTPException(422, f"{field}: not valid JSON ({exc.msg})") from None
    except RecursionError:
        raise HTTPException(422, f"{field}: nested too deeply") from None
    except ValueError as exc:  # an integer of thousands of digits
        raise HTTPException(422, f"{field}: {str(exc)[:120]}") from None
    unknown = unknown_keys(cls, data, field)
    if unknown:
        raise HTTPException(422, f"{unknown}: unknown field")
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        loc, msg = error_location(exc.errors(include_url=False)[0])
        where = ".".join([field, *loc])
        raise HTTPException(422, f"{where}: {msg}") from None


def _dataset(state: AppState, name: str) -> Path:
    root = state.settings.data_dir
    if root is None:
        raise HTTPException(404, "this server has no --data-dir; upload the file instead")
    if "\x00" in name or len(name) > 1024 or any(len(part) > 255 for part in name.split("/")):
        raise HTTPException(422, "dataset: not a usable file name")
    base = root.resolve()
    try:
        path = (base / name).resolve()
        found = path.is_relative_to(base) and path.is_file()
    except OSError:
        found = False
    if not found:
        raise HTTPException(404, f"no dataset named {quoted(name)}")
    return path


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


async def save_upload(upload: UploadFile, directory: Path, limit: int, index: int = 0) -> Path:
    """Stream an upload to `directory` under a safe name that keeps its extension: the name it
    came with (so what the reader says about it names the user's file), prefixed with `index`
    only when an earlier file of the request took that name."""
    name = _UNSAFE.sub("_", Path(upload.filename or "upload").name).lstrip(".")
    if not name:
        raise HTTPException(422, f"unusable file name {upload.filename!r}")
    if len(name) > 120:  # keep the extension, which names the format
        stem, dot, ext = name.rpartition(".")
        name = stem[: 100 - len(ext)] + dot + ext[:16] if dot else name[:120]
    target = directory / name
    if target.exists():
        target = directory / f"{index}-{name}"
    size = 0
    with open(target, "wb") as out:
        while chunk := await upload.read(1 << 20):
            size += len(chunk)
            if size > limit:
                raise HTTPException(413, f"{name}: upload exceeds {limit} bytes")
            out.write(chunk)
    if size == 0:
        raise HTTPException(422, f"{name}: the file is empty")
    return target


async def _read_frame(
    state: AppState, path: Path, frame: int, role: p.Role, reference: int | None = None
) -> tuple[p.Topology, Any, Any, Any]:
    """Topology, positions and box of one frame of an untrusted file, read in a child process;
    with `reference`, that frame too (positions and box: a fit's reference), else None."""
    async with state.readers:
        try:
            structure = await asyncio.to_thread(
                IsolatedStructure, str(path), (), state.settings.spooled_read_limits(role)
            )
        except StructureError as exc:
            raise HTTPException(422, str(exc)) from None
        try:
            if frame >= structure.n_frames:
                raise HTTPException(
                    422, f"frame {frame} out of range: the file has {structure.n_frames}"
                )
            positions, box = await asyncio.to_thread(structure.frame, frame)
            ref = None
            if reference is not None and reference != frame:
                ref = await asyncio.to_thread(structure.frame, reference)
        except StructureError as exc:
            raise HTTPException(422, str(exc)) from None
        finally:
            await asyncio.to_thread(structure.close)
    return structure.topology, positions, box, ref


def check_periodic_texts(state: AppState, params: p.RenderParams, field: str) -> None:
    """The centre and fit selections must parse, keep to the selection limits and name fixed
    atoms: a 422 naming the field."""
    try:
        check_periodic(params, state.selections.limits.selection)
    except PeriodicError as exc:
        raise HTTPException(422, f"{field}.{exc}") from None


async def _displayed(
    state: AppState,
    slot: str,
    render_params: p.RenderParams,
    topology: p.Topology,
    positions: Any,
    box: Any,
    held: Any,
    reference: Any = None,
) -> tuple[Any, Shown | None]:
    """The frame as `render_params` display it (on the GPU queue's device), with how."""
    if not needs_display(render_params, box):
        return positions, None
    try:
        options = await PeriodicOptions(render_params, held).get_async(box)
    except PeriodicError as exc:
        raise HTTPException(422, f"params.{exc}") from None
    if reference is not None and options.fit != "off":
        ref_positions, ref_box = reference
        ref_options = await PeriodicOptions(render_params, held).get_async(ref_box)
        await state.gpu.display(
            DisplayRequest(slot, topology, ref_positions, ref_box, ref_options, True, True)
        )
    shown = await state.gpu.display(
        DisplayRequest(slot, topology, positions, box, options, restart=True)
    )
    return shown.positions, shown


def check_size(state: AppState, width: int, height: int) -> None:
    """Refuse an image size past the limits with a 422 whose detail starts with the field to
    change (`width: ...`, the longer side for a count of pixels), which clients read as the
    error's path."""
    lim = state.settings.limits
    size = f"image size {width}x{height}"
    longer = "width" if width >= height else "height"
    for name, value in (("width", width), ("height", height)):
        if value < 1:
            raise HTTPException(422, f"{name}: {size}: width and height must be >= 1")
    device = state.gpu.device_name
    if device.startswith("cpu") and width * height > state.settings.cpu_max_rest_pixels:
        raise HTTPException(
            422,
            f"{longer}: {size} is {width * height:,} pixels; this server renders on its CPU, "
            f"where at most {state.settings.cpu_max_rest_pixels:,} pixels are rendered per image",
        )
    for name, value in (("width", width), ("height", height)):
        if value > lim.max_image_side:
            raise HTTPException(
                422, f"{name}: {size} exceeds the limit of {lim.max_image_side} px a side"
            )
    if width * height > lim.max_image_pixels:
        raise HTTPException(
            422,
            f"{longer}: {size} is {width * height:,} pixels, over the limit of "
            f"{lim.max_image_pixels:,} pixels an image",
        )


@router.post(
    "/api/render",
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}},
    summary="Render one image of an uploaded structure, a dataset, or a live session",
)
async def render_image(
    http: Request,
    state: State,
    role: Annotated[p.Role, Depends(render_access)],
    _form: FormBody,
    file: Annotated[
        UploadFile | None,
        File(description="a structure: PDB, mmCIF, BinaryCIF, GRO, TPR, XYZ, ... (gzipped too)"),
    ] = None,
    dataset: Annotated[
        str | None, Form(description="file name under the server's --data-dir")
    ] = None,
    session: Annotated[
        str | None, Form(description="a live session: render its latest frame")
    ] = None,
    frame: Annotated[
        int, Form(ge=0, description="which frame of a file or dataset (not of a session)")
    ] = 0,
    params: Annotated[str | None, Form(description="RenderParams as JSON")] = None,
    camera: Annotated[
        str | None, Form(description="Camera as JSON; default frames the molecule")
    ] = None,
    width: Annotated[int, Form()] = 800,
    height: Annotated[int, Form()] = 600,
    format: Annotated[Literal["png", "jpeg"], Form()] = "png",
) -> Response:
    check_size(state, width, height)
    given = [x for x in (file, dataset, session) if x is not None]
    if len(given) != 1:
        raise HTTPException(422, "give exactly one of file, dataset or session")
    render_params = _model(p.RenderParams, params, "params")
    if render_params is not None:
        check_layer_texts(state, render_params, "params")
    cam = _model(p.Camera, camera, "camera")
    held = None
    frame_key = frame
    reference = None
    live = None
    if session is not None:
        if frame:
            raise HTTPException(
                422, "frame: a session renders its latest frame; frame picks one of a file"
            )
        live = state.sessions.get(session)
        if live is None:
            raise HTTPException(404, f"no session named {quoted(session)}")
        if live.topology is None or live.positions is None or live.raw_positions is None:
            raise HTTPException(409, f"session {session!r} has no frame yet")
        topology, positions, box = live.topology, live.raw_positions, live.box
        if render_params is None:
            render_params = live.render_params
        elif "layers" not in render_params.model_fields_set:  # the session's layers
            render_params = render_params.model_copy(update={"layers": live.render_params.layers})
        cam = cam or live.camera
        held, frame_key = live.layers.held, live.positions_id  # its worker has them
    else:
        if render_params is not None:
            check_periodic_texts(state, render_params, "params")
        fits = render_params is not None and render_params.fit != "off"
        workdir = Path(tempfile.mkdtemp(prefix="render-", dir=state.upload_dir))
        try:
            path = (
                await save_upload(file, workdir, state.settings.max_upload_bytes)
                if file
                else _dataset(state, dataset or "")
            )
            topology, positions, box, reference = await _read_frame(
                state, path, frame, role, REFERENCE_FRAME if fits else None
            )
        finally:
            shutil.rmtree(workdir, ignore_errors=True)
    # a file opens on its molecule, as a session does, unless the parameters name layers
    render_params = await asyncio.to_thread(
        opening_params, render_params or p.RenderParams(), topology
    )
    owner = (role, client_address(http.client.host if http.client else None))
    if render_params.layers:
        used, allowed = state.selections.used_s(owner), state.settings.selection_seconds_per_min
        if used >= allowed:
            raise HTTPException(
                429,
                f"your layers' selections took {used:.0f} s of the server's selection workers "
                f"in the last minute (selection_seconds_per_min: {allowed:g}); wait a little",
                headers={"Retry-After": "10"},
            )
    own = held is None and (bool(render_params.layers) or needs_selections(render_params))
    if own:
        held = state.selections.hold(topology)
    slot = f"rest:{uuid.uuid4().hex}"
    try:
        try:  # evaluated by a selection worker (priced first, bounded in time and memory)
            plans = await FrameLayers(render_params, topology, held, owner=owner).plans_async(
                positions, frame_key, box
            )
        except LayerError as exc:
            raise HTTPException(422, f"params.{exc}") from None
        if (
            live is not None
            and live.positions is not None
            and all(
                getattr(render_params, f) == getattr(live.render_params, f) for f in PERIODIC_FIELDS
            )
        ):
            shown, cell = live.positions, live.shown  # displayed already, as asked
        else:
            shown, cell = await _displayed(
                state, slot, render_params, topology, positions, box, held, reference
            )
    finally:
        if own and held is not None:
            held.release()
    if cam is None:
        from server.render.camera import fit_camera
        from server.render.layerplan import visible_atoms

        drawn = visible_atoms(plans, topology.n_atoms)
        cam = fit_camera(shown[drawn] if len(drawn) else shown, width, height)
    request = RenderRequest(
        slot, Snapshot(topology, shown), render_params, cam, width, height, layers=plans
    )
    try:  # in bands of rows: live sessions take their turns between them
        limit = state.settings.one_off_render_seconds
        out = await state.gpu.render_bands(request, limit, gone=http.is_disconnected)
    except RenderError as exc:  # what was sent cannot be drawn on this server's devices
        raise HTTPException(422, f"cannot draw this: {exc}") from None
    finally:
        await state.gpu.release(slot)
    image = out.image()
    outline = displayed_cell(cell, box) if render_params.show_cell else None
    loop = asyncio.get_running_loop()
    if outline is not None:
        image = await loop.run_in_executor(state.encoders, draw_cell, image, cam, outline)
    data, _ms = await loop.run_in_executor(
        state.encoders, state.encoder.encode, image, format, render_params.jpeg_quality
    )
    return Response(data, media_type=f"image/{format}")


@router.post("/api/jobs", status_code=202, summary="Render a trajectory to a zip of PNGs or an MP4")
async def create_job(
    state: State,
    _role: Annotated[p.Role, Depends(steerer_access)],
    _form: FormBody,
    topology: Annotated[UploadFile | None, File(description="topology/structure file")] = None,
    trajectory: Annotated[
        list[UploadFile] | None, File(description="DCD/XTC/TRR/multi-model PDB")
    ] = None,
    dataset: Annotated[str | None, Form(description="topology file under --data-dir")] = None,
    trajectory_dataset: Annotated[
        list[str] | None, Form(description="trajectory files under --data-dir")
    ] = None,
    start: Annotated[int, Form(ge=0)] = 0,
    stop: Annotated[int | None, Form(ge=0)] = None,
    stride: Annotated[int, Form(ge=1)] = 1,
    params: Annotated[str | None, Form()] = None,
    camera: Annotated[str | None, Form()] = None,
    width: Annotated[int, Form()] = 640,
    height: Annotated[int, Form()] = 480,
    output: Annotated[Literal["zip", "mp4"], Form()] = "zip",
    fps: Annotated[float, Form(gt=0, le=240, allow_inf_nan=False)] = 30.0,
) -> JSONResponse:
    check_size(state, width, height)
    if (topology is None) == (dataset is None):
        raise HTTPException(422, "give exactly one of topology (upload) or dataset")
    if stop is not None and stop <= start:  # refused now, not a job that fails once it runs
        raise HTTPException(422, f"stop {stop} must be after start {start}: no frame between")
    render_params = _model(p.RenderParams, params, "params") or p.RenderParams()
    check_layer_texts(state, render_params, "params")
    check_periodic_texts(state, render_params, "params")
    cam = _model(p.Camera, camera, "camera")
    workdir = Path(tempfile.mkdtemp(prefix="job-", dir=state.upload_dir))
    try:
        limit = state.settings.max_upload_bytes
        if topology is not None:
            top = await save_upload(topology, workdir, limit)
            trajs = [
                await save_upload(t, workdir, limit, i + 1) for i, t in enumerate(trajectory or [])
            ]
        else:
            top = _dataset(state, dataset or "")
            trajs = [_dataset(state, t) for t in trajectory_dataset or []]
        # fail fast on unreadable input, before a job exists
        async with state.readers:
            try:
                checked = await asyncio.to_thread(
                    IsolatedStructure,
                    str(top),
                    [str(t) for t in trajs],
                    state.settings.spooled_read_limits(),
                )
            except StructureError as exc:
                raise HTTPException(422, str(exc)) from None
            await asyncio.to_thread(checked.close)
        if start >= checked.n_frames:
            raise HTTPException(
                422, f"start {start} is past the last frame: the trajectory has {checked.n_frames}"
            )
    except BaseException:  # nothing of a refused job stays on disk
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    spec = JobSpec(
        topology=top,
        trajectories=trajs,
        params=render_params,
        camera=cam,
        width=width,
        height=height,
        output=output,
        start=start,
        stop=stop,
        stride=stride,
        fps=fps,
        workdir=workdir,
    )
    job = state.jobs.submit(spec)
    return JSONResponse(
        job.describe(), status_code=202, headers={"Location": f"/api/jobs/{job.id}"}
    )


@router.get("/api/jobs", summary="Jobs, newest first (running and queued ones first)")
async def list_jobs(
    state: State,
    _role: Annotated[p.Role, Depends(steerer_access)],
    active: Annotated[
        bool, Query(description="only those queued or running (a movie still recording)")
    ] = False,
) -> list[dict[str, Any]]:
    jobs = sorted(
        state.jobs.jobs.values(),
        key=lambda j: (j.state in FINAL, -j.created),
    )
    return [j.describe() for j in jobs if not (active and j.state in FINAL)]


def _job(state: AppState, job_id: str) -> Any:
    job = state.jobs.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job {quoted(job_id)}")
    return job


@router.get("/api/jobs/{job_id}", summary="Job state, progress and ETA")
async def get_job(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> dict[str, Any]:
    result: dict[str, Any] = _job(state, job_id).describe()
    return result


@router.get("/api/jobs/{job_id}/result", summary="Download a finished job's output")
async def get_job_result(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> FileResponse:
    job = _job(state, job_id)
    if job.state is not JobState.DONE or job.result is None:
        raise HTTPException(
            409, f"job {job_id} is {job.state.value}" + (f": {job.error}" if job.error else "")
        )
    media = "application/zip" if job.spec.output == "zip" else "video/mp4"
    return FileResponse(job.result, media_type=media, filename=job.result.name)


@router.post(
    "/api/jobs/{job_id}/cancel",
    summary="Stop a queued or running job (a live movie ends keeping its movie); never deletes",
)
async def cancel_job(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> dict[str, Any]:
    """Unlike DELETE, which deletes a job that has ended, this leaves an ended job and its
    output as they are: a client that asks to stop a job just as it finishes keeps what it
    made. The answer's `ending` says how a job still running ends."""
    job = _job(state, job_id)
    if job.state not in FINAL and job.ending() is None:  # else: ended, or ending as asked
        state.jobs.stop(job)
    described: dict[str, Any] = job.describe()
    return described


@router.delete(
    "/api/jobs/{job_id}",
    summary="Cancel a job, stop a live movie (keeping it; again: cancel it), or delete an output",
)
async def delete_job(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> dict[str, Any]:
    job = _job(state, job_id)
    if job.state in FINAL:
        state.jobs.forget(job)
        return {"id": job_id, "deleted": True}
    if state.jobs.stop(job):  # a live movie takes no more frames and keeps its movie
        return {**job.describe(), "finishing": True}
    described: dict[str, Any] = job.describe()
    return described


@router.get("/api/sessions", summary="Live sessions")
async def list_sessions(
    state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> list[dict[str, Any]]:
    return [s.summary() for s in state.sessions.all()]


@router.get("/api/sessions/{session_id}", summary="One session's state")
async def get_session(
    session_id: str, state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> dict[str, Any]:
    live = state.sessions.get(session_id)
    if live is None:
        raise HTTPException(404, f"no session named {quoted(session_id)}")
    return live.summary()


@router.get(
    "/api/sessions/{session_id}/log", summary="The session's steering log (JSON lines as a list)"
)
async def get_session_log(
    session_id: str, state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> list[dict[str, Any]]:
    try:
        entries = await asyncio.to_thread(state.steering_log.read, session_id)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    if not entries and state.sessions.get(session_id) is None:
        raise HTTPException(404, f"no session named {quoted(session_id)}")
    return entries


@router.get("/healthz", summary="Liveness")
async def healthz(state: State) -> dict[str, Any]:
    return {
        "status": "ok",
        "device": state.gpu.device_name,
        # every device a session may be drawn across (--gpus), each with a thread of its own
        "devices": list(state.gpu.devices) or [state.gpu.device_name],
        "encoder": state.encoder.describe(),
        # live sessions' JPEG made where they render (None: read back and encoded as above)
        "encoder_on_device": None if state.gpu.jpeg is None else state.gpu.jpeg.name,
        "video": state.services.video.describe(),
        "sessions": len(state.sessions.all()),
        # how long each device's thread has been on its current work (0 when idle)
        "render": state.gpu.busy(),
        "batch": await _batch_info(state),
    }


async def _batch_info(state: AppState) -> dict[str, Any]:
    """Where jobs render: this process, or the Ray cluster with its workers."""
    batch = state.jobs.batch
    if batch is None:
        return {"engine": "local"}
    info: dict[str, Any] = await asyncio.to_thread(batch.describe)
    workers = [w for w in info.get("workers", []) if w.get("alive", True)]
    state.metrics.batch_workers.set(len(workers))
    return info


@router.get("/metrics", summary="Prometheus metrics")
async def metrics(state: State) -> Response:
    state.metrics.sessions.set(len(state.sessions.all()))
    await _batch_info(state)
    return Response(state.metrics.text(), media_type="text/plain; version=0.0.4")


@router.post(
    "/api/sessions/{session_id}/movies",
    status_code=202,
    summary="Film a live session to an MP4 (a job; DELETE /api/jobs/{id} ends it)",
)
async def record_session(
    session_id: str,
    state: State,
    _role: Annotated[p.Role, Depends(steerer_access)],
    _form: FormBody,
    camera: Annotated[
        str | None, Form(description="Camera as JSON; default the session's camera")
    ] = None,
    width: Annotated[int, Form()] = 640,
    height: Annotated[int, Form()] = 480,
    fps: Annotated[float, Form(gt=0, le=120, allow_inf_nan=False)] = 30.0,
    max_frames: Annotated[int, Form(ge=1, le=100_000)] = 1800,
    max_s: Annotated[
        float | None,
        Form(gt=0, le=86_400, description="seconds of recording (default: movie_max_s, 600)"),
    ] = None,
    owner: Annotated[
        str | None,
        Form(
            max_length=64,
            description="a page's hello.instance: the movie ends when that page leaves",
        ),
    ] = None,
) -> JSONResponse:
    """The frame shown now and each frame the simulation sends from now on, every one, drawn
    with the session's render parameters and layers of its moment (what the dashboard shows)
    and this camera. It takes frames until `max_frames`, `max_s`, `DELETE /api/jobs/{id}`, its
    `owner` leaving the session or the session closing, then renders those still waiting
    and keeps the movie."""
    check_size(state, width, height)
    live = state.sessions.get(session_id)
    if live is None:
        raise HTTPException(404, f"no session named {quoted(session_id)}")
    cam = _model(p.Camera, camera, "camera") or live.camera
    if cam is None:
        raise HTTPException(409, f"session {session_id!r} has no frame yet to frame a camera on")
    spec = JobSpec(
        topology=Path(),
        trajectories=[],
        params=live.render_params,
        camera=cam,
        width=width,
        height=height,
        output="mp4",
        stop=max_frames,
        fps=fps,
        session=session_id,
        max_s=max_s or state.settings.movie_max_s,
    )
    told = [-SKIP_NOTICE_S]

    def skipped(frames: MovieQueue, step: int) -> None:
        if time.monotonic() - told[0] >= SKIP_NOTICE_S:  # at once, then once in a while
            told[0] = time.monotonic()
            live.broadcast(
                p.Event(
                    level="warning",
                    code="movie_skipped",
                    message=f"movie {job.id}: {frames.skip_warning()}",
                    step=step,
                )
            )

    def behind(frames: MovieQueue) -> None:
        live.broadcast(
            p.Event(
                level="info",
                code="movie_behind",
                message=f"movie {job.id}: {frames.behind_notice()}",
            )
        )

    frames = MovieQueue(state.settings.movie_queue_bytes, max_frames, skipped, behind)

    def take(step: int) -> None:  # a frame as displayed (periodic steps done)
        snap = live.snapshot()
        if snap is not None:
            frames.offer(MovieFrame(replace(snap, step=step), live.render_params, live.box))

    now = live.snapshot()
    if now is not None:  # the frame on the screen when the movie starts
        frames.offer(MovieFrame(now, live.render_params, live.box))

    async def session_closed() -> None:
        frames.close(f"session {session_id!r} closed")

    def unhook() -> None:
        if take in live.shown_sinks:
            live.shown_sinks.remove(take)
        if session_closed in live.close_hooks:
            live.close_hooks.remove(session_closed)

    live.shown_sinks.append(take)
    live.close_hooks.append(session_closed)
    job = state.jobs.record(spec, frames, lambda: live.layers.held, owner)
    frames.when_closed(unhook)
    if owner is not None:

        async def end(why: str) -> None:
            state.jobs.finish(job, why)

        state.owners.own(live, owner, job.id, end)
        frames.when_closed(lambda: state.owners.done(job.id))
    return JSONResponse(
        job.describe(), status_code=202, headers={"Location": f"/api/jobs/{job.id}"}
    )
