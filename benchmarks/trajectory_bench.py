"""Trajectories of any size: how long a multi-GB XTC or DCD takes to open and show its first
frame, what a seek to any frame costs, and how much memory the reader holds, beside reading
the frames in order (the baseline in the same run).

The trajectory is generated once into a scratch folder (never the checkout): MDAnalysisTests'
solvated adenylate kinase (47,681 atoms, GROMACS TPR) written frame after frame, each of its
10 frames with a little noise, until the file reaches `--gib`. For each file:

* `open_cold_s`: `structures.reader.load` with MDAnalysis' offsets cache removed first (an
  XTC is indexed by reading every frame's header once; a DCD's frames have one size);
  `open_warm_s`: again, the offsets read from the cache MDAnalysis writes beside the file;
* `first_frame_s`: frame 0's positions and box after the open (`load` + this is what a replay
  waits for before its first frame goes out);
* `seek_ms`: the median time to read one frame at random positions all over the file (no
  frame in between is read), against `sequential_ms`, the median time per frame reading in
  order (the baseline);
* `isolated_open_s`, `isolated_frame_ms`: the same through `structures.isolated`, the child
  process the server reads uploads and jobs with;
* `rss_mb` before opening and after every read, in this process: the reader holds one frame.

    python benchmarks/trajectory_bench.py --gib 2 --scratch /tmp/scalesteer-bench \\
        --out benchmarks/results/trajectory_cpu_2core.json
    python benchmarks/trajectory_bench.py --quick --out /tmp/trajectory_quick.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from structures.isolated import IsolatedStructure, ReadLimits
from structures.reader import load


def rss_mb() -> float:
    """This process's resident memory now (Linux /proc), in MB."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def generate(path: Path, gib: float) -> int:
    """Write adenylate kinase's frames (with noise) to `path` until it holds `gib` GiB; the
    frames written."""
    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import TPR, XTC

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(TPR, XTC)
        frames = [(ts.positions.copy(), ts.dimensions.copy()) for ts in u.trajectory]
        rng = np.random.default_rng(0)
        target = gib * (1 << 30)
        count = 0
        with mda.Writer(str(path), u.atoms.n_atoms) as writer:
            while True:
                positions, dims = frames[count % len(frames)]
                noise = rng.normal(scale=0.05, size=positions.shape).astype(np.float32)
                u.trajectory.ts.positions = positions + noise
                u.trajectory.ts.dimensions = dims
                u.trajectory.ts.frame = count
                writer.write(u.atoms)
                count += 1
                if count % 200 == 0 and path.stat().st_size >= target:
                    return count


def forget_offsets(path: Path) -> None:
    for name in (f".{path.name}_offsets.npz", f".{path.name}_offsets.lock"):
        (path.parent / name).unlink(missing_ok=True)


def median(xs: list[float]) -> float:
    return float(np.median(xs)) if xs else float("nan")


def bench_file(topology: str, path: Path, seeks: int, sequential: int) -> dict[str, Any]:
    out: dict[str, Any] = {"file": path.name, "bytes": path.stat().st_size}
    rss = {"start": rss_mb()}
    forget_offsets(path)
    t0 = time.perf_counter()
    structure = load(topology, [str(path)])
    out["open_cold_s"] = time.perf_counter() - t0
    n = structure.n_frames
    out["frames"] = n
    t0 = time.perf_counter()
    structure.frame(0)
    out["first_frame_s"] = time.perf_counter() - t0
    rss["opened"] = rss_mb()
    t0 = time.perf_counter()
    again = load(topology, [str(path)])
    out["open_warm_s"] = time.perf_counter() - t0
    del again
    rng = np.random.default_rng(1)
    seek_times = []
    for index in rng.integers(0, n, size=seeks):
        t0 = time.perf_counter()
        positions, box = structure.frame(int(index))
        seek_times.append((time.perf_counter() - t0) * 1e3)
        assert positions.shape[0] == structure.topology.n_atoms and box is not None
    rss["after_seeks"] = rss_mb()
    in_order = []
    start = n // 2
    for index in range(start, min(n, start + sequential)):
        t0 = time.perf_counter()
        structure.frame(index)
        in_order.append((time.perf_counter() - t0) * 1e3)
    rss["after_sequential"] = rss_mb()
    out["seek_ms"] = median(seek_times)
    out["seek_ms_max"] = max(seek_times)
    out["sequential_ms"] = median(in_order)
    out["seek_per_sequential"] = out["seek_ms"] / out["sequential_ms"]
    limits = ReadLimits(max_atoms=10_000_000, max_file_bytes=1 << 40)
    t0 = time.perf_counter()
    with IsolatedStructure(topology, [str(path)], limits) as isolated:
        out["isolated_open_s"] = time.perf_counter() - t0
        times = []
        for index in rng.integers(0, n, size=max(3, seeks // 4)):
            t0 = time.perf_counter()
            isolated.frame(int(index))
            times.append((time.perf_counter() - t0) * 1e3)
        out["isolated_frame_ms"] = median(times)
    out["rss_mb"] = rss
    out["rss_growth_mb"] = rss["after_sequential"] - rss["start"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gib", type=float, default=2.0, help="size of each generated file")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/scalesteer-bench"))
    ap.add_argument("--formats", default="xtc,dcd")
    ap.add_argument("--seeks", type=int, default=40)
    ap.add_argument("--sequential", type=int, default=40)
    ap.add_argument("--quick", action="store_true", help="small files, few reads")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    from MDAnalysisTests.datafiles import TPR

    gib = 0.02 if args.quick else args.gib
    seeks = 8 if args.quick else args.seeks
    args.scratch.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "host": platform.node(),
        "gpu": "cpu",  # no device: the readers alone
        "host_cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "load_average": list(os.getloadavg()),
        "gib": gib,
        "files": [],
    }
    for fmt in args.formats.split(","):
        path = args.scratch / f"adk_{gib:g}gib.{fmt}"
        if not path.exists() or path.stat().st_size < gib * (1 << 30):
            t0 = time.perf_counter()
            written = generate(path, gib)
            print(f"  wrote {path} ({written} frames) in {time.perf_counter() - t0:.0f} s")
        row = bench_file(TPR, path, seeks, 8 if args.quick else args.sequential)
        result["files"].append(row)
        print(f"  {row}", flush=True)
    text = json.dumps(result, indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
