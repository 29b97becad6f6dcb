"""The figure of docs/rendering.md's temporal scale section, computed by the product's filter
(`server.render.temporal`, on the CPU device).

    python docs/figures/temporal_figure.py [--out docs/figures]

`temporal_smoothing.png`, left: one atom at rest with 0.3 A of thermal jitter and one 5 A jump,
raw, classical Gaussian (tau 4 frames) and arclength-warped (tau 4 frames, 1 frame per A),
centred over 33 frames. Right: the x coordinate of one residue's CA in MDAnalysisTests' adk
trajectory (PSF/DCD, a transition path of 98 frames), same three, tau 2 frames over 9.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

from server.render.temporal import TemporalSmoother  # noqa: E402


def centred(frames: np.ndarray, tau: float, strength: float, window: int) -> np.ndarray:
    """Every frame smoothed by the device filter, centred (shorter windows at the ends)."""
    n, atoms = frames.shape[:2]
    half = (window - 1) // 2
    out = np.zeros_like(frames)
    result = wp.zeros(atoms, dtype=wp.vec3, device="cpu")
    for t in range(n):
        lo, hi = max(0, t - half), min(n, t + half + 1)
        s = TemporalSmoother("cpu", atoms, hi - lo)
        for f in frames[lo:hi]:
            s.push(f)
        s.smooth(result, tau, strength, "centred", lag=hi - 1 - t)
        out[t] = result.numpy()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from MDAnalysisTests.datafiles import DCD, PSF

    from structures.reader import load

    wp.config.quiet = True
    rng = np.random.default_rng(0)
    true = np.zeros((240, 1, 3), np.float32)
    true[120:, 0, 0] = 5.0
    noisy = (true + rng.normal(scale=0.3, size=true.shape)).astype(np.float32)
    s = load(PSF, [DCD])
    ca = [i for i, name in enumerate(s.topology.names) if name == "CA"][40]
    adk = np.stack([s.positions(i)[[ca]] for i in range(s.n_frames)]).astype(np.float32)

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    for ax, frames, tau, window, title in (
        (axes[0], noisy, 4.0, 33, "one atom: jitter and a 5 Å jump"),
        (axes[1], adk, 2.0, 9, f"adk, CA of residue {s.topology.residue_ids.to_numpy()[ca]}"),
    ):
        t = np.arange(len(frames))
        ax.plot(t, frames[:, 0, 0], color="0.7", lw=1, label="raw")
        ax.plot(t, centred(frames, tau, 0.0, window)[:, 0, 0], color="tab:blue",
                label=f"classical, τ = {tau:g} frames")  # fmt: skip
        ax.plot(t, centred(frames, tau, 1.0, window)[:, 0, 0], color="tab:red",
                label="warped, 1 frame per Å")  # fmt: skip
        ax.set_xlabel("frame")
        ax.set_ylabel("x (Å)")
        ax.set_title(title)
        ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "temporal_smoothing.png", dpi=110)
    print(args.out / "temporal_smoothing.png")


if __name__ == "__main__":
    main()
