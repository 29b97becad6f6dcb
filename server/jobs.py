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
from server.encoder import encode_image
from server.gpu import GpuQueue
from server.metrics import Metrics
from server.movie import FrameWriter, Mp4Writer, ZipWriter

log = logging.getLogger("scalesteer.jobs")


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


FINAL = (JobState.DONE, JobState.FAILED, JobState.CANCELLED)


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
        self, directory: Path, gpu: GpuQueue, encoders: Executor, metrics: Metrics, max_atoms: int
    ) -> None:
        self.directory = directory
        directory.mkdir(parents=True, exist_ok=True)
        self.gpu = gpu
        self.encoders = encoders
        self.metrics = metrics
        self.max_atoms = max_atoms
        self.jobs: dict[str, Job] = {}
        self._ids = itertools.count(1)
        self._token = f"{int(time.time()):x}"

    def submit(self, spec: JobSpec) -> Job:
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
        from simulation_adapters.structure import StructureError, load

        spec = job.spec
        key = f"job:{job.id}"
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
                out = await self.gpu.call(
                    self.gpu.render_sync,
                    key,
                    topology,
                    1,
                    positions,
                    n + 1,
                    spec.params,
                    camera,
                    spec.width,
                    spec.height,
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
            with contextlib.suppress(Exception):
                await self.gpu.release(key)
            if spec.workdir is not None:
                shutil.rmtree(spec.workdir, ignore_errors=True)

    async def close(self) -> None:
        for job in self.jobs.values():
            job.cancel.set()
            if job.task is not None and not job.task.done():
                job.task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await job.task
