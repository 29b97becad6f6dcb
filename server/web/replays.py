"""REST routes for replays started from the dashboard: files opened in the browser become a
replay session (the children themselves: `server.web.children`).

The files are saved into the server's data directory (`--data-dir`, or `<state-dir>/data`),
checked by the isolated reader, then played by `scalesteer replay` in a child process of its own
(a damaged file can never take the server down) that connects back to this server's `/ws/sim`
with the server token. The child is stopped with its session's `stop` control, by
`DELETE /api/replays/{session}`, or when the server stops.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import re
import shutil
import time
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, UploadFile

import protocol as p
from protocol.messages import SESSION_NAME
from server.web.access import GatedRoute, steerer_access, viewer_access
from server.web.children import ReplayManager
from server.web.forms import FormBody
from server.web.rest import State, save_upload
from server.web.state import AppState
from server.web.validation import quoted
from structures.errors import StructureError
from structures.isolated import IsolatedStructure

log = logging.getLogger("scalesteer.replays")

router = APIRouter(route_class=GatedRoute)
_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _library(state: AppState) -> Path:
    """Where opened files are kept: the data directory, so they become datasets too."""
    root = state.settings.data_dir or state.settings.state_dir / "data"
    return root / "opened"


def _taken(state: AppState, name: str) -> bool:
    """Whether session `name` has a simulation, or a replay child that is still running."""
    running = state.replays.processes.get(name)
    live = state.sessions.get(name)
    return (running is not None and running.process.poll() is None) or (
        live is not None and live.sim is not None
    )


def _fresh_name(state: AppState, base: str) -> str:
    """`base`, or `base-2`, `base-3`, ... : the first that no simulation plays (the same
    files opened twice play side by side)."""
    base = base if re.match(SESSION_NAME, base) and base != "replay-" else "replay-upload"
    for n in range(1, state.settings.max_sessions + 2):
        name = base if n == 1 else f"{base}-{n}"
        if not _taken(state, name):
            return name
    raise HTTPException(
        409,
        f"{base}: {state.settings.max_sessions} sessions of that name play already "
        "(max_sessions); stop one of them first",
    )


@router.post("/api/replays", status_code=201, summary="Open files as a replay session")
async def open_replay(
    request: Request,
    state: State,
    _role: Annotated[p.Role, Depends(steerer_access)],
    _form: FormBody,
    topology: Annotated[UploadFile, File(description="structure or topology file")],
    trajectory: Annotated[
        list[UploadFile] | None, File(description="trajectory files (DCD, XTC, TRR, ...)")
    ] = None,
    session: Annotated[
        str | None,
        Form(description="session name (default: replay-<file>, numbered when that one plays)"),
    ] = None,
    fps: Annotated[float, Form(gt=0, le=240, allow_inf_nan=False)] = 30.0,
    loop: Annotated[bool, Form()] = False,
) -> dict[str, Any]:
    manager: ReplayManager = state.replays
    filename = topology.filename or "upload"
    if session is not None:
        name = session
        if not re.match(SESSION_NAME, name):
            raise HTTPException(422, f"session: {name!r} is not a usable session name")
        if _taken(state, name):
            raise HTTPException(
                409,
                f"session {name!r} already plays a simulation; name another session to open "
                f"{filename} in, or leave the name out to get a fresh one",
            )
    else:
        name = _fresh_name(state, "replay-" + _SAFE.sub("-", Path(filename).stem).strip("-.")[:40])
    if state.sessions.full(name):  # its child would be refused, and retry for 30 s first
        raise HTTPException(
            503,
            f"the server holds its limit of {state.sessions.limit} sessions (max_sessions); "
            f"open {filename} in a session that exists, or wait for one to close",
            headers={"Retry-After": "30"},
        )
    folder = _library(state) / f"{name}-{int(time.time())}"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        limit = state.settings.max_upload_bytes
        files = [await save_upload(topology, folder, limit)]
        files += [
            await save_upload(t, folder, limit, i + 1) for i, t in enumerate(trajectory or [])
        ]
        async with state.readers:
            try:
                checked = await asyncio.to_thread(
                    IsolatedStructure,
                    str(files[0]),
                    [str(f) for f in files[1:]],
                    state.settings.spooled_read_limits(),
                )
            except StructureError as exc:
                raise HTTPException(422, str(exc)) from None
            n_frames = checked.n_frames
            await asyncio.to_thread(checked.close)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    port = int(request.scope["server"][1])
    replay = manager.start(
        name, files, port, state.settings.token, fps, loop, state.settings.state_dir / "replays"
    )
    manager.watch(replay, functools.partial(_replay_failed, state, name))
    await asyncio.sleep(0)
    described = replay.describe()
    described["n_frames"] = n_frames
    return described


def _replay_failed(state: AppState, session: str, why: str) -> None:
    """A replay child ended with a failure: said in the log and to its session's viewers
    (their dashboard had only shown the simulation as gone)."""
    log.warning("the replay of session %s stopped: %s", session, why)
    live = state.sessions.get(session)
    if live is not None:
        message = f"the replay stopped: {why}"[:1024]
        live.simulation_stopped(p.Event(level="error", code="replay_failed", message=message))


@router.get("/api/replays", summary="Replays opened from the dashboard")
async def list_replays(
    state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> list[dict[str, Any]]:
    out = []
    for replay in state.replays.processes.values():
        described = replay.describe()
        if not described["running"]:
            described["last_words"] = replay.why_ended()
        out.append(described)
    return out


@router.get("/api/replays/{session}", summary="One replay opened from the dashboard")
async def get_replay(
    session: str, state: State, _role: Annotated[p.Role, Depends(viewer_access)]
) -> dict[str, Any]:
    replay = state.replays.processes.get(session)
    if replay is None:
        raise HTTPException(404, f"no replay for session {quoted(session)}")
    described = replay.describe()
    if not described["running"]:
        described["last_words"] = replay.why_ended()
    rec = state.recordings.get(replay.recording) if replay.recording else None
    if rec is not None:  # the timeline's steering marks, for viewers too
        described["marks"] = rec.marks()
    return described


@router.delete("/api/replays/{session}", summary="Stop a replay opened from the dashboard")
async def stop_replay(
    session: str, state: State, _role: Annotated[p.Role, Depends(steerer_access)]
) -> dict[str, Any]:
    with contextlib.suppress(KeyError):
        if await asyncio.to_thread(state.replays.stop, session):
            return state.replays.processes[session].describe()
    raise HTTPException(404, f"no replay for session {quoted(session)}")
