"""Batch jobs in this process and on Ray, the same job side by side in one run.

The job: adenylate kinase (MDAnalysisTests' PSF/DCD, 3,341 atoms, 98 frames, replayed
`--repeat` times as one trajectory list) rendered to an MP4, through `JobManager` exactly as
`POST /api/jobs` renders it. Engines: in-process (the GPU queue of the server), and a local Ray
instance with 1 and 2 render actors (one per GPU where there are GPUs, else per CPU).

    python benchmarks/batch_bench.py --out benchmarks/results/batch_cpu_2core.json \\
        --size 320x240 --repeat 1 --workers 1,2            # the CPU scaling, 2 cores
    python benchmarks/batch_bench.py --out benchmarks/results/batch_h100.json \\
        --size 1920x1080 --repeat 11 --workers 1 --device cuda:0   # ~1,000 frames, one GPU
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


async def run_job(
    engine: Any, device: str, size: tuple[int, int], repeat: int, files: tuple[str, str]
) -> dict[str, Any]:
    import protocol as p
    from server.metrics import Metrics
    from server.pipeline.gpu import GpuQueue
    from server.pipeline.jobs import JobManager, JobSpec, JobState
    from server.settings import ServerSettings

    gpu = GpuQueue(device=device)
    encoders = ThreadPoolExecutor(max_workers=4)
    with tempfile.TemporaryDirectory() as work:
        limits = ServerSettings().read_limits()
        jobs = JobManager(Path(work), gpu, encoders, Metrics(), limits, batch=engine)
        spec = JobSpec(
            topology=Path(files[0]),
            trajectories=[Path(files[1])] * repeat,
            params=p.RenderParams(),
            camera=None,
            width=size[0],
            height=size[1],
            output="mp4",
        )
        t0 = time.perf_counter()
        job = jobs.submit(spec)
        while job.state in (JobState.QUEUED, JobState.RUNNING):
            await asyncio.sleep(0.05)
        wall = time.perf_counter() - t0
        assert job.state is JobState.DONE, job.error
        out = {"frames": job.done, "wall_s": wall, "frames_per_s": job.done / wall}
    gpu.close()
    encoders.shutdown()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--files", nargs=2, metavar=("PSF", "DCD"), help="default: MDAnalysisTests' adk"
    )
    args = ap.parse_args(argv)
    if args.files is None:
        from MDAnalysisTests.datafiles import DCD, PSF

        args.files = (PSF, DCD)
    files = (str(args.files[0]), str(args.files[1]))
    import ray

    from server.pipeline.distributed import RayBatch

    size = tuple(int(v) for v in args.size.split("x"))
    result: dict[str, Any] = {
        "benchmark": "batch",
        "device": args.device,
        "host": platform.node(),
        "cpus": __import__("os").cpu_count(),
        "size": list(size),
        "runs": [],
    }
    if args.device.startswith("cuda"):
        import warp as wp

        wp.init()
        result["gpu"] = wp.get_device(args.device).name
    base = asyncio.run(run_job(None, args.device, size, args.repeat, files))
    result["runs"].append({"engine": "in-process", **base})
    print(json.dumps(result["runs"][-1]), flush=True)
    ray.init(include_dashboard=False, log_to_driver=False)
    for n in [int(w) for w in args.workers.split(",")]:
        engine = RayBatch(workers=n)

        async def warm_then_time(engine: Any = engine) -> dict[str, Any]:
            await run_job(engine, args.device, size, 1, files)  # start the actors, warm them
            return await run_job(engine, args.device, size, args.repeat, files)

        run = asyncio.run(warm_then_time())
        engine.close()
        run.update(engine="ray", workers=n, time_vs_in_process=run["wall_s"] / base["wall_s"])
        result["runs"].append(run)
        print(json.dumps(run), flush=True)
    ray.shutdown()
    args.out.write_text(json.dumps(result, indent=1))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
