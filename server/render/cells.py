"""The cell grid's layout and the rows of cells a walk around a box visits.

The grid itself is built every frame by grid.py; the density walks (density.py, warped.py)
read its layout from `GridInfo` and visit the rows of cells within the cutoff reach of a box,
each row trimmed to its chord of the reach (`row_span`).
(No `from __future__ import annotations`: warp resolves function annotations eagerly.)
"""

from typing import no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)

wp.set_module_options({"enable_backward": False})


@wp.struct
class GridInfo:
    """The cell grid of one frame, computed on the device (no host round trip)."""

    origin: wp.vec3
    h: float
    inv_h: float
    dims: wp.vec3i
    ncells: int
    box_hi: wp.vec3
    reach: float
    valid: int
    bdims: wp.vec3i  # bricks of BRICK^3 cells per axis
    bricks: int  # 1 when the brick bounds exist for this grid


BRICK = 4
"""Cells per brick edge: the coarse level of empty-space skipping."""
PARTS = 3
"""Parts per cell edge: the fine level of empty-space skipping. A walked cell also keeps which
of its PARTS^3 = 27 parts have a density bound below the level, one bit each of one word."""
PART_SLACK = 1.0e-3
"""Each part's bound covers the part widened by this fraction of its edge on every side, so
a point that rounding puts in the part beside it is still covered."""

PART_BITS = (1 << PARTS**3) - 1
"""The bits of a cell's word that mark its parts below the level."""
WALKED = 1 << 30
"""The bit of a cell's word set once its parts have been walked, so a view that reaches it
again does not list it twice (visibility.py)."""

_PARTS = wp.constant(PARTS)  # type: ignore[no-untyped-call]


@wp.func
@no_type_check
def axis_span(a: float, b: float, origin: float, inv_h: float, n: int):
    """Cells [lo, hi] along one axis that overlap [a, b] (clamped, possibly empty)."""
    fa = wp.clamp((a - origin) * inv_h, -1.0, float(n))
    fb = wp.clamp((b - origin) * inv_h, -1.0, float(n))
    return wp.max(int(wp.floor(fa)), 0), wp.min(int(wp.floor(fb)), n - 1)


@wp.func
@no_type_check
def row_span(g: GridInfo, lo_x: float, hi_x: float, dy: float, dz: float, r2: float):
    """Cells [x0, x1] of the row at gaps (dy, dz) from the box [lo, hi] that hold atoms within
    sqrt(r2) of a point of the box (empty when x1 < x0): the row's chord of the rounded box,
    so no atom of a cutoff sphere is lost and rows near the rim load fewer atoms."""
    rem = r2 - dy * dy - dz * dz
    x0 = wp.int32(0)
    x1 = wp.int32(-1)
    if rem > 0.0:
        hw = wp.sqrt(rem)
        x0, x1 = axis_span(lo_x - hw, hi_x + hw, g.origin[0], g.inv_h, g.dims[0])
    return x0, x1


@wp.func
@no_type_check
def interval_gap(lo_a: float, hi_a: float, lo_b: float, hi_b: float) -> float:
    """Distance between intervals [lo_a, hi_a] and [lo_b, hi_b] (0 when they overlap)."""
    return wp.max(wp.max(lo_a - hi_b, lo_b - hi_a), 0.0)


@wp.func
@no_type_check
def cell_at(g: GridInfo, p: wp.vec3) -> int:
    """Index of the cell holding p (clamped to the grid; x fastest)."""
    q = (p - g.origin) * g.inv_h
    cx = wp.clamp(int(wp.floor(q[0])), 0, g.dims[0] - 1)
    cy = wp.clamp(int(wp.floor(q[1])), 0, g.dims[1] - 1)
    cz = wp.clamp(int(wp.floor(q[2])), 0, g.dims[2] - 1)
    return (cz * g.dims[1] + cy) * g.dims[0] + cx


@wp.func
@no_type_check
def cell_box(g: GridInfo, c: int):
    """The corners (lo, hi) of cell c (x fastest)."""
    ix = c % g.dims[0]
    iy = (c // g.dims[0]) % g.dims[1]
    iz = c // (g.dims[0] * g.dims[1])
    lo = g.origin + wp.vec3(float(ix), float(iy), float(iz)) * g.h
    return lo, lo + wp.vec3(g.h, g.h, g.h)


@wp.func
@no_type_check
def part_at(g: GridInfo, p: wp.vec3):
    """The cell holding p (as `cell_at`) and the bit of its part (x fastest)."""
    q = (p - g.origin) * g.inv_h
    cx = wp.clamp(int(wp.floor(q[0])), 0, g.dims[0] - 1)
    cy = wp.clamp(int(wp.floor(q[1])), 0, g.dims[1] - 1)
    cz = wp.clamp(int(wp.floor(q[2])), 0, g.dims[2] - 1)
    n = float(_PARTS)
    px = wp.clamp(int((q[0] - float(cx)) * n), 0, _PARTS - 1)
    py = wp.clamp(int((q[1] - float(cy)) * n), 0, _PARTS - 1)
    pz = wp.clamp(int((q[2] - float(cz)) * n), 0, _PARTS - 1)
    cell = (cz * g.dims[1] + cy) * g.dims[0] + cx
    return cell, px + _PARTS * (py + _PARTS * pz)
