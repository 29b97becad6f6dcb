"""Batch trajectory renders: background jobs on the shared GPU queue, with progress and cancel.

A job renders frame by frame (each frame is its own GPU submission, so live sessions keep their
turn), writes to a temporary file, and only a complete file is reported `done`; anything that
goes wrong marks the job `failed` with the reason and removes the partial output.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import itertools
import logging
import shutil
import threading
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import protocol as p
from server.metrics import Metrics
from server.pipeline.encoder import encode_image
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.pipeline.movie import FrameWriter, Mp4Writer, ZipWriter

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
    cancel: threading.Event = field(default_factory=threading.Event)
    task: asyncio.Task[None] | None = None

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
            "created": self.created,
            "started": self.started,
            "finished": self.finished,
            "result": f"/api/jobs/{self.id}/result" if self.state is JobState.DONE else None,
        }


class JobError(Exception):
    """A job input problem reported to the user as the job's failure reason."""


class JobManager:
    def __init__(
        self,
        directory: Path,
        gpu: GpuQueue,
        encoders: Executor,
        metrics: Metrics,
        max_atoms: int,
        *,
        retention_s: float = 24 * 3600.0,
        max_bytes: int = 2 << 30,
    ) -> None:
        """Outputs of finished jobs are kept `retention_s` seconds, and the newest of them
        together at most `max_bytes` (older outputs are removed first)."""
        self.directory = directory
        self.retention_s = retention_s
        self.max_bytes = max_bytes
        directory.mkdir(parents=True, exist_ok=True)
        self.gpu = gpu
        self.encoders = encoders
        self.metrics = metrics
        self.max_atoms = max_atoms
        self.jobs: dict[str, Job] = {}
        self._ids = itertools.count(1)
        self._token = f"{int(time.time()):x}"

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

    def forget(self, job: Job) -> None:
        """Drop a finished job and its output."""
        if job.result is not None:
            job.result.unlink(missing_ok=True)
            job.result = None
        self.jobs.pop(job.id, None)

    def submit(self, spec: JobSpec) -> Job:
        self.reap()
        job = Job(id=f"j{self._token}-{next(self._ids)}", spec=spec)
        self.jobs[job.id] = job
        job.task = asyncio.create_task(self._run(job), name=f"job-{job.id}")
        return job

    def cancel(self, job: Job) -> None:
        job.cancel.set()
        if job.state is JobState.QUEUED:
            job.state = JobState.CANCELLED
            job.finished = time.time()

    async def _run(self, job: Job) -> None:
        from structures.reader import StructureError, load

        spec = job.spec
        slot = f"job:{job.id}"
        writer: FrameWriter | None = None
        loop = asyncio.get_running_loop()
        try:
            if job.cancel.is_set():
                return
            job.state = JobState.RUNNING
            job.started = time.time()
            try:
                structure = await asyncio.to_thread(
                    load,
                    str(spec.topology),
                    [str(t) for t in spec.trajectories],
                    max_atoms=self.max_atoms,
                )
            except StructureError as exc:
                raise JobError(str(exc)) from None
            indices = list(range(structure.n_frames))[spec.start : spec.stop : spec.stride]
            if not indices:
                raise JobError(
                    f"the frame range selects no frames (the trajectory has {structure.n_frames})"
                )
            job.total = len(indices)
            camera = spec.camera
            suffix = "zip" if spec.output == "zip" else "mp4"
            final = self.directory / f"{job.id}.{suffix}"
            if spec.output == "zip":
                writer = ZipWriter(final)
            else:
                writer = await loop.run_in_executor(
                    self.encoders, Mp4Writer, final, spec.fps, spec.width, spec.height
                )
            topology = structure.topology
            for n, index in enumerate(indices):
                if job.cancel.is_set():
                    job.state = JobState.CANCELLED
                    break
                positions = await asyncio.to_thread(structure.positions, index)
                if camera is None:
                    from server.render.camera import fit_camera

                    camera = fit_camera(positions, spec.width, spec.height)
                snapshot = Snapshot(topology, positions, positions_id=n + 1, step=index)
                out = await self.gpu.render(
                    RenderRequest(slot, snapshot, spec.params, camera, spec.width, spec.height)
                )
                png = None
                if isinstance(writer, ZipWriter):
                    png, _ms = await loop.run_in_executor(
                        self.encoders, encode_image, out.rgba, "png"
                    )
                await loop.run_in_executor(self.encoders, writer.add, index, out.rgba, png)
                job.done = n + 1
            if job.state is JobState.CANCELLED:
                await loop.run_in_executor(self.encoders, writer.abort)
            else:
                await loop.run_in_executor(self.encoders, writer.close)
                job.result = final
                job.state = JobState.DONE
        except JobError as exc:
            job.state, job.error = JobState.FAILED, str(exc)
        except asyncio.CancelledError:
            job.state, job.error = JobState.CANCELLED, "server shutting down"
            raise
        except Exception as exc:
            log.exception("job %s failed", job.id)
            job.state, job.error = (
                JobState.FAILED,
                f"internal error ({type(exc).__name__}); see the server log",
            )
        finally:
            if job.state is not JobState.DONE and writer is not None:
                with contextlib.suppress(Exception):
                    writer.abort()
            job.finished = time.time()
            self.metrics.jobs.labels(job.state.value).inc()
            self.reap()
            with contextlib.suppress(Exception):
                await self.gpu.release(slot)
            if spec.workdir is not None:
                shutil.rmtree(spec.workdir, ignore_errors=True)

    async def close(self) -> None:
        for job in self.jobs.values():
            job.cancel.set()
            if job.task is not None and not job.task.done():
                job.task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await job.task


def _size(path: Path | None) -> int:
    try:
        return path.stat().st_size if path is not None else 0
    except OSError:
        return 0
