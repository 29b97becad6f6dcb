"""Neighbour walks shared by a block of rays: the thesis's work-block cache (5.2.3, fig. 5.3).

The per-ray walks of density.py give every ray its own chain of loads: the 32 rays of a warp
(an 8x4 tile of neighbouring pixels) read nearly the same atoms, one after another, and rays
whose walks differ in length leave lanes idle. Here the block of `COOP` rays (one warp) walks
one neighbourhood together. The rays that need a density pass are grouped around a leader (the
lowest lane still waiting): every ray whose query box lies within `margin` of the leader's joins
the group. The rows of cells around the group's box are listed once, one row per lane; their
atoms are loaded `COOP` at a time, one per lane (independent loads, all in flight together),
into shared memory; then every ray of the group sums, from shared memory, the atoms it reaches.
Rays outside the group wait for the next round, with a leader of their own.

Every function here synchronises the block: all its threads must reach it the same number of
times, rays without work passing `want = 0`. Each ray still visits the atoms it reaches in the
order its own walk would (rows by z then y, atoms in cell order), and atoms of the group's wider
rows lie beyond its cutoff, so its sums are bit for bit the per-ray ones.
(No `from __future__ import annotations`: warp resolves the annotations of generated
functions eagerly.)
"""

from typing import Any, no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import GridInfo, axis_span, interval_gap, row_span

wp.set_module_options({"enable_backward": False})

COOP = 32
"""Rays per block that share their walks: one warp, one 8x4 pixel tile of the caster."""
_COOP = wp.constant(COOP)  # type: ignore[no-untyped-call]
_FAR = wp.constant(3.0e30)  # type: ignore[no-untyped-call]


@wp.struct
class Group:
    """One round's group: whether this ray is in it, and the box every member lies in."""

    member: int
    lo: wp.vec3
    hi: wp.vec3
    found: int


@wp.func
@no_type_check
def block_any(flag: int) -> int:
    """1 when any thread of the block passes a non-zero flag (all threads get the answer)."""
    return wp.tile_max(wp.tile(flag))[0]


@wp.func
@no_type_check
def block_min(x: float) -> float:
    """The smallest x over the block's threads (all threads get it)."""
    return wp.tile_min(wp.tile(x))[0]


@wp.func
@no_type_check
def group_of(left: int, lo: wp.vec3, hi: wp.vec3, lane: int, margin: float) -> Group:
    """The next group among the rays with `left` set: the lowest such lane leads, and every
    waiting ray whose box [lo, hi] lies inside the leader's grown by `margin` joins it. The
    group's box is the union of its members' boxes."""
    nb = wp.block_dim()
    cand = nb
    if left != 0:
        cand = lane
    leader = wp.tile_min(wp.tile(cand))[0]
    out = Group()
    out.member = 0
    out.found = 0
    out.lo = lo
    out.hi = hi
    if leader < nb:
        grow = wp.vec3(margin, margin, margin)
        glo = wp.tile_from_thread(shape=1, value=lo, thread_idx=leader, storage="shared")[0] - grow
        ghi = wp.tile_from_thread(shape=1, value=hi, thread_idx=leader, storage="shared")[0] + grow
        out.found = 1
        inside = lo[0] >= glo[0] and lo[1] >= glo[1] and lo[2] >= glo[2]
        inside = inside and hi[0] <= ghi[0] and hi[1] <= ghi[1] and hi[2] <= ghi[2]
        ulo = wp.vec3(_FAR, _FAR, _FAR)
        uhi = wp.vec3(-_FAR, -_FAR, -_FAR)
        if lane == leader or (left != 0 and inside):
            out.member = 1
            ulo = lo
            uhi = hi
        # the group walks the rows around its members' union, not the whole grown box
        out.lo = wp.vec3(block_min(ulo[0]), block_min(ulo[1]), block_min(ulo[2]))
        out.hi = wp.vec3(-block_min(-uhi[0]), -block_min(-uhi[1]), -block_min(-uhi[2]))
    return out


@wp.func
@no_type_check
def row_cells(g: GridInfo, r: int, z0: int, y0: int, ny: int, lo: wp.vec3, hi: wp.vec3):
    """Row r (by z, then y) of the rows around [lo, hi]: the index of its first cell and its
    cells [x0, x1], trimmed to the chord of the reach like the per-ray walk (x1 < x0: none)."""
    iz = z0 + r // ny
    iy = y0 + r % ny
    zlo = g.origin[2] + float(iz) * g.h
    ylo = g.origin[1] + float(iy) * g.h
    dz = interval_gap(lo[2], hi[2], zlo, zlo + g.h)
    dy = interval_gap(lo[1], hi[1], ylo, ylo + g.h)
    x0, x1 = row_span(g, lo[0], hi[0], dy, dz, g.reach * g.reach)
    return (iz * g.dims[1] + iy) * g.dims[0], x0, x1


@wp.func
@no_type_check
def slot_row(offsets: wp.tile[wp.int32, COOP], nb: int, gi: int) -> int:
    """The last of the block's `nb` rows whose first slot is at or before `gi` (offsets
    ascend)."""
    lo = wp.int32(0)
    hi = nb - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if offsets[mid] <= gi:
            lo = mid
        else:
            hi = mid - 1
    return lo


def coop_rows(
    name: str, load: Any, consume: Any, query: Any, acc: Any, field: Any, wide: bool
) -> Any:
    """A block-cooperative walk over the sorted items around each ray's box (the cooperative
    form of density.cell_rows).

    Returns `walk(f, lo, hi, q, total, want, lane, margin) -> total`: the rays with `want` set
    add `consume(f, q, a, b, i, total)` for every item of the rows around their box, where
    `load(f, j) -> (a: vec4, b: vec4, i: int)` is what one lane loads for sorted item j into
    shared memory (`wide` = False: only `a` travels, and `consume` must not read b or i).
    `query` and `acc` are the warp types of q and total; `field` is the struct walked (any
    with `info` and `cell_start`)."""
    Query = query
    Acc = acc
    Field = field
    WIDE = wide

    @no_type_check
    def walk(
        f: Field,
        lo: wp.vec3,
        hi: wp.vec3,
        q: Query,
        total: Acc,
        want: int,
        lane: int,
        margin: float,
    ) -> Acc:
        g = f.info[0]
        r = g.reach
        nb = wp.block_dim()
        out = total
        left = want
        row_j0 = wp.tile_zeros(shape=_COOP, dtype=wp.int32, storage="shared")
        row_off = wp.tile_zeros(shape=_COOP, dtype=wp.int32, storage="shared")
        items_a = wp.tile_zeros(shape=_COOP, dtype=wp.vec4, storage="shared")
        items_b = wp.tile_zeros(shape=_COOP, dtype=wp.vec4, storage="shared")
        items_i = wp.tile_zeros(shape=_COOP, dtype=wp.int32, storage="shared")
        going = wp.int32(1)
        while going != 0:
            grp = group_of(left, lo, hi, lane, margin)
            if grp.found == 0:
                going = 0
            else:
                z0, z1 = axis_span(grp.lo[2] - r, grp.hi[2] + r, g.origin[2], g.inv_h, g.dims[2])
                y0, y1 = axis_span(grp.lo[1] - r, grp.hi[1] + r, g.origin[1], g.inv_h, g.dims[1])
                ny = y1 - y0 + 1
                rows = wp.max(z1 - z0 + 1, 0) * wp.max(ny, 0)
                base = wp.int32(0)
                while base < rows:
                    j0 = wp.int32(0)
                    count = wp.int32(0)
                    if base + lane < rows:
                        cells, x0, x1 = row_cells(g, base + lane, z0, y0, ny, grp.lo, grp.hi)
                        if x1 >= x0:
                            j0 = f.cell_start[cells + x0]
                            count = f.cell_start[cells + x1 + 1] - j0
                    counts = wp.tile(count)
                    first = wp.untile(wp.tile_scan_exclusive(counts))
                    n_items = wp.tile_sum(counts)[0]
                    row_j0[lane] = j0
                    row_off[lane] = first
                    c = wp.int32(0)
                    while c < n_items:
                        gi = c + lane
                        a = wp.vec4(_FAR, _FAR, _FAR, 0.0)
                        b = wp.vec4(0.0, 0.0, 0.0, 0.0)
                        oj = wp.int32(-1)
                        if gi < n_items:
                            s = slot_row(row_off, nb, gi)
                            a, b, oj = load(f, row_j0[s] + gi - row_off[s])
                        # every lane is done reading the last chunk before it is overwritten
                        row_j0[lane] = row_j0[lane]
                        items_a[lane] = a
                        if wp.static(WIDE):
                            items_b[lane] = b
                            items_i[lane] = oj
                        n = wp.min(nb, n_items - c)
                        if grp.member != 0:
                            for m in range(n):
                                if wp.static(WIDE):
                                    out = consume(f, q, items_a[m], items_b[m], items_i[m], out)
                                else:
                                    out = consume(f, q, items_a[m], b, oj, out)
                        c += nb
                    base += nb
                if grp.member != 0:
                    left = 0
        # no thread leaves (and frees the shared rows) while another still reads them
        row_j0[lane] = 0
        return out

    return wp.func(name=f"coop_{name}")(walk)
