"""REST API: one-off renders, batch trajectory jobs, sessions, health and metrics.

Inputs are structures uploaded as files or named datasets under `--data-dir` (never any other
server path). Every failure is a 4xx naming what was wrong; server faults are logged, not leaked.
"""

from __future__ import annotations

import asyncio
import json
import re
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import ValidationError

import protocol as p
from server.pipeline.gpu import RenderRequest, Snapshot
from server.pipeline.jobs import FINAL, JobSpec, JobState
from server.web.auth import token_role
from server.web.state import AppState

router = APIRouter()


def app_state(request: Request) -> AppState:
    state: AppState = request.app.state.scalesteer
    return state


def _token(request: Request) -> str | None:
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return request.headers.get("x-scalesteer-token") or request.query_params.get("token")


def viewer_access(request: Request) -> p.Role:
    role = token_role(app_state(request).settings, _token(request))
    if role is None:
        raise HTTPException(401, "missing or wrong token (Authorization: Bearer TOKEN or ?token=)")
    return role


def steerer_access(request: Request) -> p.Role:
    role = viewer_access(request)
    if role != "steerer":
        raise HTTPException(403, "this needs the server token; the viewer token is read-only")
    return role


State = Annotated[AppState, Depends(app_state)]


def _model(cls: type[Any], raw: str | None, field: str) -> Any:
    if raw is None or raw == "":
        return None
    try:
        return cls.model_validate(json.loads(raw))
    except json.JSONDecodeError as exc:
        raise HTTPException(422, f"{field}: not valid JSON ({exc.msg})") from None
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        where = ".".join(str(x) for x in err["loc"])
        raise HTTPException(
            422, f"{field}.{where}: {err['msg']}" if where else f"{field}: {err['msg']}"
        ) from None


def _dataset(state: AppState, name: str) -> Path:
    root = state.settings.data_dir
    if root is None:
        raise HTTPException(404, "this server has no --data-dir; upload the file instead")
    base = root.resolve()
    path = (base / name).resolve()
    if not path.is_relative_to(base) or not path.is_file():
        raise HTTPException(404, f"no dataset named {name!r}")
    return path


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


async def _save_upload(upload: UploadFile, directory: Path, limit: int, index: int = 0) -> Path:
    """Stream an upload to `directory` under a unique, safe name that keeps its extension."""
    name = _UNSAFE.sub("_", Path(upload.filename or "upload").name).lstrip(".")
    if not name:
        raise HTTPException(422, f"unusable file name {upload.filename!r}")
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


def _check_size(state: AppState, width: int, height: int) -> None:
    lim = state.settings.limits
    if width < 1 or height < 1:
        raise HTTPException(422, f"image size {width}x{height}: width and height must be >= 1")
    if max(width, height) > lim.max_image_side or width * height > lim.max_image_pixels:
        raise HTTPException(
            422, f"image size {width}x{height} exceeds the limit ({lim.max_image_side} px a side)"
        )


@router.post(
    "/api/render",
    responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}},
    summary="Render one image of an uploaded structure, a dataset, or a live session",
)
async def render_image(
    state: State,
    _role: Annotated[p.Role, Depends(viewer_access)],
    file: Annotated[UploadFile | None, File(description="PDB, mmCIF, GRO or XYZ")] = None,
    dataset: Annotated[
        str | None, Form(description="file name under the server's --data-dir")
    ] = None,
    session: Annotated[
        str | None, Form(description="a live session: render its latest frame")
    ] = None,
    frame: Annotated[int, Form(ge=0)] = 0,
    params: Annotated[str | None, Form(description="RenderParams as JSON")] = None,
    camera: Annotated[
        str | None, Form(description="Camera as JSON; default frames the molecule")
    ] = None,
    width: Annotated[int, Form()] = 800,
    height: Annotated[int, Form()] = 600,
    format: Annotated[Literal["png", "jpeg"], Form()] = "png",
) -> Response:
    _check_size(state, width, height)
    given = [x for x in (file, dataset, session) if x is not None]
    if len(given) != 1:
        raise HTTPException(422, "give exactly one of file, dataset or session")
    render_params = _model(p.RenderParams, params, "params")
    cam = _model(p.Camera, camera, "camera")
    if session is not None:
        live = state.sessions.get(session)
        if live is None:
            raise HTTPException(404, f"no session named {session!r}")
        if live.topology is None or live.positions is None:
            raise HTTPException(409, f"session {session!r} has no frame yet")
        topology, positions = live.topology, live.positions
        render_params = render_params or live.render_params
        cam = cam or live.camera
    else:
        from structures.reader import StructureError, load

        workdir = Path(tempfile.mkdtemp(prefix="render-", dir=state.upload_dir))
        try:
            path = (
                await _save_upload(file, workdir, state.settings.max_upload_bytes)
                if file
                else _dataset(state, dataset or "")
            )
            try:
                structure = await asyncio.to_thread(
                    load, str(path), (), max_atoms=state.settings.limits.max_atoms
                )
                if frame >= structure.n_frames:
                    raise HTTPException(
                        422, f"frame {frame} out of range: the file has {structure.n_frames}"
                    )
                positions = await asyncio.to_thread(structure.positions, frame)
            except StructureError as exc:
                raise HTTPException(422, str(exc)) from None
            topology = structure.topology
        finally:
            shutil.rmtree(workdir, ignore_errors=True)
    render_params = render_params or p.RenderParams()
    if cam is None:
        from server.render.camera import fit_camera

        cam = fit_camera(positions, width, height)
    slot = f"rest:{uuid.uuid4().hex}"
    request = RenderRequest(slot, Snapshot(topology, positions), render_params, cam, width, height)
    try:
        out = await state.gpu.render(request)
    finally:
        await state.gpu.release(slot)
    data, _ms = await asyncio.get_running_loop().run_in_executor(
        state.encoders, state.encoder.encode, out.rgba, format, render_params.jpeg_quality
    )
    return Response(data, media_type=f"image/{format}")


@router.post("/api/jobs", status_code=202, summary="Render a trajectory to a zip of PNGs or an MP4")
async def create_job(
    state: State,
    _role: Annotated[p.Role, Depends(steerer_access)],
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
    fps: Annotated[float, Form(gt=0, le=240)] = 30.0,
) -> JSONResponse:
    _check_size(state, width, height)
    if (topology is None) == (dataset is None):
        raise HTTPException(422, "give exactly one of topology (upload) or dataset")
    render_params = _model(p.RenderParams, params, "params") or p.RenderParams()
    cam = _model(p.Camera, camera, "camera")
    from structures.reader import StructureError, load

    workdir = Path(tempfile.mkdtemp(prefix="job-", dir=state.upload_dir))
    try:
        limit = state.settings.max_upload_bytes
        if topology is not None:
            top = await _save_upload(topology, workdir, limit)
            trajs = [
                await _save_upload(t, workdir, limit, i + 1) for i, t in enumerate(trajectory or [])
            ]
        else:
            top = _dataset(state, dataset or "")
            trajs = [_dataset(state, t) for t in trajectory_dataset or []]
        try:  # fail fast on unreadable input, before a job exists
            await asyncio.to_thread(
                load, str(top), [str(t) for t in trajs], max_atoms=state.settings.limits.max_atoms
            )
        except StructureError as exc:
            raise HTTPException(422, str(exc)) from None
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


def _job(state: AppState, job_id: str) -> Any:
    job = state.jobs.jobs.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job {job_id!r}")
    return job


@router.get("/api/jobs/{job_id}", summary="Job state, progress and ETA")
async def get_job(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> dict[str, Any]:
    result: dict[str, Any] = _job(state, job_id).describe()
    return result


@router.get("/api/jobs/{job_id}/result", summary="Download a finished job's output")
async def get_job_result(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> FileResponse:
    job = _job(state, job_id)
    if job.state is not JobState.DONE or job.result is None:
        raise HTTPException(
            409, f"job {job_id} is {job.state.value}" + (f": {job.error}" if job.error else "")
        )
    media = "application/zip" if job.spec.output == "zip" else "video/mp4"
    return FileResponse(job.result, media_type=media, filename=job.result.name)


@router.delete("/api/jobs/{job_id}", summary="Cancel a job (or delete a finished one's output)")
async def delete_job(
    job_id: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> dict[str, Any]:
    job = _job(state, job_id)
    if job.state in FINAL:
        state.jobs.forget(job)
        return {"id": job_id, "deleted": True}
    state.jobs.cancel(job)
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
        raise HTTPException(404, f"no session named {session_id!r}")
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
        raise HTTPException(404, f"no session named {session_id!r}")
    return entries


@router.get("/healthz", summary="Liveness")
async def healthz(state: State) -> dict[str, Any]:
    return {
        "status": "ok",
        "device": state.gpu.actual_device or state.settings.device,
        "encoder": state.encoder.describe(),
        "sessions": len(state.sessions.all()),
    }


@router.get("/metrics", summary="Prometheus metrics")
async def metrics(state: State) -> Response:
    state.metrics.sessions.set(len(state.sessions.all()))
    return Response(state.metrics.text(), media_type="text/plain; version=0.0.4")
