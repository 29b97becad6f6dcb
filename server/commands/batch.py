"""`scalesteer batch`: render a trajectory to an MP4 or a zip of PNGs, without a server.

    scalesteer batch adk.psf adk.dcd -o adk.mp4 --size 1920x1080 --ray-address HEAD:6379

The job runs exactly as `POST /api/jobs` runs it (`server.pipeline.jobs`): in this process, or
on Ray when asked (`--engine ray`: a cluster, or a local instance that ends with this command)
or when a cluster is configured (`--ray-address`, `SCALESTEER_RAY_ADDRESS`, `RAY_ADDRESS`) for
jobs of 64 frames or more.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from server.commands.render import (
    _size,
    add_layer_options,
    add_periodic_options,
    device_refusal,
    layer_option,
    periodic_fields,
    periodic_refusal,
    size_refusal,
)
from server.settings import ray_cluster_address


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="scalesteer batch",
        description="Render a trajectory to an MP4 or a zip of PNGs, in this process or on Ray.",
    )
    ap.add_argument("topology", help="structure or topology file (pdb, psf, gro, ...)")
    ap.add_argument("trajectory", nargs="*", help="trajectory files (dcd, xtc, trr, ...)")
    ap.add_argument("-o", "--output", required=True, type=Path, help="out.mp4 or out.zip")
    ap.add_argument("--size", type=_size, default=(1280, 720), help="WxH (default 1280x720)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stop", type=int, default=None)
    ap.add_argument("--stride", type=_positive_int, default=1, help="every Nth frame (N >= 1)")
    ap.add_argument("--fps", type=_frame_rate, default=30.0, help="the movie's frames a second")
    ap.add_argument(
        "--params",
        default="{}",
        metavar="JSON",
        help='render parameters as JSON, e.g. \'{"sigma_A": 3, "mode": "volume"}\' (every field: '
        'docs/protocol.schema.json, RenderParams); a "layers" list in it draws parts of the '
        "system, as --layers does",
    )
    add_layer_options(ap)
    ap.add_argument("--camera", default=None, help="camera as JSON (default: fit the first frame)")
    ap.add_argument("--device", default="auto", help="render device of the in-process engine")
    ap.add_argument(
        "--engine",
        choices=["auto", "ray", "local"],
        default="auto",
        help="auto: Ray when a cluster is configured (jobs of 64 frames or more), else this "
        "process; ray: Ray always (a local instance without --ray-address); local: this process",
    )
    ap.add_argument(
        "--ray-address",
        default=ray_cluster_address(),
        help="a Ray cluster to join, HOST:PORT (env SCALESTEER_RAY_ADDRESS or RAY_ADDRESS)",
    )
    ap.add_argument("--ray-workers", type=int, default=None, help="Ray render actors at most")
    add_periodic_options(ap)
    return ap


async def run(args: argparse.Namespace) -> int:
    import protocol as p
    from protocol.fields import unknown_keys
    from server.metrics import Metrics
    from server.pipeline.gpu import GpuQueue
    from server.pipeline.jobs import JobManager, JobSpec, JobState
    from server.pipeline.periodic import PeriodicError, check_periodic
    from server.pipeline.selections import check_layers
    from server.settings import ServerSettings
    from server.web.app import batch_engine
    from structures.selection_pool import SelectionPool

    suffix = args.output.suffix.lower()
    if suffix not in (".mp4", ".zip"):
        print(
            f"scalesteer batch: {args.output}: the output must end in .mp4 or .zip", file=sys.stderr
        )
        return 2
    try:
        try:
            raw = json.loads(args.params)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--params is not valid JSON: {exc.msg}") from None
        unknown = unknown_keys(p.RenderParams, raw, "params")
        if unknown:
            raise ValueError(f"{unknown}: unknown field")
        params = p.RenderParams.model_validate({**raw, **periodic_fields(args)})
        layers = layer_option(args)
        if layers is not None:
            if "layers" in params.model_fields_set:
                raise ValueError("--params names layers: leave out --select, --layers, --all-atoms")
            params = params.model_copy(update={"layers": layers})
        check_layers(params)
        check_periodic(params)
        camera = _camera(args.camera)
        if args.stop is not None and args.stop <= args.start:  # as REST refuses it, unread
            raise ValueError(f"--stop {args.stop} must be after --start {args.start}: no frame")
        if args.start < 0:
            raise ValueError(f"--start {args.start}: frames count from 0")
        # and what no frame could be drawn with, before the input is read
        refusal = size_refusal(*args.size) or device_refusal(args.device)
        if refusal is not None:
            raise ValueError(refusal)
    except PeriodicError as exc:
        print(f"scalesteer batch: {periodic_refusal(exc.path, exc.reason, args)}", file=sys.stderr)
        return 2
    except ValueError as exc:  # JSON, validation and selection errors are ValueErrors
        print(f"scalesteer batch: {exc}", file=sys.stderr)
        return 2
    settings = ServerSettings(
        device=args.device,
        batch_engine=args.engine,
        ray_address=args.ray_address,
        ray_workers=args.ray_workers,
    )
    work = Path(tempfile.mkdtemp(prefix="scalesteer-batch-"))
    batch = batch_engine(settings, work / "ray")
    gpu = GpuQueue(device=args.device)
    encoders = ThreadPoolExecutor(max_workers=4, thread_name_prefix="encode")
    # layers are evaluated as the server evaluates them (docs/server.md, "Selections")
    selections = SelectionPool(settings.selection_limits())
    jobs = JobManager(
        work,
        gpu,
        encoders,
        Metrics(),
        settings.read_limits(),
        batch=batch,
        max_running=1,
        selections=selections,
    )
    spec = JobSpec(
        topology=Path(args.topology).resolve(),
        trajectories=[Path(t).resolve() for t in args.trajectory],
        params=params,
        camera=camera,
        width=args.size[0],
        height=args.size[1],
        output="mp4" if suffix == ".mp4" else "zip",
        start=args.start,
        stop=args.stop,
        stride=args.stride,
        fps=args.fps,
    )
    if batch is None:
        engine = f"this process ({args.device})"
    else:
        where = args.ray_address or "a local instance, started now"
        engine = f"Ray ({where}; jobs under {batch.min_frames} frames here)"
        if not batch.min_frames:
            engine = f"Ray ({where})"
    print(f"scalesteer batch: rendering on {engine}", flush=True)
    job = jobs.submit(spec)
    last, said = 0.0, None
    try:
        while job.state in (JobState.QUEUED, JobState.RUNNING):
            await asyncio.sleep(0.2)
            if job.done == 0 and job.stage and job.stage != said:
                said = job.stage
                print(f"  {job.stage}...", flush=True)
            elif time.monotonic() - last > 2 and job.total and job.done:
                last = time.monotonic()
                eta = job.describe().get("eta_s")
                tail = f", about {eta:.0f} s left" if eta else ""
                print(f"  {job.done}/{job.total} frames{tail}", flush=True)
    except (KeyboardInterrupt, asyncio.CancelledError):
        jobs.cancel(job)
        raise
    finally:
        if batch is not None:
            await asyncio.to_thread(batch.close)
        await asyncio.to_thread(selections.close)
        await asyncio.to_thread(gpu.close)
        encoders.shutdown(wait=True)
    if job.state is not JobState.DONE or job.result is None:
        error = _as_option(job.error or "", args)
        print(f"scalesteer batch: {job.state.value}: {error}", file=sys.stderr)
        shutil.rmtree(work, ignore_errors=True)
        return 1
    args.output.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(job.result), args.output)
    shutil.rmtree(work, ignore_errors=True)
    print(f"scalesteer batch: {job.done} frames -> {args.output}")
    return 0


def _as_option(error: str, args: argparse.Namespace) -> str:
    """A job's error about a centre or fit selection (the job names its render parameter,
    `params.<field>`), named by the option it came from."""
    for field in ("center_selection", "fit_selection"):
        prefix = f"params.{field}: "
        if error.startswith(prefix):
            return periodic_refusal(field, error[len(prefix) :], args)
    return error


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _frame_rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.1 <= value <= 240:
        raise argparse.ArgumentTypeError(f"must be between 0.1 and 240 frames a second, got {text}")
    return value


def _camera(text: str | None) -> Any:
    """--camera's JSON as a `protocol.Camera`; ValueError naming the option and the field."""
    from pydantic import ValidationError

    import protocol as p
    from protocol.fields import error_location, unknown_keys

    if not text:
        return None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--camera is not valid JSON ({exc.msg}): {text!r}") from None
    unknown = unknown_keys(p.Camera, raw, "camera")
    if unknown:
        raise ValueError(f"--camera: {unknown}: unknown field")
    try:
        return p.Camera.model_validate(raw)
    except ValidationError as exc:
        loc, msg = error_location(exc.errors(include_url=False)[0])
        raise ValueError(f"--camera: {'.'.join(loc) or 'camera'}: {msg}") from None


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return asyncio.run(run(args))
    except KeyboardInterrupt:
        return 130
