"""1D transfer functions for volume mode: control points -> a 256-entry RGBA table.

`x` is density in units of the iso level (x = S / iso_level). The table samples x uniformly on
[0, x_max] (x_max = the largest control point); beyond x_max the last entry holds. Alpha is the
opacity of a 1 angstrom thick slab (`REFERENCE_LENGTH`), so images do not change with the ray
step: a constant density over a length dt gets alpha' = 1 - (1 - alpha) ** (dt / REFERENCE_LENGTH).
The caster reads the table through its segments (segments.py), the integral along a ray segment
whose density changes from one sample to the next.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol import TFPoint

TABLE_SIZE = 256
REFERENCE_LENGTH = 1.0
"""Angstrom of material over which a transfer-function alpha applies."""

Point = tuple[float, tuple[float, float, float], float]

PRESETS: dict[str, tuple[Point, ...]] = {
    # a soft electron cloud: faint at the rim, denser and whiter inside
    "cloud": (
        (0.0, (0.25, 0.45, 0.95), 0.0),
        (0.15, (0.25, 0.45, 0.95), 0.0),
        (0.5, (0.45, 0.65, 1.0), 0.06),
        (1.0, (0.8, 0.88, 1.0), 0.2),
        (2.0, (1.0, 1.0, 1.0), 0.45),
        (4.0, (1.0, 0.95, 0.85), 0.7),
    ),
    # nested translucent shells at half, one and two iso levels
    "shells": (
        (0.0, (0.2, 0.45, 1.0), 0.0),
        (0.25, (0.2, 0.45, 1.0), 0.0),
        (0.5, (0.2, 0.5, 1.0), 0.12),
        (0.75, (0.3, 0.8, 0.7), 0.0),
        (1.0, (0.3, 1.0, 0.4), 0.3),
        (1.3, (0.8, 0.7, 0.3), 0.0),
        (1.6, (1.0, 0.35, 0.2), 0.0),
        (2.0, (1.0, 0.35, 0.2), 0.7),
        (2.4, (1.0, 0.35, 0.2), 0.0),
    ),
    # an opaque wall at the iso level: volume mode that looks like iso mode
    "iso-like": (
        (0.0, (0.85, 0.85, 0.9), 0.0),
        (0.95, (0.85, 0.85, 0.9), 0.0),
        (1.0, (0.85, 0.85, 0.9), 1.0),
        (2.0, (0.85, 0.85, 0.9), 1.0),
    ),
}


@dataclass(frozen=True)
class TransferTable:
    """A sampled transfer function.

    `rgba` is (TABLE_SIZE, 4) float32 (colour, per-angstrom alpha) at x = i * x_max / (size-1);
    `clear_below` is the largest x with alpha(y) == 0 for every y <= x (-1 if alpha(0) > 0):
    regions whose density bound stays at or below it are skipped.
    """

    rgba: npt.NDArray[np.float32]
    x_max: float
    clear_below: float

    def lookup(self, x: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Linear interpolation in the table, exactly as the device does it: (..., 4)."""
        xs = np.asarray(x, dtype=np.float64)
        n = self.rgba.shape[0]
        u = np.clip(xs / self.x_max, 0.0, 1.0) * (n - 1)
        i0 = np.minimum(np.floor(u).astype(np.int64), n - 1)
        i1 = np.minimum(i0 + 1, n - 1)
        f = (u - i0)[..., None]
        t = self.rgba.astype(np.float64)
        out: npt.NDArray[np.float64] = t[i0] * (1.0 - f) + t[i1] * f
        return out


def _as_points(points: Sequence[TFPoint] | Sequence[Point]) -> list[Point]:
    out: list[Point] = []
    for p in points:
        if isinstance(p, TFPoint):
            out.append((float(p.x), (p.color[0], p.color[1], p.color[2]), float(p.alpha)))
        else:
            x, c, a = p
            out.append((float(x), (float(c[0]), float(c[1]), float(c[2])), float(a)))
    return out


def build_table(
    points: Sequence[TFPoint] | Sequence[Point] = (),
    preset: str = "cloud",
    size: int = TABLE_SIZE,
) -> TransferTable:
    """Sample piecewise-linear control points (or the preset when `points` is empty).

    Points are sorted by x; ties keep their given order, which makes a step at that x.
    """
    if size < 2:
        raise ValueError("transfer table needs at least 2 entries")
    pts = _as_points(points) if len(points) else list(PRESETS[preset])
    for x, c, a in pts:
        if (
            not all(np.isfinite((x, *c, a)))
            or x < 0
            or not 0 <= a <= 1
            or not all(0 <= v <= 1 for v in c)
        ):
            raise ValueError(f"transfer-function point out of range: x={x}, color={c}, alpha={a}")
    pts.sort(key=lambda p: p[0])
    xs = np.array([p[0] for p in pts])
    vals = np.array([[*p[1], p[2]] for p in pts])
    x_max = float(xs[-1]) if xs[-1] > 0 else 1.0
    grid = np.linspace(0.0, x_max, size)
    table: npt.NDArray[np.float32] = np.stack(
        [np.interp(grid, xs, vals[:, k]) for k in range(4)], axis=-1
    ).astype(np.float32)
    nonzero = np.nonzero(table[:, 3] > 0)[0]
    if len(nonzero) == 0:
        clear = float("inf")
    elif nonzero[0] == 0:
        clear = -1.0
    else:
        clear = float(grid[nonzero[0] - 1])
    return TransferTable(rgba=table, x_max=x_max, clear_below=clear)


def sample_alpha(alpha: npt.ArrayLike, dt: float) -> npt.NDArray[np.float64]:
    """Opacity of a constant density over a length `dt` from a per-`REFERENCE_LENGTH` alpha."""
    a = np.clip(np.asarray(alpha, dtype=np.float64), 0.0, 1.0)
    out: npt.NDArray[np.float64] = 1.0 - np.power(1.0 - a, dt / REFERENCE_LENGTH)
    return out
