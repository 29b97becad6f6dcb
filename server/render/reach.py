"""How far each atom's Gaussian reaches: the least cutoff that keeps the surface in place.

The renderer tapers every Gaussian to zero at k sigma (density.py). The surface of the default
relative level moves against the untruncated density by at most max(0.05 A, 1 % of sigma) once k
is large enough, and how large depends on sigma: at small sigma the level sits close to the
atoms, where the tail beyond 3 sigma weighs nothing; at large sigma the surface is made of the
overlapping tails of many atoms. `REACH` is the least k measured on real proteins
(`benchmarks/reach_accuracy.py`, `benchmarks/results/reach_accuracy.json`: villin and adenylate
kinase, 32 rays each) plus a quarter sigma of margin; `reach_sigmas` interpolates it in log
sigma and never exceeds the render parameters' `cutoff_sigmas`. `surface_shift` is the
float64 measure both the benchmark and the tests use.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

REACH: tuple[tuple[float, float], ...] = (
    (0.3, 2.75),
    (0.5, 4.0),
    (0.75, 3.75),
    (1.0, 4.0),
    (1.5, 3.75),
    (2.0, 4.0),
    (3.0, 4.0),
    (4.5, 3.75),
    (6.0, 3.75),
    (9.0, 3.75),
    (12.0, 3.75),
)
"""(sigma in A, k): the least cutoff measured, plus margin (see the module docstring)."""


def reach_sigmas(sigma: float, limit: float) -> float:
    """The cutoff in sigmas the accuracy bound needs at `sigma` (interpolated in log sigma,
    held flat beyond the table), at most `limit`."""
    s = np.log([p[0] for p in REACH])
    k = np.array([p[1] for p in REACH])
    need = float(np.interp(math.log(max(float(sigma), 1e-6)), s, k))
    return min(need, float(limit))


def _density(points: F64, positions: F64, sigma: float, k: float | None) -> F64:
    from scipy.spatial import cKDTree

    reach = (k if k is not None else 8.0) * sigma
    tree = cKDTree(positions)
    out = np.zeros(len(points))
    for start in range(0, len(points), 2048):
        block = points[start : start + 2048]
        near = tree.query_ball_point(block, reach)
        owner = np.repeat(np.arange(len(block)), [len(x) for x in near])
        if not len(owner):
            continue
        atoms = np.concatenate([np.asarray(x, dtype=np.int64) for x in near])
        d2 = ((positions[atoms] - block[owner]) ** 2).sum(axis=1)
        e = d2 / (2.0 * sigma * sigma)
        value = np.exp(-e)
        if k is not None:
            ek = 0.5 * k * k
            u = np.minimum(e / ek, 1.0)
            value = value * (1.0 - u**16) ** 2
        out[start : start + len(block)] = np.bincount(owner, value, minlength=len(block))
    return out


def surface_shift(
    positions: npt.ArrayLike, sigma: float, k: float, level: float = 0.25, rays: int = 32
) -> float:
    """How far (A) the outermost crossing of the iso-surface at `level` times the mean density
    at the atoms moves, along `rays` rays from the centre, when each Gaussian is tapered at
    `k` sigma instead of untruncated (8 sigma: its tail beyond weighs under 1e-13)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    centre = pos.mean(axis=0)
    extent = float(np.linalg.norm(pos - centre, axis=1).max())
    dirs = np.random.default_rng(11).normal(size=(rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    radii = np.linspace(0.0, extent + 5.0 * sigma, 900)
    pts = (centre + radii[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    crossings = []
    for cut in (None, k):
        field = _density(pts, pos, sigma, cut).reshape(rays, -1)
        scale = _density(pos[:: max(1, len(pos) // 2048)], pos, sigma, cut).mean()
        s = field - level * scale
        out = np.full(rays, np.nan)
        for r in range(rays):
            above = np.nonzero(s[r] >= 0)[0]
            if len(above) and above[-1] + 1 < len(radii):
                i = above[-1]
                out[r] = radii[i] + s[r, i] / (s[r, i] - s[r, i + 1]) * (radii[i + 1] - radii[i])
        crossings.append(out)
    a, b = crossings
    both = np.isfinite(a) & np.isfinite(b)
    if (np.isfinite(a) != np.isfinite(b)).any():
        return math.inf
    return float(np.abs(a[both] - b[both]).max()) if both.any() else 0.0
