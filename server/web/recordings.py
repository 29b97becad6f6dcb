"""REST routes for recordings of steered sessions: start and stop, list, download, replay with
the steering marks on the timeline, and export to an MP4 with the steering drawn on it.

The recording itself is `server.pipeline.recordings`; its steering span is bracketed by two
entries of the session's steering log (`recording_started`, `recording_stopped`), so the log
says when a run was recorded too. Like jobs, recordings need the server token.
"""

from __future__ import annotations

import asyncio
import io
import time
import zipfile
from concurrent.futures import Future
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

import protocol as p
from server.pipeline.jobs import JobSpec
from server.pipeline.marks import pull_path
from server.pipeline.recordings import FILES, Recording
from server.web.access import GatedRoute, steerer_access
from server.web.rest import SKIP_NOTICE_S, State, check_layer_texts, check_size
from server.web.validation import quoted

router = APIRouter(route_class=GatedRoute)
Steerer = Annotated[p.Role, Depends(steerer_access)]


class RecordingRequest(BaseModel):
    """How to record: every `stride`-th frame, up to `max_bytes` of trajectory; `owner` ties
    the recording to a page (`hello.instance`): it stops when that page leaves."""

    model_config = ConfigDict(extra="forbid")
    stride: int = Field(1, ge=1, le=100_000)
    max_bytes: int | None = Field(None, ge=1 << 16, description="default: the server's limit")
    owner: str | None = Field(
        None, max_length=64, description="a page's hello.instance: stopped when it leaves"
    )


class MovieRequest(BaseModel):
    """An MP4 of a recording, optionally with its steering drawn on it."""

    model_config = ConfigDict(extra="forbid")
    width: int = Field(640, ge=16)
    height: int = Field(480, ge=16)
    fps: float = Field(30.0, gt=0, le=120)
    stride: int = Field(1, ge=1)
    overlay: bool = True
    """Steering actions as captions and pulls as arrows."""
    caption_s: float = Field(2.0, ge=0, le=60)
    """How long (movie seconds) a caption stays after its action."""
    camera: p.Camera | None = None
    """Default: the session's camera when the recording started."""
    params: p.RenderParams | None = None
    """Default: the session's render parameters when the recording started."""


def _recording(state: State, rec_id: str) -> Recording:
    rec = state.recordings.get(rec_id)
    if rec is None:
        raise HTTPException(404, f"no recording {quoted(rec_id)}")
    return rec


def _kept(state: State, rec: Recording) -> None:
    """(Right before what reads `rec`'s files starts, with no await between: a movie job, a
    replay.) Refuses a recording whose deletion is under way or done: the reader would lose
    its files halfway."""
    if rec.deleting or state.recordings.get(rec.id) is not rec:
        raise HTTPException(409, f"recording {rec.id} is being deleted")


def _movies_of(state: State, rec: Recording) -> None:
    """Refuses to delete `rec` while a movie of it is queued or rendering (409 naming it)."""
    movies = state.jobs.reading(rec.directory)
    if not movies:
        return
    said = ", ".join(
        f"{j.id} ({'being cancelled' if j.ending() == 'cancelling' else j.state.value})"
        for j in movies
    )
    how = (
        "retry once it has ended"
        if all(j.ending() == "cancelling" for j in movies)
        else f"cancel it first (POST /api/jobs/{movies[0].id}/cancel) or wait for it to end"
    )
    raise HTTPException(
        409, f"recording {rec.id} is being rendered to a movie by job {said}; {how}"
    )


def _finished(rec: Recording) -> None:
    if rec.running:
        raise HTTPException(409, f"recording {rec.id} is still recording; stop it first")
    if rec.frames == 0:
        raise HTTPException(409, f"recording {rec.id} holds no frame")


@router.post(
    "/api/sessions/{session_id}/recordings",
    status_code=201,
    summary="Record a session's frames and steering (until stopped)",
)
async def start_recording(
    session_id: str, state: State, _role: Steerer, body: RecordingRequest | None = None
) -> JSONResponse:
    body = body or RecordingRequest()
    live = state.sessions.get(session_id)
    if live is None:
        raise HTTPException(404, f"no session named {quoted(session_id)}")
    if live.topology is None:
        raise HTTPException(409, f"session {session_id!r} has no simulation topology yet")
    for rec in state.recordings.recordings.values():
        if rec.running and rec.session == session_id:
            raise HTTPException(409, f"session {session_id!r} is already recording ({rec.id})")
    # claimed before the first await: of concurrent starts, one records and the others get 409
    if session_id in state.recordings.starting:
        raise HTTPException(409, f"session {session_id!r} is already starting a recording")
    state.recordings.starting.add(session_id)
    try:
        first_id, written = live.log_event({"event": "recording_started"})
        await asyncio.wrap_future(written)
        limit = min(body.max_bytes or state.settings.recording_max_bytes,
                    state.settings.recording_max_bytes)  # fmt: skip
        rec = state.recordings.start(
            session_id,
            live.topology,
            live.render_params,
            live.camera,
            first_id,
            body.stride,
            limit,
            state.settings.recording_queue_bytes,
            body.owner,
        )
    finally:
        state.recordings.starting.discard(session_id)
    told = [-SKIP_NOTICE_S]

    def sink(step: int, time_ps: float, positions: Any, box: Any) -> None:
        kept = state.recordings.add(rec, step, time_ps, positions, box)
        if not kept and time.monotonic() - told[0] >= SKIP_NOTICE_S:
            told[0] = time.monotonic()  # everyone in the session hears of it, once in a while
            live.broadcast(
                p.Event(
                    level="warning",
                    code="recording_skipped",
                    message=f"recording {rec.id}: {rec.skip_warning()}",
                    step=step,
                )
            )
        if not rec.running and sink in live.frame_sinks:  # capped
            live.frame_sinks.remove(sink)
            state.owners.done(rec.id)

    async def session_closed() -> None:
        if rec.running:  # (the server's shutdown may have ended it already)
            await _stop(state, rec, f"session {session_id!r} closed")

    def detach() -> tuple[int, Future[None]]:
        if sink in live.frame_sinks:
            live.frame_sinks.remove(sink)
        if session_closed in live.close_hooks:
            live.close_hooks.remove(session_closed)
        return live.log_event({"event": "recording_stopped", "recording": rec.id})

    rec.detach = detach
    live.frame_sinks.append(sink)
    live.close_hooks.append(session_closed)  # a reaped session ends its recording
    if body.owner is not None:

        async def owner_left(why: str) -> None:
            if rec.running:
                await _stop(state, rec, why)

        state.owners.own(live, body.owner, rec.id, owner_left)
    return JSONResponse(
        rec.describe(), status_code=201, headers={"Location": f"/api/recordings/{rec.id}"}
    )


async def _stop(state: State, rec: Recording, why: str | None = None) -> None:
    """Unhook the recording, mark its end in the session's log, write what is queued; `why`
    says what ended it when no one asked (kept in `ended_because`)."""
    state.owners.done(rec.id)
    if why is not None and rec.running:
        rec.ended_because = why
    last_id = None
    if rec.detach is not None:
        last_id, written = rec.detach()
        rec.detach = None
        await asyncio.wrap_future(written)
    await asyncio.to_thread(state.recordings.stop, rec, last_id)


@router.post("/api/recordings/{rec_id}/stop", summary="Stop a recording, keeping it")
async def stop_recording(rec_id: str, state: State, _role: Steerer) -> dict[str, Any]:
    rec = _recording(state, rec_id)
    await _stop(state, rec)
    return _described(rec)


def _described(rec: Recording) -> dict[str, Any]:
    out = rec.describe()
    if not rec.running:
        out["marks"] = rec.marks()
    return out


@router.get("/api/recordings", summary="Recordings, newest first")
async def list_recordings(state: State, _role: Steerer) -> list[dict[str, Any]]:
    recs = sorted(state.recordings.recordings.values(), key=lambda r: r.started, reverse=True)
    return [r.describe() for r in recs]


@router.get("/api/recordings/{rec_id}", summary="A recording: state, size, steering marks")
async def get_recording(rec_id: str, state: State, _role: Steerer) -> dict[str, Any]:
    return _described(_recording(state, rec_id))


@router.get("/api/recordings/{rec_id}/files/{name}", summary="One file of a recording")
async def get_recording_file(rec_id: str, name: str, state: State, _role: Steerer) -> FileResponse:
    rec = _recording(state, rec_id)
    if name not in FILES or not (rec.directory / name).is_file():
        raise HTTPException(404, f"recording {rec_id} has no file {quoted(name)}")
    return FileResponse(rec.directory / name, filename=f"{rec.id}-{name}")


@router.get("/api/recordings/{rec_id}/download", summary="A recording's files as one zip")
async def download_recording(rec_id: str, state: State, _role: Steerer) -> StreamingResponse:
    rec = _recording(state, rec_id)
    _finished(rec)

    def pack() -> bytes:
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as z:
            for name in FILES:
                if (rec.directory / name).is_file():
                    z.write(rec.directory / name, f"{rec.id}/{name}")
        return buffer.getvalue()

    data = await asyncio.to_thread(pack)
    return StreamingResponse(
        iter([data]),
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{rec.id}.zip"'},
    )


@router.delete(
    "/api/recordings/{rec_id}",
    summary="Delete a recording (stopping it, and any replay of it, first)",
)
async def delete_recording(rec_id: str, state: State, _role: Steerer) -> dict[str, Any]:
    rec = _recording(state, rec_id)
    if rec.deleting:
        raise HTTPException(409, f"recording {rec_id} is being deleted already")
    _movies_of(state, rec)
    rec.deleting = True  # from here no movie or replay of it starts (`_kept`)
    # a replay of it would play on from the files it has open, deleted under it
    replays = [
        name
        for name, replay in state.replays.processes.items()
        if replay.recording == rec.id and replay.process.poll() is None
    ]
    try:
        if rec.running:
            await _stop(state, rec)
        for name in replays:
            await asyncio.to_thread(state.replays.stop, name)
        await asyncio.to_thread(state.recordings.delete, rec)
    except BaseException:
        rec.deleting = False
        raise
    return {"id": rec_id, "deleted": True, "replays_stopped": replays}


@router.post(
    "/api/recordings/{rec_id}/replay",
    status_code=201,
    summary="Replay a recording as a session, with its steering marks on the timeline",
)
async def replay_recording(
    rec_id: str, request: Request, state: State, _role: Steerer, fps: float = 30.0
) -> dict[str, Any]:
    rec = _recording(state, rec_id)
    _kept(state, rec)
    _finished(rec)
    if not 0 < fps <= 240:
        raise HTTPException(422, "fps: must be in (0, 240]")
    name = f"replay-{rec.id[1:13]}"
    running = state.replays.processes.get(name)
    if running is not None and running.process.poll() is None:
        return {**running.describe(), "recording": rec.id}
    files = [rec.directory / "topology.pdb", rec.directory / "frames.xtc"]
    port = int(request.scope["server"][1])
    replay = state.replays.start(
        name,
        files,
        port,
        state.settings.token,
        fps,
        False,
        state.settings.state_dir / "replays",
        recording=rec.id,
    )
    return {**replay.describe(), "n_frames": rec.frames}


@router.post(
    "/api/recordings/{rec_id}/movie",
    status_code=202,
    summary="Render a recording to an MP4 (a job), with its steering drawn on it",
)
async def recording_movie(
    rec_id: str, state: State, _role: Steerer, body: MovieRequest | None = None
) -> JSONResponse:
    body = body or MovieRequest()
    rec = _recording(state, rec_id)
    _kept(state, rec)
    _finished(rec)
    check_size(state, body.width, body.height)
    started = p.RenderParams.model_validate(rec.render_params)
    params = body.params or started
    if "layers" not in params.model_fields_set:  # the layers of the recording's start
        params = params.model_copy(update={"layers": started.layers})
    check_layer_texts(state, params, "params")
    camera = body.camera or (p.Camera.model_validate(rec.camera) if rec.camera else None)
    overlay = None
    if body.overlay:
        entries = await asyncio.to_thread(rec.steering)
        steps = await asyncio.to_thread(rec.frame_steps)
        overlay = {
            "marks": rec.marks(),
            "pulls": pull_path(entries, steps),
            "hold_frames": max(1, round(body.caption_s * body.fps)),
        }
    spec = JobSpec(
        topology=rec.directory / "topology.pdb",
        trajectories=[rec.directory / "frames.xtc"],
        params=params,
        camera=camera,
        width=body.width,
        height=body.height,
        output="mp4",
        stride=body.stride,
        fps=body.fps,
        overlay=overlay,
        expected_frames=rec.frames,
    )
    _kept(state, rec)  # its deletion may have begun during the reads above
    job = state.jobs.submit(spec)
    return JSONResponse(
        job.describe(), status_code=202, headers={"Location": f"/api/jobs/{job.id}"}
    )
