"""Batch trajectory renders: background jobs on the shared GPU queue, with progress and cancel.

A job renders frame by frame (each frame is its own GPU submission, so live sessions keep their
turn), writes to a temporary file, and only a complete file is reported `done`; anything that
goes wrong marks the job `failed` with the reason and removes the partial output.

Job records are files (`<jobs dir>/<id>.json`, written atomically at every change of state), so a
restart loses none: a job that was queued or running starts again from its kept inputs (or fails
saying why, when they are gone), a finished job's output stays downloadable. Ids are random
(128 bits), so a job is reachable only by whoever was given its id. Input files are read in a
child process (`structures.isolated`): a file that crashes the reader fails its job, not the
server.

Kept whole: a job's life (queued, rendering, done or failed, started again from its record after a
restart) is one state machine in `JobManager`, and the records it keeps are written and read only
here.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import json
import logging
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import protocol as p
from server.metrics import Metrics
from server.pipeline.distributed import ChunkInputs, RayBatch, upload_refs
from server.pipeline.encoder import encode_image
from server.pipeline.gpu import DisplayRequest, GpuQueue, RenderRequest, Snapshot
from server.pipeline.history import time_window
from server.pipeline.livemovie import MovieQueue
from server.pipeline.movie import FrameWriter, Mp4Writer, ZipWriter
from server.pipeline.overlay import draw_cell, draw_overlay
from server.pipeline.periodic import (
    REFERENCE_FRAME,
    PeriodicError,
    PeriodicOptions,
    displayed_cell,
    needs_display,
    needs_selections,
)
from server.pipeline.selections import FrameLayers, LayerError, opening_params
from server.render.errors import RenderError
from structures.errors import StructureError
from structures.isolated import IsolatedStructure, ReadLimits
from structures.selection_pool import Held, SelectionPool

SelectionsOf = Callable[[], Held | None]
"""The live session's selection worker, where a movie's layers are evaluated."""

log = logging.getLogger("scalesteer.jobs")


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"
    EXPIRED = "expired"
    """Done, but its output was removed by the retention policy (`error` says why)."""


FINAL = (JobState.DONE, JobState.FAILED, JobState.CANCELLED, JobState.EXPIRED)
MAX_RECORDS = 1000
"""Finished job records kept (oldest forgotten first); outputs follow the retention policy."""
JOB_ID = re.compile(r"^j[A-Za-z0-9_-]{22}$")


@dataclass
class JobSpec:
    topology: Path
    trajectories: list[Path]
    params: p.RenderParams
    camera: p.Camera | None
    width: int
    height: int
    output: Literal["zip", "mp4"]
    start: int = 0
    stop: int | None = None
    stride: int = 1
    fps: float = 30.0
    workdir: Path | None = None  # uploaded files live here; removed with the job
    session: str | None = None
    """A recording of this live session (no input files): its next `stop` frames."""
    overlay: dict[str, Any] | None = None
    """Steering drawn on the frames (`server.pipeline.overlay`): marks, pulls, hold_frames."""
    expected_frames: int | None = None
    """Frames the input should hold (a recording's count): fewer readable ones (a file cut
    short) make the output partial, and the job says so."""
    max_s: float | None = None
    """A movie of a live session takes frames for at most this long (seconds)."""

    def record(self) -> dict[str, Any]:
        """A JSON-able form, to survive restarts."""
        return {
            "session": self.session,
            "topology": str(self.topology),
            "trajectories": [str(t) for t in self.trajectories],
            # unset fields stay unset: parameters that name no layers get the default ones
            "params": self.params.model_dump(mode="json", exclude_unset=True),
            "camera": self.camera.model_dump(mode="json") if self.camera else None,
            "width": self.width,
            "height": self.height,
            "output": self.output,
            "start": self.start,
            "stop": self.stop,
            "stride": self.stride,
            "fps": self.fps,
            "workdir": str(self.workdir) if self.workdir else None,
            "overlay": self.overlay,
            "expected_frames": self.expected_frames,
            "max_s": self.max_s,
        }

    @classmethod
    def from_record(cls, raw: dict[str, Any]) -> JobSpec:
        camera = raw.get("camera")
        workdir = raw.get("workdir")
        return cls(
            topology=Path(raw["topology"]),
            trajectories=[Path(t) for t in raw["trajectories"]],
            params=p.RenderParams.model_validate(raw["params"]),
            camera=p.Camera.model_validate(camera) if camera else None,
            width=int(raw["width"]),
            height=int(raw["height"]),
            output=raw["output"],
            start=int(raw["start"]),
            stop=None if raw["stop"] is None else int(raw["stop"]),
            stride=int(raw["stride"]),
            fps=float(raw["fps"]),
            workdir=Path(workdir) if workdir else None,
            session=raw.get("session"),
            overlay=raw.get("overlay"),
            expected_frames=raw.get("expected_frames"),
            max_s=raw.get("max_s"),
        )


@dataclass
class Job:
    id: str
    spec: JobSpec
    state: JobState = JobState.QUEUED
    total: int = 0
    done: int = 0
    created: float = field(default_factory=time.time)
    started: float | None = None
    finished: float | None = None
    error: str | None = None
    result: Path | None = None
    restarts: int = 0
    """How many server restarts found this job unfinished (each started it again)."""
    stage: str | None = None
    """What a running job is doing before its first frame: reading its input, starting Ray."""
    partial: bool = False
    """The output holds fewer frames than its input should have given (`warning` says why)."""
    warning: str | None = None
    owner: str | None = None
    """The page (`hello.instance`) whose leaving ends this job (None: nobody's)."""
    frames: MovieQueue | None = None
    """A movie of a live session: the frames taken and not yet rendered."""
    cancel: threading.Event = field(default_factory=threading.Event)
    task: asyncio.Task[None] | None = None

    def record(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "spec": self.spec.record(),
            "state": self.state.value,
            "total": self.total,
            "done": self.done,
            "created": self.created,
            "started": self.started,
            "finished": self.finished,
            "error": self.error,
            "result": str(self.result) if self.result else None,
            "restarts": self.restarts,
            "partial": self.partial,
            "warning": self.warning,
        }

    @classmethod
    def from_record(cls, raw: dict[str, Any]) -> Job:
        return cls(
            id=str(raw["id"]),
            spec=JobSpec.from_record(raw["spec"]),
            state=JobState(raw["state"]),
            total=int(raw["total"]),
            done=int(raw["done"]),
            created=float(raw["created"]),
            started=raw["started"],
            finished=raw["finished"],
            error=raw["error"],
            result=Path(raw["result"]) if raw["result"] else None,
            restarts=int(raw.get("restarts", 0)),
            partial=bool(raw.get("partial", False)),
            warning=raw.get("warning"),
        )

    def describe(self) -> dict[str, Any]:
        eta = None
        if self.state is JobState.RUNNING and self.started and self.done:
            rate = self.done / (time.time() - self.started)
            eta = (self.total - self.done) / rate if rate > 0 else None
        return {
            "id": self.id,
            "state": self.state.value,
            "progress": {"done": self.done, "total": self.total},
            "eta_s": eta,
            "error": self.error,
            "output": self.spec.output,
            "session": self.spec.session,
            "created": self.created,
            "started": self.started,
            "finished": self.finished,
            "restarts": self.restarts,
            "stage": self.stage if self.state is JobState.RUNNING else None,
            "partial": self.partial,
            "warning": self.warning,
            "result": f"/api/jobs/{self.id}/result" if self.state is JobState.DONE else None,
            "kind": self.kind,
            "owner": self.owner,
            "ending": self.ending(),
            **({"movie": self.movie()} if self.spec.session is not None else {}),
        }

    def ending(self) -> str | None:
        """How a job asked to stop is ending while it still runs: `cancelling` (it ends
        `cancelled`, its output discarded) or `finishing` (a live movie takes no more frames
        and keeps its movie); None otherwise."""
        if self.state not in (JobState.QUEUED, JobState.RUNNING):
            return None
        if self.cancel.is_set():
            return "cancelling"
        if self.frames is not None and self.frames.closed:
            return "finishing"
        return None

    @property
    def kind(self) -> str:
        """`live` (a movie of a live session), `recording` (a movie of a recorded run) or
        `trajectory`."""
        if self.spec.session is not None:
            return "live"
        return "recording" if self.spec.expected_frames is not None else "trajectory"

    def movie(self) -> dict[str, Any]:
        """A live movie's frames (taken, waiting to render, skipped) and its bounds."""
        out: dict[str, Any] = {"max_frames": self.spec.stop, "max_s": self.spec.max_s}
        if self.frames is not None:
            out.update(self.frames.describe())
        return out


class _FrameCache:
    """Trajectory frames read once each (a temporal filter needs its neighbours too): as read
    (with their box, for the selections) and as displayed (`display`: the periodic steps,
    frames taken in the order they are first asked for)."""

    def __init__(
        self,
        structure: IsolatedStructure,
        display: Callable[[int, Any, Any], Awaitable[tuple[Any, Any]]] | None = None,
    ) -> None:
        self.structure = structure
        self.display = display
        self.frames: dict[int, tuple[Any, Any, Any, Any]] = {}

    async def read(self, index: int) -> tuple[Any, Any]:
        """Positions and box of frame `index` as the file holds them."""
        raw, box, _shown, _how = await self._frame(index)
        return raw, box

    async def get(self, index: int) -> Any:
        """Positions of frame `index` as displayed."""
        return (await self._frame(index))[2]

    async def shown(self, index: int) -> Any:
        """How frame `index` was displayed (None: as read)."""
        return (await self._frame(index))[3]

    async def _frame(self, index: int) -> tuple[Any, Any, Any, Any]:
        if index not in self.frames:
            # a damaged frame raises StructureError as it is: the job keeps the frames before it
            raw, box = await asyncio.to_thread(self.structure.frame, index)
            shown, how = raw, None
            if self.display is not None:
                shown, how = await self.display(index, raw, box)
            self.frames[index] = (raw, box, shown, how)
        return self.frames[index]

    def forget_before(self, first: int) -> None:
        for i in [i for i in self.frames if i < first]:
            del self.frames[i]


class JobError(Exception):
    """A job input problem reported to the user as the job's failure reason."""


class JobManager:
    MAX_RESTARTS = 2
    """A job found unfinished after this many restarts fails instead of starting again (its
    input may be what brings the server down)."""

    def __init__(
        self,
        directory: Path,
        gpu: GpuQueue,
        encoders: Executor,
        metrics: Metrics,
        read_limits: ReadLimits,
        *,
        retention_s: float = 24 * 3600.0,
        max_bytes: int = 2 << 30,
        max_running: int = 2,
        upload_dir: Path | None = None,
        batch: RayBatch | None = None,
        selections: SelectionPool | None = None,
    ) -> None:
        """Outputs of finished jobs are kept `retention_s` seconds, and the newest of them
        together at most `max_bytes` (older outputs are removed first). At most `max_running`
        jobs read and render at once; the others wait `queued`. Layer selections are
        evaluated by `selections` (the server's workers; a pool of its own by default)."""
        self.directory = directory
        self.retention_s = retention_s
        self.max_bytes = max_bytes
        directory.mkdir(parents=True, exist_ok=True)
        self.gpu = gpu
        self.encoders = encoders
        self.metrics = metrics
        self.read_limits = read_limits
        self.upload_dir = upload_dir
        self.batch = batch
        """Trajectory jobs render on this Ray pool when given, else in this process."""
        self.selections = selections or SelectionPool()
        self.jobs: dict[str, Job] = {}
        self._running = asyncio.Semaphore(max_running)

    def restore(self) -> list[Job]:
        """Read the records a previous run left, clean what nothing refers to, and start again
        the jobs it did not finish. Returns the jobs started again."""
        for part in self.directory.glob("*.part*"):
            part.unlink(missing_ok=True)
        for tmp in self.directory.glob("*.json.tmp"):
            tmp.unlink(missing_ok=True)
        resumed: list[Job] = []
        for path in sorted(self.directory.glob("*.json")):
            try:
                job = Job.from_record(json.loads(path.read_text(encoding="utf-8")))
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.warning("unreadable job record %s (%s); moved aside", path.name, exc)
                path.rename(path.with_suffix(".broken"))
                continue
            self.jobs[job.id] = job
            if job.state is JobState.DONE and (job.result is None or not job.result.is_file()):
                job.state, job.result = JobState.EXPIRED, None
                job.error = "output missing after a server restart"
                self._save(job)
            if job.state in FINAL:
                continue
            inputs = [job.spec.topology, *job.spec.trajectories]
            if job.spec.session is not None:
                self._fail_on_restart(
                    job, "the server restarted during this recording of a live session"
                )
            elif job.restarts >= self.MAX_RESTARTS:
                self._fail_on_restart(
                    job,
                    f"the server restarted {job.restarts + 1} times "
                    "while it ran; not started again",
                )
            elif not all(f.is_file() for f in inputs):
                self._fail_on_restart(job, "the server restarted and its input files are gone")
            else:
                job.restarts += 1
                job.state, job.done, job.started = JobState.QUEUED, 0, None
                job.error = None
                self._save(job)
                job.task = asyncio.create_task(self._run(job), name=f"job-{job.id}")
                resumed.append(job)
        self._clean_uploads()
        self.reap()
        return resumed

    def _fail_on_restart(self, job: Job, why: str) -> None:
        job.state, job.error, job.finished = JobState.FAILED, why, time.time()
        if job.spec.workdir is not None:
            shutil.rmtree(job.spec.workdir, ignore_errors=True)
        self.metrics.jobs.labels(job.state.value).inc()
        self._save(job)

    def _clean_uploads(self) -> None:
        """Remove upload folders no unfinished job needs (requests cut off by a crash)."""
        if self.upload_dir is None or not self.upload_dir.is_dir():
            return
        kept = {
            j.spec.workdir.resolve()
            for j in self.jobs.values()
            if j.spec.workdir is not None and j.state not in FINAL
        }
        for entry in self.upload_dir.iterdir():
            if entry.resolve() not in kept:
                if entry.is_dir():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)

    def _save(self, job: Job) -> None:
        """Write the job's record atomically (a crash leaves the old record or the new one)."""
        path = self.directory / f"{job.id}.json"
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(job.record(), separators=(",", ":")), encoding="utf-8")
        os.replace(tmp, path)

    def reap(self, now: float | None = None) -> list[Job]:
        """Apply the retention policy: remove outputs older than `retention_s`, then the oldest
        until the rest fit in `max_bytes`; forget the oldest finished records beyond
        MAX_RECORDS. Returns the jobs whose output was removed."""
        now = time.time() if now is None else now
        done = sorted(
            (j for j in self.jobs.values() if j.state is JobState.DONE and j.result is not None),
            key=lambda j: j.finished or 0.0,
        )
        removed: list[Job] = []
        for job in done:
            if now - (job.finished or now) > self.retention_s:
                self._expire(job, f"output removed after {self.retention_s / 3600:g} h")
                removed.append(job)
        kept = [j for j in done if j not in removed]
        sizes = {j.id: _size(j.result) for j in kept}
        total = sum(sizes.values())
        for job in kept:
            if total <= self.max_bytes:
                break
            total -= sizes[job.id]
            self._expire(job, f"output removed: job outputs exceeded {self.max_bytes} bytes")
            removed.append(job)
        finished = sorted(
            (j for j in self.jobs.values() if j.state in FINAL), key=lambda j: j.finished or 0.0
        )
        for job in finished[: max(0, len(finished) - MAX_RECORDS)]:
            self.forget(job)
        return removed

    def _expire(self, job: Job, why: str) -> None:
        if job.result is not None:
            job.result.unlink(missing_ok=True)
        job.result = None
        job.state = JobState.EXPIRED
        job.error = why
        self._save(job)

    def forget(self, job: Job) -> None:
        """Drop a finished job and its output."""
        if job.result is not None:
            job.result.unlink(missing_ok=True)
            job.result = None
        self.jobs.pop(job.id, None)
        (self.directory / f"{job.id}.json").unlink(missing_ok=True)

    def get(self, job_id: str) -> Job | None:
        return self.jobs.get(job_id) if JOB_ID.match(job_id) else None

    def reading(self, directory: Path) -> list[Job]:
        """The jobs queued or running whose input lies in `directory` (a recording's movies):
        deleting it under them would fail them halfway with a missing file."""
        return [
            j
            for j in self.jobs.values()
            if j.state in (JobState.QUEUED, JobState.RUNNING)
            and j.spec.topology.is_relative_to(directory)
        ]

    def submit(self, spec: JobSpec) -> Job:
        self.reap()
        job = Job(id=f"j{secrets.token_urlsafe(16)}", spec=spec)
        self.jobs[job.id] = job
        self._save(job)
        job.task = asyncio.create_task(self._run(job), name=f"job-{job.id}")
        return job

    def record(
        self, spec: JobSpec, frames: MovieQueue, selections: SelectionsOf, owner: str | None = None
    ) -> Job:
        """Start a movie of a live session: every frame put into `frames` (by whoever hooked
        the session's frames), rendered with its own render parameters and the spec's camera,
        until the queue closes (`finish`, `spec.stop` frames, `spec.max_s` seconds) and the
        frames waiting in it are rendered. `selections` gives the session's selection worker,
        for the layers."""
        if spec.session is None or spec.output != "mp4" or spec.camera is None:
            raise ValueError("a recording needs a session, a camera and MP4 output")
        self.reap()
        job = Job(id=f"j{secrets.token_urlsafe(16)}", spec=spec, owner=owner, frames=frames)
        self.jobs[job.id] = job
        self._save(job)
        if spec.max_s is not None:
            timer = asyncio.get_running_loop().call_later(
                spec.max_s, frames.close, f"it recorded for its {spec.max_s:g} s (max_s)"
            )
            frames.when_closed(timer.cancel)
        job.task = asyncio.create_task(
            self._record(job, frames, selections), name=f"recording-{job.id}"
        )
        return job

    def finish(self, job: Job, why: str = "it was stopped") -> None:
        """End a movie of a live session: it takes no more frames, renders those waiting and
        keeps the movie (`cancel` discards it)."""
        if job.frames is not None:
            job.frames.close(why)

    def stop(self, job: Job) -> bool:
        """Stop a job not ended: a live movie still taking frames finishes (keeping its movie;
        True), any other job is cancelled (False)."""
        if job.state is JobState.RUNNING and job.frames is not None and not job.frames.closed:
            self.finish(job)
            return True
        self.cancel(job)
        return False

    def cancel(self, job: Job) -> None:
        job.cancel.set()
        if job.frames is not None:
            job.frames.close("it was cancelled")
        if job.state is JobState.QUEUED:
            job.state = JobState.CANCELLED
            job.finished = time.time()
            self._save(job)
            if job.spec.workdir is not None:  # it never starts: its uploads go now
                shutil.rmtree(job.spec.workdir, ignore_errors=True)

    async def _run(self, job: Job) -> None:
        async with self._running:
            await self._render(job)

    async def _render_here(
        self,
        job: Job,
        structure: IsolatedStructure,
        indices: list[int],
        writer: FrameWriter,
    ) -> bool:
        """Render the frames on this server's GPU queue, in order, into `writer`; False when
        the job was cancelled before the last frame."""
        params = job.spec.params
        wanted = bool(params.layers) or needs_selections(params)
        held = self.selections.hold(structure.topology) if wanted else None
        try:
            display = await self._display(job, structure, held)
            frames = _FrameCache(structure, display)
            return await self._frames_here(job, structure, indices, writer, frames, held)
        finally:
            if held is not None:
                held.release()

    async def _display(
        self, job: Job, structure: IsolatedStructure, held: Held | None
    ) -> Callable[[int, Any, Any], Awaitable[tuple[Any, Any]]] | None:
        """How the job's frames are displayed (the periodic steps on the GPU queue's device),
        or None when they are drawn as read. A fit first takes the file's first frame as its
        reference."""
        params = job.spec.params
        if params.periodic == "off" and params.center == "off" and params.fit == "off":
            return None
        slot = f"job:{job.id}"
        topology = structure.topology
        options = PeriodicOptions(params, held)
        state = {"last": -2}

        async def display(index: int, raw: Any, box: Any) -> tuple[Any, Any]:
            if not needs_display(params, box):
                return raw, None
            try:
                how = await options.get_async(box)
            except PeriodicError as exc:
                raise JobError(f"params.{exc}") from None
            if how.fit != "off" and state["last"] == -2:
                ref_raw, ref_box = await asyncio.to_thread(structure.frame, REFERENCE_FRAME)
                ref_how = await options.get_async(ref_box)
                await self.gpu.display(
                    DisplayRequest(slot, topology, ref_raw, ref_box, ref_how, True, True)
                )
            restart = index <= state["last"] or state["last"] < 0
            state["last"] = index
            shown = await self.gpu.display(
                DisplayRequest(slot, topology, raw, box, how, restart=restart)
            )
            return shown.positions, shown

        return display

    async def _frames_here(
        self,
        job: Job,
        structure: IsolatedStructure,
        indices: list[int],
        writer: FrameWriter,
        frames: _FrameCache,
        held: Held | None,
    ) -> bool:
        spec = job.spec
        slot = f"job:{job.id}"
        loop = asyncio.get_running_loop()
        camera = spec.camera
        topology = structure.topology
        window = time_window(spec.params, structure.n_frames)
        layers = FrameLayers(spec.params, topology, held)
        for n, index in enumerate(indices):
            if job.cancel.is_set():
                return False
            try:
                raw, box = await frames.read(index)
            except (OSError, StructureError) as exc:  # a file damaged from here on
                if n == 0:
                    raise JobError(f"frame {index} could not be read: {exc}") from None
                job.partial = True
                job.warning = (
                    f"frame {index} could not be read ({exc}); the output holds the {n} "
                    "frame(s) before it"
                )
                log.warning("job %s: %s", job.id, job.warning)
                return True
            positions = await frames.get(index)
            try:  # evaluated by a selection worker, awaited here
                plans = await layers.plans_async(raw, index, box)
            except LayerError as exc:
                raise JobError(f"params.{exc}") from None
            if camera is None:
                from server.render.camera import fit_camera
                from server.render.layerplan import visible_atoms

                shown = visible_atoms(plans, topology.n_atoms)
                fit = positions[shown] if len(shown) else positions
                camera = fit_camera(fit, spec.width, spec.height)
            history: tuple[tuple[int, Any], ...] = ()
            lag = None
            if window is not None:
                first, last = window(index)
                history = tuple([(i + 1, await frames.get(i)) for i in range(first, last + 1)])
                lag = last - index
                frames.forget_before(first)
            snapshot = Snapshot(
                topology,
                positions,
                positions_id=index + 1,  # the ids the history frames carry too
                step=index,
                history=history,
                history_epoch=index,  # each frame its own window: chunks render the same
                live=False,
                lag=lag,
            )
            out = await self.gpu.render(
                RenderRequest(
                    slot, snapshot, spec.params, camera, spec.width, spec.height, layers=plans
                )
            )
            rgba = out.image()
            if spec.params.show_cell:
                cell = displayed_cell(await frames.shown(index), box)
                if cell is not None:
                    rgba = await loop.run_in_executor(self.encoders, draw_cell, rgba, camera, cell)
            if spec.overlay is not None:
                rgba = await loop.run_in_executor(
                    self.encoders, draw_overlay, rgba, index, spec.overlay, camera, positions
                )
            png = None
            if isinstance(writer, ZipWriter):
                png, _ms = await loop.run_in_executor(self.encoders, encode_image, rgba, "png")
            await loop.run_in_executor(self.encoders, writer.add, index, rgba, png)
            job.done = n + 1
        return True

    async def _render(self, job: Job) -> None:
        spec = job.spec
        slot = f"job:{job.id}"
        writer: FrameWriter | None = None
        structure: IsolatedStructure | None = None
        loop = asyncio.get_running_loop()
        if job.cancel.is_set():
            return
        job.state = JobState.RUNNING
        job.started = time.time()
        job.stage = "reading its input"
        job.partial, job.warning = False, None
        self._save(job)
        outcome, error, result = JobState.DONE, None, None
        try:
            try:
                structure = await asyncio.to_thread(
                    IsolatedStructure,
                    str(spec.topology),
                    [str(t) for t in spec.trajectories],
                    self.read_limits,
                )
            except StructureError as exc:
                raise JobError(str(exc)) from None
            opening = await asyncio.to_thread(opening_params, spec.params, structure.topology)
            if opening is not spec.params:  # the default layers, kept for a restart
                job.spec = spec = replace(spec, params=opening)
                self._save(job)
            expected = spec.expected_frames
            if structure.notes:  # a trajectory cut short, read as far as it goes
                job.partial = True
                job.warning = "; ".join(structure.notes) + "; the output has the whole frames"
                log.warning("job %s: %s", job.id, job.warning)
            if expected is not None and structure.n_frames < expected:
                job.partial = True
                job.warning = (
                    f"{spec.trajectories[-1].name if spec.trajectories else spec.topology.name}: "
                    f"{structure.n_frames} readable frame(s) of the {expected} it should hold "
                    "(the file is cut short); the output has only those"
                )
                log.warning("job %s: %s", job.id, job.warning)
            indices = list(range(structure.n_frames))[spec.start : spec.stop : spec.stride]
            if not indices:
                raise JobError(
                    f"the frame range selects no frames (the trajectory has {structure.n_frames})"
                )
            job.total = len(indices)
            suffix = "zip" if spec.output == "zip" else "mp4"
            final = self.directory / f"{job.id}.{suffix}"
            if spec.output == "zip":
                writer = ZipWriter(final)
            else:
                writer = await loop.run_in_executor(
                    self.encoders, Mp4Writer, final, spec.fps, spec.width, spec.height
                )
            # `unwrap` follows atoms from frame to frame: only one process can
            if (
                self.batch is not None
                and len(indices) >= self.batch.min_frames
                and spec.params.periodic != "unwrap"
            ):
                completed = await self._render_on_ray(job, structure, indices, writer)
            else:
                job.stage = "rendering"
                completed = await self._render_here(job, structure, indices, writer)
            if completed:
                await loop.run_in_executor(self.encoders, writer.close)
                result = final
            else:
                outcome = JobState.CANCELLED
        except (JobError, StructureError, RenderError) as exc:
            outcome, error = JobState.FAILED, str(exc)
        except asyncio.CancelledError:
            # shutting down: the record stays `running`, so the next start runs the job again
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.abort()
            if structure is not None:
                structure.close()
            raise
        except Exception as exc:
            log.exception("job %s failed", job.id)
            outcome = JobState.FAILED
            error = f"internal error ({type(exc).__name__}); see the server log"
        if structure is not None:
            await asyncio.to_thread(structure.close)
        if outcome is not JobState.DONE and writer is not None:
            with contextlib.suppress(Exception):
                writer.abort()
        with contextlib.suppress(Exception):
            await self.gpu.release(slot)
        if spec.workdir is not None:
            await asyncio.to_thread(shutil.rmtree, spec.workdir, True)
        # the outcome is published in one step, with no await in between
        job.state, job.error, job.result = outcome, error, result
        job.finished = time.time()
        self.metrics.jobs.labels(job.state.value).inc()
        self._save(job)
        self.reap()

    async def _render_on_ray(
        self, job: Job, structure: IsolatedStructure, indices: list[int], writer: FrameWriter
    ) -> bool:
        """The frames of `job` rendered by the Ray pool and written here in order; False when
        the job was cancelled."""
        assert self.batch is not None
        spec = job.spec
        loop = asyncio.get_running_loop()
        camera = spec.camera
        plans = None
        if camera is None or spec.params.layers or needs_selections(spec.params):
            # the first frame's layers here: a layer past the selection limits fails the job
            # now, not in every chunk; and the camera frames what they show, as displayed
            wanted = bool(spec.params.layers) or needs_selections(spec.params)
            held = self.selections.hold(structure.topology) if wanted else None
            try:
                raw, box = await asyncio.to_thread(structure.frame, indices[0])
                layers = FrameLayers(spec.params, structure.topology, held)
                plans = await layers.plans_async(raw, indices[0], box)
                display = await self._display(job, structure, held)
                first = raw if display is None else (await display(indices[0], raw, box))[0]
            except StructureError as exc:
                raise JobError(str(exc)) from None
            except LayerError as exc:
                raise JobError(f"params.{exc}") from None
            finally:
                if held is not None:
                    held.release()
        if camera is None:
            from server.render.camera import fit_camera
            from server.render.layerplan import visible_atoms

            shown = visible_atoms(plans, structure.topology.n_atoms)
            camera = fit_camera(first[shown] if len(shown) else first, spec.width, spec.height)
        files = [spec.topology, *spec.trajectories]
        if not self.batch.started:
            job.stage = "starting Ray"
        try:
            await self.batch.ensure()
        except RuntimeError as exc:  # a local instance that did not start says why
            raise JobError(f"Ray: {exc}") from None
        job.stage = "rendering"
        if spec.workdir is not None:  # uploads: through the object store
            refs: list[Any] = await asyncio.to_thread(upload_refs, files)
        else:
            refs = [str(f) for f in files]
        inputs = ChunkInputs(
            job=job.id,
            topology=refs[0],
            trajectories=tuple(refs[1:]),
            params=spec.params.model_dump(mode="json"),
            camera=camera.model_dump(mode="json"),
            width=spec.width,
            height=spec.height,
            png=spec.output == "zip",
            n_frames=structure.n_frames,
            reference=indices[0],
            overlay=spec.overlay,
            selection_limits=self.selections.limits,
        )

        async def write(index: int, rgba: Any, png: bytes | None) -> None:
            await loop.run_in_executor(self.encoders, writer.add, index, rgba, png)
            job.done += 1

        try:
            return await self.batch.render(inputs, indices, write, job.cancel)
        except RuntimeError as exc:
            raise JobError(str(exc)) from None

    async def _record(self, job: Job, frames: MovieQueue, selections: SelectionsOf) -> None:
        spec = job.spec
        assert spec.camera is not None
        slot = f"job:{job.id}"
        loop = asyncio.get_running_loop()
        job.state, job.started = JobState.RUNNING, time.time()
        job.stage = "rendering"
        self._save(job)
        final = self.directory / f"{job.id}.mp4"
        writer: Mp4Writer | None = None
        outcome, error, result = JobState.DONE, None, None
        layers: FrameLayers | None = None
        try:
            writer = await loop.run_in_executor(
                self.encoders, Mp4Writer, final, spec.fps, spec.width, spec.height
            )
            while (frame := await frames.next()) is not None:
                if job.cancel.is_set():
                    break
                job.total = frames.taken
                snap = frame.snapshot
                if layers is None or layers.params is not frame.params:
                    layers = FrameLayers(frame.params, snap.topology, selections())
                try:  # the session's worker, with its frames' keys
                    plans = await layers.plans_async(snap.positions, snap.positions_id, frame.box)
                except LayerError as exc:
                    raise JobError(f"params.{exc}") from None
                started = time.monotonic()
                out = await self.gpu.render(
                    RenderRequest(
                        slot, snap, frame.params, spec.camera, spec.width, spec.height, layers=plans
                    )
                )
                await loop.run_in_executor(self.encoders, writer.add, snap.step, out.image(), None)
                frames.rendered(time.monotonic() - started)
                job.done += 1
            job.total = frames.taken
            if job.cancel.is_set():
                outcome = JobState.CANCELLED
            elif job.done == 0:
                raise JobError("the session sent no frame while recording")
            else:
                job.warning = frames.skip_warning()
                job.partial = job.warning is not None
                await loop.run_in_executor(self.encoders, writer.close)
                result = final
        except (JobError, StructureError, RenderError) as exc:
            outcome, error = JobState.FAILED, str(exc)
        except asyncio.CancelledError:
            frames.close("the server stopped")
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.abort()
            raise
        except Exception as exc:
            log.exception("recording %s failed", job.id)
            outcome = JobState.FAILED
            error = f"internal error ({type(exc).__name__}); see the server log"
        frames.close("it ended")
        if outcome is not JobState.DONE and writer is not None:
            with contextlib.suppress(Exception):
                writer.abort()
        with contextlib.suppress(Exception):
            await self.gpu.release(slot)
        job.state, job.error, job.result = outcome, error, result
        job.finished = time.time()
        self.metrics.jobs.labels(job.state.value).inc()
        self._save(job)
        self.reap()

    async def close(self) -> None:
        """Stop the running jobs without finishing them: their records stay unfinished, so the
        next start runs them again."""
        for job in self.jobs.values():
            if job.task is not None and not job.task.done():
                job.task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await job.task


def _size(path: Path | None) -> int:
    try:
        return path.stat().st_size if path is not None else 0
    except OSError:
        return 0
