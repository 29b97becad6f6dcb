"""How much of the geodesic grid an iso image reaches: the bricks the fill walks (the control,
every brick whose points' bound reaches the cut) against those within the spline's and the
prefilter's reach of a ray's hit (`geodesic_volume.REACH_STEPS` grid steps).

A frame fills the grid over the whole atom box, and the rays of an iso image read it only up
to their first crossing. Bricks farther than REACH_STEPS steps from every hit change no pixel
beyond what the prefilter's decay (0.27 a step) carries: their share is what a grid limited to
the view could leave unwalked. The count is the same on any device, so it runs on the CPU.

    python benchmarks/visible_bricks.py --cases 496@500x500 --out /tmp/visible_bricks.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.render_bench import build_system, cases_of, topology_of
from protocol import RenderParams
from server.render import geodesic_volume
from server.render.camera import camera_frame, fit_camera, image_rays
from server.render.renderer import Renderer
from server.render.tuning import Tuning


def brick_centres(r: Renderer) -> tuple[np.ndarray, float]:
    """Centres of the bricks the last grid listed, and the grid's spacing."""
    vol = r._gvol
    assert vol is not None
    v = vol.vol.numpy()[0]
    nx, ny, _nz = (int(x) for x in v["dims"])
    bx = -(-nx // geodesic_volume.BRICK_X)
    by = -(-ny // geodesic_volume.BRICK_Y)
    listed = vol.listed.numpy()[: int(vol.count.numpy()[0])].astype(np.int64)
    corner = np.stack(
        [
            (listed % bx) * geodesic_volume.BRICK_X,
            ((listed // bx) % by) * geodesic_volume.BRICK_Y,
            (listed // (bx * by)) * geodesic_volume.BRICK_Z,
        ],
        axis=1,
    ).astype(np.float64)
    half = (
        np.array([geodesic_volume.BRICK_X, geodesic_volume.BRICK_Y, geodesic_volume.BRICK_Z]) - 1
    ) / 2.0
    h = float(v["h"])
    return np.asarray(v["origin"], np.float64) + (corner + half) * h, h


def measure(
    n: int, w: int, h: int, sigma: float, reach_steps: float = geodesic_volume.REACH_STEPS
) -> dict[str, Any]:
    """One case's walked and reached bricks (a brick is reached when its centre lies within
    `reach_steps` grid steps plus its half diagonal of a hit)."""
    pos, el, bonds = build_system(n)
    r = Renderer("cpu", max_atoms=n, tuning=Tuning(geodesic_volume=True))
    r.set_topology(topology_of(el, bonds))
    r.set_positions(pos)
    cam = fit_camera(pos, w, h)
    params = RenderParams(scale_space="geodesic", sigma_A=sigma)
    t0 = time.perf_counter()
    r.render(params, cam, w, h)
    seconds = time.perf_counter() - t0
    assert r.last_density == "geodesic_volume", r.last_density
    centres, step = brick_centres(r)
    depth = r.read_depth()
    origins, dirs = image_rays(camera_frame(cam, w, h))
    hit = np.isfinite(depth)
    hits = origins[hit] + depth[hit][:, None] * dirs[hit]
    half_diagonal = 0.5 * step * float(np.linalg.norm([3.0, 3.0, 1.0]))
    reach = reach_steps * step + half_diagonal
    near, _ = cKDTree(hits).query(centres, k=1, distance_upper_bound=reach)
    reached = int(np.isfinite(near).sum())
    return {
        "n_atoms": n,
        "width": w,
        "height": h,
        "sigma_A": sigma,
        "spacing_A": step,
        "reach_A": reach,
        "bricks_walked": len(centres),
        "bricks_reached": reached,
        "reached_share": reached / max(len(centres), 1),
        "hit_pixels": int(hit.sum()),
        "frame_s_cpu": seconds,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default="496@500x500,5684@500x500")
    p.add_argument("--sigma", type=float, default=1.5)
    p.add_argument("--out", default="")
    args = p.parse_args(argv)
    rows = []
    for n, w, h in cases_of(args.cases, []):
        row = measure(n, w, h, args.sigma)
        rows.append(row)
        print(
            f"N={n:,} {w}x{h}: {row['bricks_reached']:,} of {row['bricks_walked']:,} walked "
            f"bricks within {row['reach_A']:.2f} A of a hit ({row['reached_share']:.1%})",
            flush=True,
        )
    if args.out:
        out = {
            "benchmark": "visible_bricks",
            "device": "cpu",
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "rows": rows,
        }
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
