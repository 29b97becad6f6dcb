"""Uniform cell grid rebuilt on the device every frame.

Build: bounding box (atomic min/max) -> grid layout (one thread, so the host never waits) ->
cell key per atom and per-cell counts -> exclusive scan of the counts = `cell_start` -> atoms
in cell order (`order`), by one of two sorts:

* "counting" (the default): each atom's rank in its cell is the value its count's atomic add
  returned, so its slot is `cell_start[cell] + rank`; the ranks come in the order the device
  ran the atoms, so each cell's atoms are then put back in index order (each atom moves by the
  number of its cell's atoms with a smaller index, in cells of up to `SORTED_IN_CELL` atoms).
  The result is the stable sort's, atom for atom, without its passes over all keys. Grids
  whose cells are large enough to hold more (`DENSE_ATOMS_PER_A3`) use the radix sort.
* "radix": a stable radix sort of (cell, atom) pairs.

Cells are ordered x-fastest, so a row of neighbouring cells is one contiguous range of sorted
atoms. Everything is sized once from the atom count; the grid never has more than
`cell_capacity(n)` cells (the cell size grows when the box would need more).
"""

from __future__ import annotations

from typing import Any, no_type_check

import warp

from protocol.limits import MAX_COORDINATE_A
from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import BRICK, GridInfo, cell_at

wp: Any = warp  # warp's host API is unannotated: calls through it are dynamic

FAR = wp.constant(float(MAX_COORDINATE_A))
"""A coordinate past this flags its frame (`protocol.limits.MAX_COORDINATE_A`)."""

wp.set_module_options({"enable_backward": False})

MIN_CELLS = 1 << 15
CELLS_PER_ATOM = 1.875
MAX_REDUCE_THREADS = 1 << 18
REDUCE_BLOCK = 256
"""The bounding box is reduced by up to MAX_REDUCE_THREADS threads in blocks of REDUCE_BLOCK
(one atomic per axis and block)."""


SORTED_IN_CELL = 64
"""The counting sort puts the atoms of cells of up to this many atoms in index order; a cell
with more keeps the order the device ran its atoms in (the same atoms, with sums over them
equal up to float rounding from frame to frame). Each atom reads its cell's slots, so the
limit also bounds that work."""
DENSE_ATOMS_PER_A3 = 0.15
"""About the most atoms a molecular system packs per cubic angstrom, hydrogens included (water
has 0.1, a protein's interior about 0.13): a grid whose cells could hold more than
SORTED_IN_CELL atoms at this density is sorted by the radix sort (at the default scale a cell
holds up to 4 atoms at two cells per cutoff, 32 at one; sigma from about 4 A changes sorts)."""
GRID_SORTS = ("counting", "radix")


@wp.struct
class Cull:
    """Which atoms a grid keeps: those within `margin` of the inner side of every plane (the
    edges of an image band's rays), and those in cells `mark_kernel` marked. `planes` 0 keeps
    every atom. A dropped atom goes to the key `capacity`, after every cell."""

    planes: int
    top: wp.vec4  # (normal, offset): kept where dot(normal, p) + offset >= -margin
    bottom: wp.vec4
    margin: float


def keep_all() -> Cull:
    c = Cull()
    c.planes = 0
    c.top = wp.vec4(0.0, 0.0, 0.0, 0.0)
    c.bottom = wp.vec4(0.0, 0.0, 0.0, 0.0)
    c.margin = 0.0
    return c


@wp.func
@no_type_check
def kept(cull: Cull, marks: wp.array[wp.int32], c: int, p: wp.vec3) -> bool:
    out = True
    if cull.planes != 0 and marks[c] == 0:
        t = wp.dot(wp.vec3(cull.top[0], cull.top[1], cull.top[2]), p) + cull.top[3]
        b = wp.dot(wp.vec3(cull.bottom[0], cull.bottom[1], cull.bottom[2]), p) + cull.bottom[3]
        out = t >= -cull.margin and b >= -cull.margin
    return out


@wp.kernel
@no_type_check
def mark_kernel(
    positions: wp.array[wp.vec3], stride: int, info: wp.array[GridInfo], marks: wp.array[wp.int32]
):
    """Mark the cells that meet the reach sphere of every `stride`-th atom (the atoms the mean
    density of relative levels is taken at): a culled grid keeps their neighbours, so every
    device finds the same mean density."""
    k = wp.tid()
    g = info[0]
    if g.valid == 0:
        return
    p = positions[k * stride]
    q = (p - g.origin) * g.inv_h
    r = int(wp.ceil(g.reach * g.inv_h))
    r2 = g.reach * g.reach
    cx = wp.clamp(int(wp.floor(q[0])), 0, g.dims[0] - 1)
    cy = wp.clamp(int(wp.floor(q[1])), 0, g.dims[1] - 1)
    cz = wp.clamp(int(wp.floor(q[2])), 0, g.dims[2] - 1)
    for z in range(wp.max(cz - r, 0), wp.min(cz + r + 1, g.dims[2])):
        dz = gap(q[2], z) * g.h
        for y in range(wp.max(cy - r, 0), wp.min(cy + r + 1, g.dims[1])):
            dy = gap(q[1], y) * g.h
            row = (z * g.dims[1] + y) * g.dims[0]
            for x in range(wp.max(cx - r, 0), wp.min(cx + r + 1, g.dims[0])):
                dx = gap(q[0], x) * g.h
                if dx * dx + dy * dy + dz * dz <= r2:
                    marks[row + x] = 1


@wp.func
@no_type_check
def gap(q: float, i: int) -> float:
    """Distance (in cells) from grid coordinate q to cell i along one axis."""
    return wp.max(wp.max(float(i) - q, q - float(i + 1)), 0.0)


def cell_capacity(n_atoms: int) -> int:
    """Most cells a grid for `n_atoms` may use: bounds device memory at 8 bytes per cell (12
    for a grid with more cells than twice its atoms, which lists the cells it walks apart)."""
    return max(int(CELLS_PER_ATOM * n_atoms), MIN_CELLS)


CELL_THREADS = 1 << 24
"""Most threads a per-cell kernel launches; each strides over the cells (or listed cells)
beyond them. The host never learns a frame's cell count, and a sparse box can use a third
of the cells it could have: a thread per possible cell then mostly starts only to return."""


def cell_threads(capacity: int) -> int:
    """Threads of a kernel over up to `capacity` cells (`CELL_THREADS`)."""
    return max(min(capacity, CELL_THREADS), 1)


def brick_capacity(cells: int) -> int:
    """Bricks allocated for a grid of `cells` cells (4x headroom over cells / 64 for thin
    boxes; a grid needing more simply walks cells only)."""
    return cells // 16 + 1024


@wp.kernel
@no_type_check
def bbox_kernel(
    positions: wp.array[wp.vec3],
    n: int,
    stride: int,
    bmin: wp.array[float],
    bmax: wp.array[float],
    bad: wp.array[wp.int32],
):
    """Strided min/max per thread, reduced over the block, then one atomic per axis and block:
    enough threads to keep the memory busy, few atomics, exact result. A non-finite coordinate
    flags the frame (it then draws background only), as does one past `MAX_COORDINATE_A`."""
    t = wp.tid()
    lo = wp.vec3(wp.inf, wp.inf, wp.inf)
    hi = wp.vec3(-wp.inf, -wp.inf, -wp.inf)
    finite = wp.int32(1)
    i = t
    while i < n:
        p = positions[i]
        # NaN fails every comparison, so this also refuses NaN and Inf
        if not (wp.abs(p[0]) <= FAR and wp.abs(p[1]) <= FAR and wp.abs(p[2]) <= FAR):
            finite = 0
        lo = wp.min(lo, p)
        hi = wp.max(hi, p)
        i += stride
    all_finite = wp.tile_min(wp.tile(finite))[0]
    lo = wp.vec3(
        wp.tile_min(wp.tile(lo[0]))[0],
        wp.tile_min(wp.tile(lo[1]))[0],
        wp.tile_min(wp.tile(lo[2]))[0],
    )
    hi = wp.vec3(
        wp.tile_max(wp.tile(hi[0]))[0],
        wp.tile_max(wp.tile(hi[1]))[0],
        wp.tile_max(wp.tile(hi[2]))[0],
    )
    if t % wp.block_dim() == 0:
        if all_finite == 0:
            wp.atomic_max(bad, 0, 1)
        if lo[0] <= hi[0]:
            for k in range(3):
                wp.atomic_min(bmin, k, lo[k])
                wp.atomic_max(bmax, k, hi[k])


@wp.kernel
@no_type_check
def setup_kernel(
    bmin: wp.array[float],
    bmax: wp.array[float],
    reach: float,
    cells_per_reach: float,
    capacity: int,
    brick_capacity: int,
    bad: wp.array[wp.int32],
    info: wp.array[GridInfo],
):
    """Lay the grid over the atoms plus `reach` on every side, so the density is zero on and
    outside its box; the cell size is reach / cells_per_reach unless that needs more cells
    than `capacity`. Resets the min/max accumulators for the next frame."""
    lo = wp.vec3(bmin[0], bmin[1], bmin[2])
    hi = wp.vec3(bmax[0], bmax[1], bmax[2])
    for k in range(3):
        bmin[k] = wp.inf
        bmax[k] = -wp.inf
    finite = bad[0] == 0
    bad[0] = 0
    g = GridInfo()
    g.valid = 0
    # an invalid grid is one cell that every atom falls in: the keys, counts and sort of the
    # frame (which draws background) stay in bounds
    g.dims = wp.vec3i(1, 1, 1)
    g.ncells = 1
    if finite and lo[0] <= hi[0] and lo[1] <= hi[1] and lo[2] <= hi[2]:
        amax = wp.max(wp.max(wp.abs(lo[0]), wp.abs(hi[0])), wp.max(wp.abs(lo[1]), wp.abs(hi[1])))
        amax = wp.max(amax, wp.max(wp.abs(lo[2]), wp.abs(hi[2])))
        # float32 rounding of positions and cell coordinates must never lose a neighbour
        r = reach * (1.0 + 1.0e-4) + amax * 4.0e-7 + 1.0e-6
        h = r / cells_per_reach
        origin = lo - wp.vec3(r, r, r)
        ext = hi - lo + wp.vec3(2.0 * r, 2.0 * r, 2.0 * r)
        nx = wp.float32(1.0)
        ny = wp.float32(1.0)
        nz = wp.float32(1.0)
        for _it in range(200):
            nx = wp.floor(ext[0] / h) + 1.0
            ny = wp.floor(ext[1] / h) + 1.0
            nz = wp.floor(ext[2] / h) + 1.0
            if nx * ny * nz <= float(capacity):
                break
            h = h * 1.1
        g.origin = origin
        g.h = h
        g.inv_h = 1.0 / h
        g.dims = wp.vec3i(int(nx), int(ny), int(nz))
        g.ncells = int(nx) * int(ny) * int(nz)
        g.box_hi = origin + wp.vec3(nx * h, ny * h, nz * h)
        g.reach = r
        g.valid = 1
        bx = (int(nx) + BRICK - 1) // BRICK
        by = (int(ny) + BRICK - 1) // BRICK
        bz = (int(nz) + BRICK - 1) // BRICK
        g.bdims = wp.vec3i(bx, by, bz)
        g.bricks = 0
        if bx * by * bz <= brick_capacity:
            g.bricks = 1
    info[0] = g


@wp.kernel
@no_type_check
def keys_kernel(
    positions: wp.array[wp.vec3],
    info: wp.array[GridInfo],
    cull: Cull,
    marks: wp.array[wp.int32],
    dropped: int,
    keys: wp.array[wp.int32],
    values: wp.array[wp.int32],
    counts: wp.array[wp.int32],
):
    """Cell of each atom (x fastest), its index as the sort value, and integer cell counts
    (integer atomics, so the counts and everything after them are deterministic). Apart from
    `ranked_keys_kernel` because an atomic add whose result is unused is faster on the device
    (one H200, 100M atoms: 1.24 ms against 1.50)."""
    i = wp.tid()
    p = positions[i]
    c = cell_at(info[0], p)
    k = dropped
    if kept(cull, marks, c, p):  # a dropped atom needs no count (and its atomics would queue)
        k = c
        wp.atomic_add(counts, c, 1)
    keys[i] = k
    values[i] = i


@wp.kernel
@no_type_check
def ranked_keys_kernel(
    positions: wp.array[wp.vec3],
    info: wp.array[GridInfo],
    cull: Cull,
    marks: wp.array[wp.int32],
    dropped: int,
    keys: wp.array[wp.int32],
    ranks: wp.array[wp.int32],
    counts: wp.array[wp.int32],
):
    """Cell of each atom and its rank among the atoms of that cell the device ran before it."""
    i = wp.tid()
    p = positions[i]
    c = cell_at(info[0], p)
    k = dropped
    r = wp.int32(-1)
    if kept(cull, marks, c, p):  # a dropped atom takes no slot (and its atomics would queue)
        k = c
        r = wp.atomic_add(counts, c, 1)
    keys[i] = k
    ranks[i] = r


@wp.kernel
@no_type_check
def place_kernel(
    keys: wp.array[wp.int32],
    ranks: wp.array[wp.int32],
    cell_start: wp.array[wp.int32],
    placed: wp.array[wp.int32],
):
    """Each kept atom into its slot: its cell's first slot plus its rank there."""
    i = wp.tid()
    if ranks[i] >= 0:
        placed[cell_start[keys[i]] + ranks[i]] = i


@wp.kernel
@no_type_check
def order_cells_kernel(
    keys: wp.array[wp.int32],
    cell_start: wp.array[wp.int32],
    placed: wp.array[wp.int32],
    dropped: int,
    order: wp.array[wp.int32],
):
    """`placed` with each cell's atoms in index order, in `order`: the atom in slot j moves
    to its cell's first slot plus the number of the cell's atoms with a smaller index. One
    thread per slot, reading its cell's slots (the same ones as its neighbours, from cache);
    a cell of more than SORTED_IN_CELL atoms is copied as it is."""
    j = wp.tid()
    if j >= cell_start[dropped]:  # the slots after the kept atoms: no cell reads them
        return
    i = placed[j]
    c = keys[i]
    a = cell_start[c]
    b = cell_start[c + 1]
    if b - a > SORTED_IN_CELL:
        order[j] = i
        return
    before = wp.int32(0)
    for k in range(a, b):
        if placed[k] < i:
            before += 1
    order[a + before] = i


@wp.kernel
@no_type_check
def brick_kernel(
    info: wp.array[GridInfo], cell_bound: wp.array[float], brick_bound: wp.array[float]
):
    """Largest cell bound of each brick: a ray skips a whole brick when even that is low."""
    b = wp.tid()
    g = info[0]
    if g.valid == 0 or g.bricks == 0:
        return
    nb = g.bdims[0] * g.bdims[1] * g.bdims[2]
    if b >= nb:
        return
    bx = (b % g.bdims[0]) * BRICK
    by = ((b // g.bdims[0]) % g.bdims[1]) * BRICK
    bz = (b // (g.bdims[0] * g.bdims[1])) * BRICK
    m = wp.float32(0.0)
    for z in range(bz, wp.min(bz + BRICK, g.dims[2])):
        for y in range(by, wp.min(by + BRICK, g.dims[1])):
            row = (z * g.dims[1] + y) * g.dims[0]
            for x in range(bx, wp.min(bx + BRICK, g.dims[0])):
                m = wp.max(m, cell_bound[row + x])
    brick_bound[b] = m


@wp.kernel
@no_type_check
def cell_weight_kernel(
    info: wp.array[GridInfo],
    threads: int,
    cell_start: wp.array[wp.int32],
    atoms: wp.array[wp.vec4],
    out: wp.array[float],
):
    """The summed weight of each cell's atoms (sorted atoms, weight in w); `threads` threads
    stride over the cells."""
    c = wp.tid()
    g = info[0]
    if g.valid == 0:
        return
    while c < g.ncells:
        s = float(0.0)
        for j in range(cell_start[c], cell_start[c + 1]):
            s += atoms[j][3]
        out[c] = s
        c += threads


@wp.kernel
@no_type_check
def spread_kernel(
    info: wp.array[GridInfo],
    threads: int,
    axis: int,
    inv2s2: float,
    scale: float,
    src: wp.array[float],
    dst: wp.array[float],
):
    """One axis of the separable cell-pair bound: dst[c] = scale * sum over the cells c + k e
    within reach of exp(-inv2s2 gap(k)^2) src[c + k e], gap(k) = (|k| - 1) h the least distance
    between the two cells along the axis; `threads` threads stride over the cells."""
    c = wp.tid()
    g = info[0]
    if g.valid == 0:
        return
    reach = int(wp.ceil(g.reach * g.inv_h))
    n = g.dims[axis]
    stride = 1
    if axis == 1:
        stride = g.dims[0]
    elif axis == 2:
        stride = g.dims[0] * g.dims[1]
    while c < g.ncells:
        # the cell's index along the axis (no more integer divisions than the axis needs)
        i = wp.int32(0)
        if axis == 0:
            i = c % n
        elif axis == 1:
            i = (c // stride) % n
        else:
            i = c // stride
        s = float(0.0)
        for k in range(-reach, reach + 1):
            j = i + k
            if j >= 0 and j < n:
                gap = float(wp.max(wp.abs(k) - 1, 0)) * g.h
                s += wp.exp(-inv2s2 * gap * gap) * src[c + k * stride]
        dst[c] = s * scale
        c += threads


def _view(base: wp.array, offset: int, dtype: Any, length: int) -> wp.array:
    """`length` 4-byte items of `base` from item `offset` on, as `dtype`: buffers the build
    is done with hold later stages' data, so the grid stays within its bytes per atom."""
    return wp.array(
        ptr=base.ptr + 4 * offset, dtype=dtype, shape=(length,), device=base.device, copy=False
    )


class CellGrid:
    """Device buffers of the grid for up to `n_atoms` atoms, reused every frame.

    `cell_values` (float, capacity + 1) is scratch that the counts use during the build and
    the caller may fill with per-cell data afterwards (the density bound): sharing it keeps
    the grid at 8 bytes per cell (and 4 more for the list of cells the bound walks when the
    grid has more than twice as many cells as atoms).
    """

    def __init__(
        self, device: str, n_atoms: int, sort: str = "counting", *, cell_list: bool = True
    ):
        if sort not in GRID_SORTS:
            raise ValueError(f"grid sort must be one of {', '.join(GRID_SORTS)}, got {sort!r}")
        self.device = device
        self.sort = sort
        self.n_atoms = int(n_atoms)
        self.capacity = cell_capacity(self.n_atoms)
        n2 = max(2 * self.n_atoms, 2)
        # the sort's keys are free once it is done: they hold the coarse cell bound after it
        self.keys = wp.zeros(max(n2, self.capacity + 1), dtype=wp.int32, device=device)
        self.order = wp.zeros(n2, dtype=wp.int32, device=device)
        self.cell_start = wp.zeros(self.capacity + 1, dtype=wp.int32, device=device)
        self.cell_values = wp.zeros(self.capacity + 1, dtype=float, device=device)
        self.brick_capacity = brick_capacity(self.capacity)
        self.brick_values = wp.zeros(self.brick_capacity, dtype=float, device=device)
        self._counts = _view(self.cell_values, 0, wp.int32, self.capacity + 1)
        # the second half of the sort's values is free once it is done: the cells the bound
        # walks are listed there; a small molecule's grid has more cells than atoms, and the
        # cells a full list leaves out are walked one thread each, out of step: such a grid
        # lists its cells in a buffer of its own (128 KB at the least capacity)
        self._own_work: wp.array | None = None
        if self.n_atoms >= self.capacity // 2 or not cell_list:
            self.work = _view(self.order, self.n_atoms, wp.int32, self.n_atoms)
        else:
            self.work = self._own_work = wp.zeros(self.capacity, dtype=wp.int32, device=device)
        self.work_count = wp.zeros(1, dtype=wp.int32, device=device)
        # the counting sort's ranks: the second half of the keys (no double buffer to keep)
        self._ranks = _view(self.keys, self.n_atoms, wp.int32, max(self.n_atoms, 1))
        self.coarse = _view(self.keys, 0, float, self.capacity + 1)
        # and once the coarse bounds are read, which parts of each cell are below the level
        self.parts = _view(self.keys, 0, wp.int32, self.capacity + 1)
        self.bmin = wp.full(3, wp.inf, dtype=float, device=device)
        self.bmax = wp.full(3, -wp.inf, dtype=float, device=device)
        self.bad = wp.zeros(1, dtype=wp.int32, device=device)
        self.info = wp.zeros(1, dtype=GridInfo, device=device)
        self._end_bit = max(int(self.capacity).bit_length(), 1)
        self._keep_all = keep_all()

    @property
    def nbytes(self) -> int:
        arrays = (
            self.keys,
            self.order,
            self.cell_start,
            self.cell_values,
            self.brick_values,
            self.bmin,
            self.bmax,
            *(() if self._own_work is None else (self._own_work,)),
        )
        return sum(int(a.capacity) for a in arrays) + 64

    def invalidate(self) -> None:
        """Mark the grid empty (no atoms): rays then see only background."""
        self.info.zero_()

    def build(
        self,
        positions: wp.array,
        n: int,
        reach: float,
        cells_per_reach: float,
        cull: Cull | None = None,
        sample_stride: int = 0,
    ) -> None:
        """Rebuild for the first `n` positions; all launches are asynchronous. With `cull`, the
        grid is laid over every atom as without it (the same cells, each atom in the same cell
        and order), but keeps only the atoms `cull` keeps, and with `sample_stride` > 0 those
        within reach of every `sample_stride`-th atom; the others sort after every cell."""
        if n <= 0:
            self.invalidate()
            return
        dev = self.device
        threads = min(-(-max(n // 8, 1) // REDUCE_BLOCK) * REDUCE_BLOCK, MAX_REDUCE_THREADS)
        wp.launch(
            bbox_kernel,
            threads,
            (positions, n, threads, self.bmin, self.bmax, self.bad),
            device=dev,
            block_dim=REDUCE_BLOCK,
        )
        wp.launch(
            setup_kernel,
            1,
            (
                self.bmin,
                self.bmax,
                float(reach),
                float(cells_per_reach),
                self.capacity,
                self.brick_capacity,
                self.bad,
                self.info,
            ),
            device=dev,
        )
        self._counts.zero_()
        # the marks live in `cell_start` until the scan writes it
        marks = self.cell_start
        if cull is None:
            cull = self._keep_all
        else:
            marks.zero_()
            if sample_stride > 0:
                samples = min(n, max(n // sample_stride, 1))
                args = (positions, sample_stride, self.info, marks)
                wp.launch(mark_kernel, samples, args, device=dev)
        sort = (self.info, cull, marks, self.capacity)
        edge = reach / cells_per_reach
        if self.sort == "radix" or edge**3 * DENSE_ATOMS_PER_A3 > SORTED_IN_CELL:
            keyed = (positions, *sort, self.keys, self.order, self._counts)
            wp.launch(keys_kernel, n, keyed, device=dev)
            wp.utils.radix_sort_pairs(self.keys, self.order, n, 0, self._end_bit)
            wp.utils.array_scan(self._counts, self.cell_start, inclusive=False)
            return
        ranked = (positions, *sort, self.keys, self._ranks, self._counts)
        wp.launch(ranked_keys_kernel, n, ranked, device=dev)
        wp.utils.array_scan(self._counts, self.cell_start, inclusive=False)
        # atoms are placed in the second half of `order` (free until the cell bounds list
        # their cells there), then moved into index order within their cells
        placed = (self.keys, self._ranks, self.cell_start, self.work)
        wp.launch(place_kernel, n, placed, device=dev)
        ordered = (self.keys, self.cell_start, self.work, self.capacity, self.order)
        wp.launch(order_cells_kernel, n, ordered, device=dev)

    @property
    def lists_own_cells(self) -> bool:
        """The cells the bound walks are listed in a buffer of the grid's own (a small
        molecule's grid: more cells than twice its atoms)."""
        return self._own_work is not None

    def build_coarse(self, atoms: wp.array, inv2s2: float) -> None:
        """`coarse`: per cell, an upper bound of the Gaussian density of the sorted `atoms`
        anywhere in it, from the summed weights of the cells within reach, each counted at the
        least distance between the two cells (separable in the axes: three short passes, no
        walk over atoms). `inv2s2` is that of the widest atom; a 1e-3 margin keeps it above
        the walked bound in float32. The cells' values pass through `cell_values`."""
        dev = self.device
        threads = cell_threads(self.capacity)
        wp.launch(
            cell_weight_kernel,
            threads,
            (self.info, threads, self.cell_start, atoms, self.cell_values),
            device=dev,
        )
        spread = (self.cell_values, self.coarse, self.cell_values, self.coarse)
        for axis in range(3):
            scale = 1.0 + 1.0e-3 if axis == 2 else 1.0
            cells = (spread[axis], spread[axis + 1])
            args = (self.info, threads, axis, float(inv2s2), scale, *cells)
            wp.launch(spread_kernel, threads, args, device=dev)

    def build_bricks(self) -> None:
        """Brick maxima of `cell_values`, once the caller has filled the cell bounds."""
        args = (self.info, self.cell_values, self.brick_values)
        wp.launch(brick_kernel, self.brick_capacity, args, device=self.device)

    def read_info(self) -> dict[str, object]:
        """The grid layout on the host (synchronises; for tests and reports)."""
        g = self.info.numpy()[0]
        return {name: g[name] for name in g.dtype.names} if g.dtype.names else {"raw": g}
