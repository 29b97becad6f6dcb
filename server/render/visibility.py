"""Which empty cells of the grid the rays of one view reach before the surface.

Part bounds (the 27 sub-cell bounds of a walked cell, docs/rendering.md) save the most
samples in the empty cells just in front of the surface, but walking every open cell for them
costs in proportion to the atoms: at 10M atoms most open cells lie in cavities or behind the
surface, where no ray samples. `mark_kernel` casts every `stride_for`-th ray of the view through
the cells (a 3D DDA, no density sample) and lists the empty cells whose bound passes the level
that it crosses before it has entered `DEPTH` cells holding atoms (the surface of the view lies
in or just before those) and whose parts are not walked yet; the part walk then takes the list.
Every bound stays an upper bound, so the marks decide only speed: a ray that reaches a cell no
marking ray reached samples it with the cell's own bound, and the image is the one of walking
every cell. While the atoms stay put, each new view lists only the cells it adds.
(No `from __future__ import annotations`: warp resolves kernel annotations eagerly.)
"""

import math
from typing import no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import WALKED, GridInfo
from server.render.raycast import CameraData, camera_ray, clip_box, next_cell, walk_start

wp.set_module_options({"enable_backward": False})

_WALKED = wp.constant(WALKED)  # type: ignore[no-untyped-call]
_UNWALKED = wp.constant(~WALKED)  # type: ignore[no-untyped-call]

STRIDE = 2
"""Every STRIDE-th ray of each image row and column of a 1920x1080 image (or smaller) marks
cells (`stride_for`)."""
STRIDE_PIXELS = 1920 * 1080
"""Above this many pixels the stride grows with the image's linear size."""
DEPTH = 4
"""A marking ray stops once it has entered this many cells holding atoms: the surface of the
view lies in or before them for nearly every ray (a ray that grazes on finds cells with
their whole-cell bound)."""


MARK_REGISTERS = 64
"""Registers per thread of `mark_kernel` on CUDA: the compiler's choice (90) held it to a
quarter of the warps a multiprocessor can keep, and the kernel is bound by the latency of
its DDA steps, which more warps hide."""


def stride_for(width: int, height: int) -> int:
    """The marking rays' stride for a width x height image: `STRIDE` up to `STRIDE_PIXELS`,
    above in proportion to the image's linear size, so a larger image casts about as many
    marking rays (a cell covers more of its pixels). One H200, 3840x2160 iso: stride 4 against
    2, 1M atoms 14.44 / 14.35 ms against 14.52 / 14.50, 3M 19.25 / 19.21 against 19.46 / 19.43
    (benchmarks/HISTORY.md, "Render core, round six")."""
    scale = math.sqrt(width * height / STRIDE_PIXELS)
    return max(STRIDE, round(STRIDE * scale))


def rays(width: int, height: int, stride: int) -> tuple[int, int]:
    """Marking rays per row and per column of a width x height view."""
    return -(-width // stride), -(-height // stride)


@wp.kernel(cuda_max_registers=MARK_REGISTERS)
@no_type_check
def mark_kernel(
    info: wp.array[GridInfo],
    cam: CameraData,
    stride: int,
    cols: int,
    rows: int,
    depth: int,
    level: float,
    cell_start: wp.array[wp.int32],
    bound: wp.array[float],
    parts: wp.array[wp.int32],
    work: wp.array[wp.int32],
    work_count: wp.array[wp.int32],
):
    """List in `work` each empty cell with a bound at or above `level` and parts not yet
    walked that ray i crosses before its `depth`-th cell with atoms, once (the first ray to
    set its WALKED bit lists it; a full list leaves the bit clear)."""
    i = wp.tid()
    g = info[0]
    if g.valid == 0 or i >= cols * rows:
        return
    x = wp.min((i % cols) * stride + stride // 2, cam.width - 1)
    y = wp.min((i // cols) * stride + stride // 2, cam.height - 1)
    o, d = camera_ray(cam, x, y)
    t0, t1 = clip_box(o, d, g.origin, g.box_hi)
    if t0 >= t1:
        return
    cx, cy, cz, sx, sy, sz, tx, ty, tz, dtx, dty, dtz, left = walk_start(o, d, t0, g)
    seen = wp.int32(0)
    going = wp.int32(1)
    while going != 0:
        c = (cz * g.dims[1] + cy) * g.dims[0] + cx
        if cell_start[c + 1] > cell_start[c]:
            seen += 1
            if seen >= depth:
                going = 0
        elif bound[c] >= level and (parts[c] & _WALKED) == 0:  # noqa: SIM102
            # (nested: a kernel's `and` evaluates both sides, and this one is an atomic)
            if (wp.atomic_or(parts, c, _WALKED) & _WALKED) == 0:
                slot = wp.atomic_add(work_count, 0, 1)
                if slot < work.shape[0]:
                    work[slot] = c
                else:
                    wp.atomic_and(parts, c, _UNWALKED)
        left -= 1
        if going == 0 or wp.min(wp.min(tx, ty), tz) >= t1 or left <= 0:
            going = 0
        else:
            cx, cy, cz, tx, ty, tz, going = next_cell(
                g, cx, cy, cz, tx, ty, tz, sx, sy, sz, dtx, dty, dtz
            )
