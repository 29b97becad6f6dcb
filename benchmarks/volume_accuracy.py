"""How close a volume image is to the converged one, by step and by how segments are composited:
the pre-integrated segments (the density's ramp between samples, `server/render/segments.py`)
against the sample sum they replaced (each sample's density held over its step), in the same run.

Villin (the demo's protein) at 128x128 through the "cloud" (the default) and the sharp "shells"
transfer functions, shaded (the default lighting) and unshaded, on warp's CPU device; the
reference is each transfer function's segments at a 1/32-sigma step. Errors are in 8-bit
levels over the image (mean, 99th percentile, largest).

    python benchmarks/volume_accuracy.py --out benchmarks/results/volume_accuracy.json

The renderer's volume step (`tuning.VOLUME_STEPS` lattice steps of `step_sigmas`) is chosen from
this table; the speed it buys is `render_bench.py`'s (render_h200_volume_segments.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol import Camera, Lighting, RenderParams
from server.render.renderer import Renderer
from server.render.tuning import Tuning

REFERENCE_STEP = 1 / 32
STEPS = (0.125, 0.25, 0.5, 1.0)
SIZE = 128


def villin() -> tuple[Any, np.ndarray]:
    from tests.render.molecules import villin as load

    m = load()
    return m.topology, m.positions


def image(topology: Any, positions: np.ndarray, params: RenderParams, ramps: bool) -> np.ndarray:
    c = positions.mean(0)
    cam = Camera(position=tuple(c + np.array([0.0, 0.0, 60.0])), target=tuple(c), fov_deg=40)
    r = Renderer("cpu", tuning=Tuning(volume_steps=1, volume_ramps=ramps))
    r.set_topology(topology)
    r.set_positions(positions)
    r.render(params, cam, SIZE, SIZE)
    return r.read_rgba()[..., :3].astype(np.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    topology, positions = villin()
    rows: list[dict[str, Any]] = []
    for preset in ("cloud", "shells"):
        for shaded in (True, False):
            light = Lighting() if shaded else Lighting(diffuse=0.0, specular=0.0, ambient=1.0)

            def params(step: float, p: str = preset, lt: Lighting = light) -> RenderParams:
                return RenderParams(mode="volume", tf_preset=p, step_sigmas=step, lighting=lt)  # type: ignore[arg-type]

            ref = image(topology, positions, params(REFERENCE_STEP), True)
            for step in STEPS:
                for ramps in (False, True):
                    t0 = time.perf_counter()
                    err = np.abs(image(topology, positions, params(step), ramps) - ref)
                    row = {
                        "preset": preset,
                        "shaded": shaded,
                        "step_sigmas": step,
                        "segments": "ramps" if ramps else "sample sum",
                        "mean": round(float(err.mean()), 4),
                        "p99": float(np.percentile(err, 99)),
                        "max": float(err.max()),
                        "cpu_s": round(time.perf_counter() - t0, 2),
                    }
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    out = {
        "benchmark": "volume_accuracy",
        "device": "cpu",
        "host": platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "molecule": "villin",
        "size": [SIZE, SIZE],
        "reference_step_sigmas": REFERENCE_STEP,
        "rows": rows,
    }
    if args.out:
        args.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
