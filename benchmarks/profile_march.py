"""Renders a few frames of one configuration with the frame's kernels launched one by one,
so a profiler (Nsight Compute) can attribute time to the marching kernel:

    ncu --kernel-name regex:iso_march --launch-skip 2 --launch-count 1 \\
        --section SpeedOfLight --section Occupancy --section LaunchStats \\
        --section WarpStateStats --section MemoryWorkloadAnalysis \\
        python benchmarks/profile_march.py --atoms 100000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol import RenderParams
from server.render import Renderer
from server.render.camera import fit_camera
from server.render.tuning import Tuning

sys.path.insert(0, str(ROOT / "benchmarks"))
from render_bench import build_system, jittered_frames, topology_of


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--atoms", type=int, default=100_000)
    p.add_argument("--size", default="1920x1080")
    p.add_argument("--mode", default="iso", choices=["iso", "volume"])
    p.add_argument("--frames", type=int, default=4)
    p.add_argument(
        "--scale-space", default="classical", choices=["classical", "geodesic", "carved"]
    )
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--budget", type=int, default=None, help="first marching kernel's passes")
    p.add_argument("--lanes", type=int, default=None, help="threads per queued ray")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    pos, el, bonds = build_system(args.atoms)
    kw: dict[str, object] = {"graphs": False}
    if args.budget is not None:
        kw["march_budget"] = args.budget
    if args.lanes is not None:
        kw["split_lanes"] = args.lanes
    r = Renderer(args.device, max_atoms=args.atoms, tuning=Tuning.of(kw))
    r.set_topology(topology_of(el, bonds))
    cam = fit_camera(pos, w, h)
    params = RenderParams(mode=args.mode, scale_space=args.scale_space)  # type: ignore[arg-type]
    for i, frame in enumerate(jittered_frames(pos, args.frames)):
        r.set_positions(frame)
        r.render(params, cam, w, h)
        print(f"frame {i}: {r.timings}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
