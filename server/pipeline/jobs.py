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
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

import protocol as p
from server.metrics import Metrics
from server.pipeline.distributed import ChunkInputs, RayBatch, upload_refs
from server.pipeline.encoder import encode_image
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.pipeline.history import time_window
from server.pipeline.movie import FrameWriter, Mp4Writer, ZipWriter
from server.pipeline.overlay import draw_overlay
from server.pipeline.selections import FrameLayers, LayerError
from structures.errors import StructureError
from structures.isolated import IsolatedStructure, ReadLimits
from structures.selection_pool import Held, SelectionPool

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

    def record(self) -> dict[str, Any]:
        """A JSON-able form, to survive restarts."""
        return {
            "session": self.session,
            "topology": str(self.topology),
            "trajectories": [str(t) for t in self.trajectories],
            "params": self.params.model_dump(mode="json"),
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
    cancel: threading.Event = field(default_factory=threading.Event)
    finish: asyncio.Event = field(default_factory=asyncio.Event)
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
        }


class _FrameCache:
    """Trajectory frames read once each (a temporal filter needs its neighbours too)."""

    def __init__(self, structure: IsolatedStructure) -> None:
        self.structure = structure
        self.frames: dict[int, Any] = {}

    async def get(self, index: int) -> Any:
        if index not in self.frames:
            try:
                self.frames[index] = await asyncio.to_thread(self.structure.positions, index)
            except StructureError as exc:
                raise JobError(str(exc)) from None
        return self.frames[index]

    def forget_before(self, first: int) -> None:
        for i in [i for i in self.frames if i < first]:
            del self.frames[i]


class LiveSource(Protocol):
    """A live session as a recording sees it: its frames as they arrive, and how it renders."""

    @property
    def render_params(self) -> p.RenderParams: ...

    async def next_frame(self, after: int, timeout: float) -> Snapshot | None: ...


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

    def submit(self, spec: JobSpec) -> Job:
        self.reap()
        job = Job(id=f"j{secrets.token_urlsafe(16)}", spec=spec)
        self.jobs[job.id] = job
        self._save(job)
        job.task = asyncio.create_task(self._run(job), name=f"job-{job.id}")
        return job

    def record(self, source: LiveSource, spec: JobSpec) -> Job:
        """Start recording a live session to an MP4: each new frame, rendered with the
        session's render parameters as they are at that moment and the spec's camera, until
        `spec.stop` frames or `finish`."""
        if spec.session is None or spec.output != "mp4" or spec.camera is None:
            raise ValueError("a recording needs a session, a camera and MP4 output")
        self.reap()
        job = Job(id=f"j{secrets.token_urlsafe(16)}", spec=spec)
        self.jobs[job.id] = job
        self._save(job)
        job.task = asyncio.create_task(self._record(job, source), name=f"recording-{job.id}")
        return job

    def finish(self, job: Job) -> None:
        """End a recording now, keeping what it recorded (`cancel` discards it)."""
        job.finish.set()

    def cancel(self, job: Job) -> None:
        job.cancel.set()
        if job.state is JobState.QUEUED:
            job.state = JobState.CANCELLED
            job.finished = time.time()
            self._save(job)

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
        frames = _FrameCache(structure)
        held = self.selections.hold(structure.topology) if job.spec.params.layers else None
        try:
            return await self._frames_here(job, structure, indices, writer, frames, held)
        finally:
            if held is not None:
                held.release()

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
            positions = await frames.get(index)
            try:  # evaluated by a selection worker, awaited here
                plans = await layers.plans_async(positions, index)
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
            expected = spec.expected_frames
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
            if self.batch is not None and len(indices) >= self.batch.min_frames:
                completed = await self._render_on_ray(job, structure, indices, writer)
            else:
                job.stage = "rendering"
                completed = await self._render_here(job, structure, indices, writer)
            if completed:
                await loop.run_in_executor(self.encoders, writer.close)
                result = final
            else:
                outcome = JobState.CANCELLED
        except JobError as exc:
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
        if camera is None or spec.params.layers:
            # the first frame's layers here: a layer past the selection limits fails the job
            # now, not in every chunk; and the camera frames what they show
            held = self.selections.hold(structure.topology) if spec.params.layers else None
            try:
                first = await asyncio.to_thread(structure.positions, indices[0])
                layers = FrameLayers(spec.params, structure.topology, held)
                plans = await layers.plans_async(first, indices[0])
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

    async def _record(self, job: Job, source: LiveSource) -> None:
        spec = job.spec
        assert spec.camera is not None
        slot = f"job:{job.id}"
        loop = asyncio.get_running_loop()
        job.state, job.started = JobState.RUNNING, time.time()
        job.total = spec.stop or 0
        self._save(job)
        final = self.directory / f"{job.id}.mp4"
        writer: Mp4Writer | None = None
        outcome, error, result = JobState.DONE, None, None
        try:
            writer = await loop.run_in_executor(
                self.encoders, Mp4Writer, final, spec.fps, spec.width, spec.height
            )
            after = first = -1
            while not job.finish.is_set() and (spec.stop is None or job.done < spec.stop):
                if job.cancel.is_set():
                    outcome = JobState.CANCELLED
                    break
                waiter = asyncio.ensure_future(source.next_frame(after, 1.0))
                finish = asyncio.ensure_future(job.finish.wait())
                done, _ = await asyncio.wait({waiter, finish}, return_when=asyncio.FIRST_COMPLETED)
                finish.cancel()
                if waiter not in done:
                    waiter.cancel()
                    break
                snapshot = waiter.result()
                if snapshot is None:
                    continue
                if first < 0:
                    first = snapshot.positions_id
                after = snapshot.positions_id
                out = await self.gpu.render(
                    RenderRequest(
                        slot, snapshot, source.render_params, spec.camera, spec.width, spec.height
                    )
                )
                await loop.run_in_executor(
                    self.encoders, writer.add, snapshot.step, out.image(), None
                )
                job.done += 1
            if outcome is JobState.DONE and job.done == 0:
                raise JobError("the session sent no frame while recording")
            sent = after - first + 1  # the session's frames from the first image to the last
            if outcome is JobState.DONE and sent > job.done:
                job.partial = True
                job.warning = (
                    f"the session sent {sent} frames while recording; {job.done} of them are in "
                    "the movie (each image took longer to render than the next frame took to "
                    "come, and a movie image is always of the newest frame)"
                )
            if outcome is JobState.DONE:
                await loop.run_in_executor(self.encoders, writer.close)
                result = final
        except JobError as exc:
            outcome, error = JobState.FAILED, str(exc)
        except asyncio.CancelledError:
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.abort()
            raise
        except Exception as exc:
            log.exception("recording %s failed", job.id)
            outcome = JobState.FAILED
            error = f"internal error ({type(exc).__name__}); see the server log"
        if outcome is not JobState.DONE and writer is not None:
            with contextlib.suppress(Exception):
                writer.abort()
        with contextlib.suppress(Exception):
            await self.gpu.release(slot)
        job.state, job.error, job.result = outcome, error, result
        job.total = job.done
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
