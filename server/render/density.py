"""The multiscale Gaussian molecular density as warp functions the ray caster calls.

    S(P) = sum_i w_i K(|P - a_i|^2 / (2 s_i^2)),   K(e) = exp(-e) (1 - (e / ek)^16)^2,
    only atoms with |P - a_i| < k s_i (e < ek = k^2 / 2)

`s_i` is sigma (uniform mode) or sigma * r_i / R_REF (vdw mode); k is the reach at that sigma
(reach.py), at most `cutoff_sigmas` (default 4). The taper brings each atom's Gaussian to zero
with zero slope at the cutoff, so S is smooth where atoms enter reach (a hard cut leaves a step
of w exp(-ek) there). Each atom's K differs from its Gaussian by at most c_k w exp(-k^2 / 2),
c_k = max over e in [0, ek] of exp(ek - e) (1 - (1 - (e / ek)^16)^2), reached just inside the
cutoff: 1.023 at k = 3, 1.063 at 3.75, 1.086 at 4 (0.036 % of the peak), 2.13 at 6. K leaves out
part of the Gaussian's mass w (2 pi s^2)^(3/2): the tail beyond the cutoff, P(chi_3 > k), and
what the taper takes inside it; together 0.25 % at k = 4 (0.11 % + 0.14 %), 0.55 % at 3.75
(0.28 % + 0.27 %), 4.3 % at 3 (2.9 % + 1.4 %). Where atoms overlap fully S is low by that share,
a uniform loss the relative level (level_scale="mean") divides out (docs/rendering.md;
tests/render/test_density.py holds the device kernel to these numbers).

A density is a `DensityModel`: a field struct plus four functions with fixed signatures. The
ray caster (raycast.py) is generated from a model, so another density (the geodesic one,
geodesic_field.py, or the carved one, carved.py) plugs in by providing its own struct and
functions; the struct must carry `info` (GridInfo, one entry), `bound` (one float per cell),
`parts` (one word per cell) and `brick_bound` (one per brick) because the caster walks bricks,
cells and parts of cells to skip empty space.
(No `from __future__ import annotations`: `cell_rows` makes functions whose annotations name
its arguments, which warp resolves eagerly.)
"""

from dataclasses import dataclass
from typing import Any, no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import PART_SLACK, PARTS, GridInfo, axis_span, interval_gap, row_span

wp.set_module_options({"enable_backward": False})


@wp.struct
class GaussianField:
    """Device view of the sorted atoms and the cell grid, passed by value to kernels."""

    atoms: wp.array[wp.vec4]  # sorted by cell: (x, y, z, weight)
    inv2s2: wp.array[float]  # sorted, 1 / (2 s_i^2); read only when per_atom != 0
    order: wp.array[wp.int32]  # sorted slot -> original atom index
    colors: wp.array[wp.uint32]  # original atom index -> RGBA8
    cell_start: wp.array[wp.int32]  # ncells + 1 offsets into atoms
    bound: wp.array[float]  # per cell: upper bound of S in the cell (or > stop level)
    parts: wp.array[wp.int32]  # per cell: bit s set when part s has a bound below the level
    brick_bound: wp.array[float]  # per brick of BRICK^3 cells: the largest cell bound
    info: wp.array[GridInfo]  # one entry
    inv2s2_uniform: float
    half_k2: float  # an atom counts while d^2 / (2 s^2) < k^2 / 2
    inv_half_k2: float
    per_atom: int


@wp.struct
class Sample:
    """Everything shading needs at one point, gathered in one pass over the neighbours."""

    value: float
    grad: wp.vec3
    color: wp.vec3
    weight: float
    atom: int


@wp.func
@no_type_check
def empty_sample() -> Sample:
    """A sample before any term: nothing summed, no contributor (weight -1, atom -1)."""
    s = Sample()
    s.value = 0.0
    s.grad = wp.vec3(0.0, 0.0, 0.0)
    s.color = wp.vec3(0.0, 0.0, 0.0)
    s.weight = -1.0
    s.atom = -1
    return s


@wp.func
@no_type_check
def unpack_rgb(c: wp.uint32) -> wp.vec3:
    r = float(c & wp.uint32(255))
    g = float((c >> wp.uint32(8)) & wp.uint32(255))
    b = float((c >> wp.uint32(16)) & wp.uint32(255))
    return wp.vec3(r, g, b) * (1.0 / 255.0)


@wp.func
@no_type_check
def atom_exponent(f: GaussianField, j: int, a: wp.vec4, p: wp.vec3) -> float:
    """d^2 / (2 s_j^2) for sorted atom j."""
    ex = a[0] - p[0]
    ey = a[1] - p[1]
    ez = a[2] - p[2]
    c = f.inv2s2_uniform
    if f.per_atom != 0:
        c = f.inv2s2[j]
    return (ex * ex + ey * ey + ez * ez) * c


@wp.func
@no_type_check
def dist2(a: wp.vec4, p: wp.vec3) -> float:
    ex = a[0] - p[0]
    ey = a[1] - p[1]
    ez = a[2] - p[2]
    return ex * ex + ey * ey + ez * ez


@wp.struct
class Span4:
    """Four points o + d ts[q] along a line (ts increasing), and the squared radius around
    their middle beyond which an atom reaches none of them (uniform mode)."""

    o: wp.vec3
    d: wp.vec3
    ts: wp.vec4
    lim2: float


@wp.struct
class BoxQuery:
    lo: wp.vec3
    hi: wp.vec3
    stop_above: float


def cell_rows(
    name: str, row: Any, query: Any, acc: Any, stop: Any = None, field: Any = None
) -> Any:
    """The neighbour walk every density evaluation shares, made for one row function.

    Returns `walk(f, lo, hi, q, acc) -> acc`: for every row of cells (along x) within the
    cutoff reach of the box [lo, hi], trimmed to the chord of the reach around the box
    (`row_span`), the row's items are one contiguous range [j0, j1) of the sorted items, and
    `acc = row(f, q, j0, j1, acc)`. `stop(q, acc) -> bool`, when given, ends the walk early.
    `query` and `acc` are the warp types of `q` and `acc`; `field` is the struct walked (any
    with `info` and `cell_start`; GaussianField by default)."""
    Query = query
    Acc = acc
    Field = GaussianField if field is None else field
    done = stop
    if done is None:

        @no_type_check
        def never(q: Query, total: Acc) -> bool:
            return False

        done = wp.func(name=f"never_{name}")(never)

    @no_type_check
    def walk(f: Field, lo: wp.vec3, hi: wp.vec3, q: Query, total: Acc) -> Acc:
        g = f.info[0]
        r = g.reach
        r2 = r * r
        z0, z1 = axis_span(lo[2] - r, hi[2] + r, g.origin[2], g.inv_h, g.dims[2])
        y0, y1 = axis_span(lo[1] - r, hi[1] + r, g.origin[1], g.inv_h, g.dims[1])
        out = total
        for iz in range(z0, z1 + 1):
            zlo = g.origin[2] + float(iz) * g.h
            dz = interval_gap(lo[2], hi[2], zlo, zlo + g.h)
            for iy in range(y0, y1 + 1):
                ylo = g.origin[1] + float(iy) * g.h
                dy = interval_gap(lo[1], hi[1], ylo, ylo + g.h)
                x0, x1 = row_span(g, lo[0], hi[0], dy, dz, r2)
                if x1 >= x0:
                    cells = (iz * g.dims[1] + iy) * g.dims[0]
                    j0 = f.cell_start[cells + x0]
                    j1 = f.cell_start[cells + x1 + 1]
                    if j1 > j0:
                        out = row(f, q, j0, j1, out)
                        if done(q, out):
                            return out
        return out

    return wp.func(name=f"walk_{name}")(walk)


TAPER_POWER = 16
"""Each atom's Gaussian is multiplied by (1 - (e / ek)^16)^2, e = d^2 / 2 s^2, ek = k^2 / 2:
it reaches zero with zero slope at the cutoff, so the summed density has no step or crease
where an atom enters reach; inside, the factor differs from 1 by less than 2 (e / ek)^16."""


@wp.func
@no_type_check
def taper(u: float) -> wp.vec2:
    """(w, dw/du) of w(u) = (1 - u^16)^2 for u = e / ek in [0, 1)."""
    u2 = u * u
    u4 = u2 * u2
    u8 = u4 * u4
    u16 = u8 * u8
    m = 1.0 - u16
    return wp.vec2(m * m, -32.0 * m * u8 * u4 * u2 * u)


@wp.func
@no_type_check
def kernel(e: float, inv_ek: float) -> float:
    """One atom's tapered Gaussian exp(-e) w(e / ek) (inside the cutoff; inv_ek 0: untapered,
    the renderer's baseline for the taper's cost)."""
    out = wp.exp(-e)
    if inv_ek > 0.0:
        u = e * inv_ek
        u2 = u * u
        u4 = u2 * u2
        u8 = u4 * u4
        m = 1.0 - u8 * u8
        out = out * m * m
    return out


@wp.func
@no_type_check
def kernel_slope(e: float, inv_ek: float) -> wp.vec2:
    """(K, -dK/de) of K(e) = exp(-e) w(e / ek): the gradient of an atom's term at P is
    -dK/de * 2 c (a - P)."""
    x = wp.exp(-e)
    out = wp.vec2(x, x)
    if inv_ek > 0.0:
        t = taper(e * inv_ek)
        out = wp.vec2(x * t[0], x * (t[0] - t[1] * inv_ek))
    return out


@wp.func
@no_type_check
def row_value(f: GaussianField, p: wp.vec3, j0: int, j1: int, total: float) -> float:
    """Sum over sorted atoms [j0, j1); the uniform/per-atom choice is made once per row."""
    s = total
    if f.per_atom == 0:
        c = f.inv2s2_uniform
        for j in range(j0, j1):
            a = f.atoms[j]
            e = dist2(a, p) * c
            if e < f.half_k2:
                s += a[3] * kernel(e, f.inv_half_k2)
    else:
        for j in range(j0, j1):
            a = f.atoms[j]
            e = dist2(a, p) * f.inv2s2[j]
            if e < f.half_k2:
                s += a[3] * kernel(e, f.inv_half_k2)
    return s


@wp.func
@no_type_check
def row_value_grad(f: GaussianField, p: wp.vec3, j0: int, j1: int, acc: wp.vec4) -> wp.vec4:
    """(gradient, value) over sorted atoms [j0, j1), added to acc."""
    s = acc[3]
    g = wp.vec3(acc[0], acc[1], acc[2])
    if f.per_atom == 0:
        c = f.inv2s2_uniform
        for j in range(j0, j1):
            a = f.atoms[j]
            e = dist2(a, p) * c
            if e < f.half_k2:
                k = kernel_slope(e, f.inv_half_k2) * a[3]
                s += k[0]
                g += (wp.vec3(a[0], a[1], a[2]) - p) * (2.0 * c * k[1])
    else:
        for j in range(j0, j1):
            a = f.atoms[j]
            cj = f.inv2s2[j]
            e = dist2(a, p) * cj
            if e < f.half_k2:
                k = kernel_slope(e, f.inv_half_k2) * a[3]
                s += k[0]
                g += (wp.vec3(a[0], a[1], a[2]) - p) * (2.0 * cj * k[1])
    return wp.vec4(g[0], g[1], g[2], s)


@wp.func
@no_type_check
def add_values4(
    v: wp.vec4,
    a: wp.vec4,
    c: float,
    half_k2: float,
    inv_half_k2: float,
    p0: wp.vec3,
    p1: wp.vec3,
    p2: wp.vec3,
    p3: wp.vec3,
) -> wp.vec4:
    """v plus one atom's terms at the four points (each only within the cutoff)."""
    pa = wp.vec3(a[0], a[1], a[2])
    e0 = wp.length_sq(pa - p0) * c
    e1 = wp.length_sq(pa - p1) * c
    e2 = wp.length_sq(pa - p2) * c
    e3 = wp.length_sq(pa - p3) * c
    out = v
    if e0 < half_k2:
        out[0] = out[0] + a[3] * kernel(e0, inv_half_k2)
    if e1 < half_k2:
        out[1] = out[1] + a[3] * kernel(e1, inv_half_k2)
    if e2 < half_k2:
        out[2] = out[2] + a[3] * kernel(e2, inv_half_k2)
    if e3 < half_k2:
        out[3] = out[3] + a[3] * kernel(e3, inv_half_k2)
    return out


@wp.func
@no_type_check
def row_values4(f: GaussianField, q: Span4, j0: int, j1: int, total: wp.vec4) -> wp.vec4:
    """S at the four points of `q` from sorted atoms [j0, j1): one load per atom serves all
    four. Atoms are taken two at a time so two loads are in flight (the loop is bound by
    their latency). In uniform mode an atom with |a - mid|^2 >= lim2 (beyond the cutoff of
    every point) is rejected with one distance."""
    v = total
    p0 = q.o + q.d * q.ts[0]
    p1 = q.o + q.d * q.ts[1]
    p2 = q.o + q.d * q.ts[2]
    p3 = q.o + q.d * q.ts[3]
    mid = (p0 + p3) * 0.5
    lim2 = q.lim2
    c = f.inv2s2_uniform
    hk = f.half_k2
    ik = f.inv_half_k2
    j = j0
    while j + 1 < j1:
        a = f.atoms[j]
        b = f.atoms[j + 1]
        if f.per_atom != 0:
            v = add_values4(v, a, f.inv2s2[j], hk, ik, p0, p1, p2, p3)
            v = add_values4(v, b, f.inv2s2[j + 1], hk, ik, p0, p1, p2, p3)
        else:
            if wp.length_sq(wp.vec3(a[0], a[1], a[2]) - mid) < lim2:
                v = add_values4(v, a, c, hk, ik, p0, p1, p2, p3)
            if wp.length_sq(wp.vec3(b[0], b[1], b[2]) - mid) < lim2:
                v = add_values4(v, b, c, hk, ik, p0, p1, p2, p3)
        j += 2
    if j < j1:
        a = f.atoms[j]
        if f.per_atom != 0:
            c = f.inv2s2[j]
        v = add_values4(v, a, c, hk, ik, p0, p1, p2, p3)
    return v


@wp.func
@no_type_check
def atom_term(
    a: wp.vec4, pa: wp.vec3, p: wp.vec3, c: float, half_k2: float, inv_half_k2: float
) -> wp.vec4:
    """(gradient, value) of one atom at p; zero beyond the cutoff."""
    u = pa - p
    e = wp.length_sq(u) * c
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if e < half_k2:
        k = kernel_slope(e, inv_half_k2) * a[3]
        g = u * (2.0 * c * k[1])
        out = wp.vec4(g[0], g[1], g[2], k[0])
    return out


@wp.func
@no_type_check
def row_value_grad4(f: GaussianField, q: Span4, j0: int, j1: int, acc: wp.mat44) -> wp.mat44:
    """(gradient, value) at the four points of `q` (rows of acc) from sorted atoms [j0, j1),
    with the same uniform-mode rejection as `row_values4`."""
    a0 = acc[0]
    a1 = acc[1]
    a2 = acc[2]
    a3 = acc[3]
    p0 = q.o + q.d * q.ts[0]
    p1 = q.o + q.d * q.ts[1]
    p2 = q.o + q.d * q.ts[2]
    p3 = q.o + q.d * q.ts[3]
    mid = (p0 + p3) * 0.5
    c = f.inv2s2_uniform
    for j in range(j0, j1):
        a = f.atoms[j]
        pa = wp.vec3(a[0], a[1], a[2])
        if f.per_atom != 0:
            c = f.inv2s2[j]
        elif wp.length_sq(pa - mid) >= q.lim2:
            continue
        a0 += atom_term(a, pa, p0, c, f.half_k2, f.inv_half_k2)
        a1 += atom_term(a, pa, p1, c, f.half_k2, f.inv_half_k2)
        a2 += atom_term(a, pa, p2, c, f.half_k2, f.inv_half_k2)
        a3 += atom_term(a, pa, p3, c, f.half_k2, f.inv_half_k2)
    return wp.matrix_from_rows(a0, a1, a2, a3)


@wp.func
@no_type_check
def row_sample(f: GaussianField, p: wp.vec3, j0: int, j1: int, acc: Sample) -> Sample:
    """Value, gradient, contribution-weighted colour and largest contributor over sorted atoms
    [j0, j1), added to acc (`acc.weight` holds the largest contribution so far)."""
    total = acc.value
    grad = acc.grad
    color = acc.color
    best_w = acc.weight
    best = acc.atom
    for j in range(j0, j1):
        a = f.atoms[j]
        e = atom_exponent(f, j, a, p)
        if e < f.half_k2:
            c = f.inv2s2_uniform
            if f.per_atom != 0:
                c = f.inv2s2[j]
            k = kernel_slope(e, f.inv_half_k2) * a[3]
            term = k[0]
            total += term
            grad += (wp.vec3(a[0], a[1], a[2]) - p) * (2.0 * c * k[1])
            oj = int(f.order[j])
            color += unpack_rgb(f.colors[oj]) * term
            if term > best_w or (term == best_w and oj < best):
                best_w = term
                best = oj
    s = Sample()
    s.value = total
    s.grad = grad
    s.color = color
    s.weight = best_w
    s.atom = best
    return s


@wp.func
@no_type_check
def row_bound(f: GaussianField, q: BoxQuery, j0: int, j1: int, total: float) -> float:
    """Every atom of [j0, j1) counted at its smallest distance to the box; stops adding once
    the sum exceeds `q.stop_above`."""
    s = total
    for j in range(j0, j1):
        a = f.atoms[j]
        nearest = wp.vec3(
            wp.clamp(a[0], q.lo[0], q.hi[0]),
            wp.clamp(a[1], q.lo[1], q.hi[1]),
            wp.clamp(a[2], q.lo[2], q.hi[2]),
        )
        e = atom_exponent(f, j, a, nearest)
        if e < f.half_k2:
            s += a[3] * wp.exp(-e)
            if s > q.stop_above:
                return s
    return s


@wp.func
@no_type_check
def bound_reached(q: BoxQuery, total: float) -> bool:
    return total > q.stop_above


if PARTS != 3:
    raise ImportError("the part bounds split each cell edge in three (27 bits of one word)")
PartBounds = wp.types.vector(length=PARTS**3, dtype=wp.float32)
"""Upper bounds of S over the PARTS^3 parts of a box (x fastest)."""


@wp.func
@no_type_check
def part_exponents(a: float, lo: float, w: float, c: float) -> wp.vec3:
    """c times the squared gap from coordinate a to each third [lo + i w, lo + (i + 1) w] of
    an axis, each widened by PART_SLACK w on both sides."""
    s = PART_SLACK * w
    g0 = interval_gap(a, a, lo - s, lo + w + s)
    g1 = interval_gap(a, a, lo + w - s, lo + 2.0 * w + s)
    g2 = interval_gap(a, a, lo + 2.0 * w - s, lo + 3.0 * w + s)
    return wp.vec3(g0 * g0, g1 * g1, g2 * g2) * c


@wp.func
@no_type_check
def add_part_terms(f: GaussianField, j: int, lo: wp.vec3, w: wp.vec3, total: PartBounds):
    """Sorted atom j counted at its smallest distance to each part of the box from `lo` with
    parts `w` wide: the squared distance is a sum over the axes, so an atom's 27 terms are
    products of three exponentials per axis."""
    out = total
    hk = f.half_k2
    a = f.atoms[j]
    c = f.inv2s2_uniform
    if f.per_atom != 0:
        c = f.inv2s2[j]
    ux = part_exponents(a[0], lo[0], w[0], c)
    uy = part_exponents(a[1], lo[1], w[1], c)
    uz = part_exponents(a[2], lo[2], w[2], c)
    if wp.min(ux) + wp.min(uy) + wp.min(uz) < hk:
        ex = wp.vec3(wp.exp(-ux[0]), wp.exp(-ux[1]), wp.exp(-ux[2])) * a[3]
        ey = wp.vec3(wp.exp(-uy[0]), wp.exp(-uy[1]), wp.exp(-uy[2]))
        ez = wp.vec3(wp.exp(-uz[0]), wp.exp(-uz[1]), wp.exp(-uz[2]))
        for iz in range(3):
            for iy in range(3):
                for ix in range(3):
                    if ux[ix] + uy[iy] + uz[iz] < hk:
                        s = ix + 3 * (iy + 3 * iz)
                        out[s] = out[s] + ex[ix] * ey[iy] * ez[iz]
    return out


@wp.func
@no_type_check
def row_part_bounds(
    f: GaussianField, q: BoxQuery, j0: int, j1: int, total: PartBounds
) -> PartBounds:
    """Every atom of [j0, j1) counted in each part of the box (`add_part_terms`)."""
    out = total
    w = (q.hi - q.lo) * (1.0 / 3.0)
    for j in range(j0, j1):
        out = add_part_terms(f, j, q.lo, w, out)
    return out


@wp.struct
class LaneBox:
    """A box whose part bounds `lanes` threads take together: lane `lane` counts every
    `lanes`-th atom of each row (as `LanePoint`)."""

    lo: wp.vec3
    hi: wp.vec3
    lane: int
    lanes: int


@wp.func
@no_type_check
def row_part_bounds_lane(
    f: GaussianField, q: LaneBox, j0: int, j1: int, total: PartBounds
) -> PartBounds:
    """The lane's share of `row_part_bounds`: the lanes' bounds add up to the box's."""
    out = total
    w = (q.hi - q.lo) * (1.0 / 3.0)
    j = j0 + q.lane
    while j < j1:
        out = add_part_terms(f, j, q.lo, w, out)
        j += q.lanes
    return out


@wp.func
@no_type_check
def parts_reached(q: BoxQuery, total: PartBounds) -> bool:
    return wp.min(total) > q.stop_above


_walk_value = cell_rows("value", row_value, wp.vec3, float)
_walk_value_grad = cell_rows("value_grad", row_value_grad, wp.vec3, wp.vec4)
_walk_values4 = cell_rows("values4", row_values4, Span4, wp.vec4)
_walk_value_grad4 = cell_rows("value_grad4", row_value_grad4, Span4, wp.mat44)
_walk_sample = cell_rows("sample", row_sample, wp.vec3, Sample)
_walk_bound = cell_rows("bound", row_bound, BoxQuery, float, bound_reached)
_walk_part_bounds = cell_rows("part_bounds", row_part_bounds, BoxQuery, PartBounds, parts_reached)
_walk_part_bounds_lane = cell_rows("part_bounds_lane", row_part_bounds_lane, LaneBox, PartBounds)


@wp.func
@no_type_check
def gaussian_value(f: GaussianField, p: wp.vec3) -> float:
    """S(p)."""
    return _walk_value(f, p, p, p, wp.float32(0.0))


@wp.func
@no_type_check
def gaussian_value_grad(f: GaussianField, p: wp.vec3) -> wp.vec4:
    """(dS/dx, dS/dy, dS/dz, S) at p; the gradient is analytic."""
    return _walk_value_grad(f, p, p, p, wp.vec4(0.0, 0.0, 0.0, 0.0))


@wp.func
@no_type_check
def span4(f: GaussianField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> Span4:
    q = Span4()
    q.o = o
    q.d = d
    q.ts = ts
    pa = o + d * ts[0]
    pb = o + d * ts[3]
    # reject radius around the middle: cutoff plus half the segment, with room for rounding
    lim = (wp.sqrt(f.half_k2 / f.inv2s2_uniform) + 0.5 * wp.length(pb - pa)) * 1.0001 + 1.0e-5
    q.lim2 = lim * lim
    return q


@wp.func
@no_type_check
def gaussian_value4(f: GaussianField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
    """S at the four points o + d ts[q] (ts increasing) in one pass over the neighbours of
    the segment they span: the ray caster samples four lattice steps at a time, so nearby rows
    and atoms are loaded once instead of four times. Each point's sum is the one `value`
    would give there (same atoms, same order)."""
    pa = o + d * ts[0]
    pb = o + d * ts[3]
    return _walk_values4(
        f, wp.min(pa, pb), wp.max(pa, pb), span4(f, o, d, ts), wp.vec4(0.0, 0.0, 0.0, 0.0)
    )


@wp.func
@no_type_check
def gaussian_value_grad4(f: GaussianField, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    """(gradient, value) at the four points o + d ts[q] (ts increasing) in one pass over the
    neighbours of their segment (shaded volume rendering)."""
    pa = o + d * ts[0]
    pb = o + d * ts[3]
    zero = wp.mat44(0.0)
    m = _walk_value_grad4(f, wp.min(pa, pb), wp.max(pa, pb), span4(f, o, d, ts), zero)
    return m[0], m[1], m[2], m[3]


@wp.func
@no_type_check
def gaussian_sample(f: GaussianField, p: wp.vec3) -> Sample:
    """Value, gradient, contribution-weighted colour and the largest contributor at p.

    Ties between equal contributions go to the lower original atom index, so the atom id is
    deterministic even for coincident atoms."""
    s = _walk_sample(f, p, p, p, empty_sample())
    s.weight = s.value
    return s


@wp.func
@no_type_check
def gaussian_box_bound(f: GaussianField, lo: wp.vec3, hi: wp.vec3, stop_above: float) -> float:
    """An upper bound of S over the box [lo, hi]: every atom in reach counted at its smallest
    distance to the box. Returns early once the sum exceeds `stop_above` (the caller only
    compares against that level)."""
    q = BoxQuery()
    q.lo = lo
    q.hi = hi
    q.stop_above = stop_above
    return _walk_bound(f, lo, hi, q, wp.float32(0.0))


@wp.func
@no_type_check
def gaussian_part_bounds(
    f: GaussianField, lo: wp.vec3, hi: wp.vec3, stop_above: float
) -> PartBounds:
    """Upper bounds of S over the 27 parts of the box [lo, hi] (each widened by PART_SLACK of
    its edge), as `gaussian_box_bound` per part; returns early once every part's sum exceeds
    `stop_above`."""
    q = BoxQuery()
    q.lo = lo
    q.hi = hi
    q.stop_above = stop_above
    s = (hi - lo) * (PART_SLACK / 3.0)
    return _walk_part_bounds(f, lo - s, hi + s, q, PartBounds())


@wp.func
@no_type_check
def gaussian_part_bounds_lane(
    f: GaussianField, lo: wp.vec3, hi: wp.vec3, lane: int, lanes: int
) -> PartBounds:
    """Lane `lane` of `lanes`' share of `gaussian_part_bounds` (the whole sum, no early
    return: no lane knows the others' sums); the lanes' shares add up to the bounds."""
    q = LaneBox()
    q.lo = lo
    q.hi = hi
    q.lane = lane
    q.lanes = lanes
    s = (hi - lo) * (PART_SLACK / 3.0)
    return _walk_part_bounds_lane(f, lo - s, hi + s, q, PartBounds())


@wp.struct
class UnsortedAtoms:
    """The atoms in their original order, reached through the grid (`order`): what the mean
    density is taken over before the atoms are gathered into cell order."""

    positions: wp.array[wp.vec3]
    weights: wp.array[float]
    radii: wp.array[float]
    order: wp.array[wp.int32]  # sorted slot -> original atom index
    cell_start: wp.array[wp.int32]
    info: wp.array[GridInfo]
    inv2s2_uniform: float
    sigma_per_radius: float
    half_k2: float
    inv_half_k2: float
    per_atom: int


@wp.func
@no_type_check
def inv2s2_of(sigma_per_radius: float, radius: float) -> float:
    """1 / (2 s^2) of an atom in vdw mode (s = sigma r / R_REF)."""
    s = sigma_per_radius * radius
    return 0.5 / (s * s)


@wp.func
@no_type_check
def unsorted_exponent(f: UnsortedAtoms, i: int, a: wp.vec4, p: wp.vec3) -> float:
    """d^2 / (2 s^2) of original atom i at p (a: its position and weight)."""
    c = f.inv2s2_uniform
    if f.per_atom != 0:
        c = inv2s2_of(f.sigma_per_radius, f.radii[i])
    return dist2(a, p) * c


@wp.struct
class LanePoint:
    """A point whose density `lanes` threads take together: lane `lane` sums every
    `lanes`-th atom of each row."""

    p: wp.vec3
    lane: int
    lanes: int


@wp.func
@no_type_check
def first_of_lane(q: LanePoint, j0: int) -> int:
    """The first index from j0 that is lane `q.lane` modulo `q.lanes`: a lane takes the atoms
    whose sorted index is its own, so a row of one or two atoms does not always fall to the
    first lanes."""
    return j0 + (q.lane - j0 % q.lanes + q.lanes) % q.lanes


@wp.func
@no_type_check
def row_value_lane(f: UnsortedAtoms, q: LanePoint, j0: int, j1: int, total: float) -> float:
    """The lane's share of `row_value` over sorted slots [j0, j1), each atom read through
    `order`: the lanes' sums add up to the density, in a fixed order."""
    s = total
    j = j0 + q.lane
    while j < j1:
        i = f.order[j]
        x = f.positions[i]
        a = wp.vec4(x[0], x[1], x[2], f.weights[i])
        e = unsorted_exponent(f, i, a, q.p)
        if e < f.half_k2:
            s += a[3] * kernel(e, f.inv_half_k2)
        j += q.lanes
    return s


_walk_value_lane = cell_rows("value_lane", row_value_lane, LanePoint, float, field=UnsortedAtoms)


MEAN_BLOCK = 64
"""Threads per block of `mean_density_kernel`: its threads are bound by the latency of their
own loads, and small blocks spread them over more multiprocessors."""
MEAN_LANES = 64
"""Partial sums of the mean density at the sampled atoms (a fixed order: the same frame
gives the same scale bit for bit, where atomic float adds would not)."""
_LANES = wp.constant(MEAN_LANES)  # type: ignore[no-untyped-call]
LANES_PER_SAMPLE = 8
"""Threads that take one sampled atom's density together on a CUDA device (each a share of
every row's atoms): one thread walking a neighbourhood alone waits on hundreds of dependent
loads while the few thousand samples leave most of the device idle
(benchmarks/results/archive/render_h200_fixed_costs.json)."""


@wp.kernel
@no_type_check
def mean_density_kernel(f: UnsortedAtoms, stride: int, lanes: int, values: wp.array[float]):
    """The density at every `stride`-th atom (the reference of relative iso levels), taken by
    `lanes` threads each: `values` holds the lanes' sums, sample by sample."""
    t = wp.tid()
    k = t // lanes
    q = LanePoint()
    q.p = f.positions[k * stride]
    q.lane = t - k * lanes
    q.lanes = lanes
    values[t] = _walk_value_lane(f, q.p, q.p, q, wp.float32(0.0))


@wp.kernel
@no_type_check
def partial_sums_kernel(values: wp.array[float], count: int, partial: wp.array[float]):
    t = wp.tid()
    s = float(0.0)
    i = t
    while i < count:
        s += values[i]
        i += _LANES
    partial[t] = s


@wp.kernel
@no_type_check
def total_kernel(partial: wp.array[float], total: wp.array[float]):
    """The sum of the partial sums, in lane order (one thread)."""
    t = float(0.0)
    for q in range(_LANES):
        t += partial[q]
    total[0] = t


@wp.kernel
@no_type_check
def gather_atoms_kernel(
    positions: wp.array[wp.vec3],
    weights: wp.array[float],
    radii: wp.array[float],
    order: wp.array[wp.int32],
    sigma_per_radius: float,
    per_atom: int,
    total: wp.array[float],
    samples: float,
    relative: int,
    atoms: wp.array[wp.vec4],
    inv2s2: wp.array[float],
):
    """Copy atoms into cell order (x, y, z, w), with 1 / (2 s_i^2) in vdw mode; for relative
    levels every weight is divided by the mean density at the sampled atoms (`total` /
    `samples`), so the levels are fractions of the density's own scale."""
    i = wp.tid()
    j = order[i]
    p = positions[j]
    w = weights[j]
    if relative != 0:
        t = total[0]
        if t > 0.0:
            w = w * samples / t
    atoms[i] = wp.vec4(p[0], p[1], p[2], w)
    if per_atom != 0:
        inv2s2[i] = inv2s2_of(sigma_per_radius, radii[j])


@dataclass(frozen=True)
class DensityModel:
    """A density the ray caster can draw.

    `value(f, p) -> float`, `value_grad(f, p) -> vec4(grad, value)`, `sample(f, p) -> Sample`,
    `box_bound(f, lo, hi, stop_above) -> float` (>= the density anywhere in the box, or any
    value above `stop_above` once that is certain), all `@wp.func` over the struct `field`.
    Optional batched forms, used by the ray caster to load each neighbour once for several
    samples along a line: `value4(f, o, d, ts: vec4) -> vec4` (S at o + d ts[q]) and
    `value_grad4(f, o, d, ts: vec4) -> (vec4, vec4, vec4, vec4)` ((gradient, S) at each);
    a model without them gets versions that call `value` / `value_grad` per point. Also
    optional, for models that can cheaply tell a value is below a level: `value4_level(f, o,
    d, ts, level)` and `value_grad4_level(...)`, exact where a value may reach `level`, and any
    negative value (read "below, value unknown") where it cannot; the marching kernels only
    compare values with the level, so they use these. And `part_bounds(f, lo, hi,
    stop_above) -> PartBounds`, the bounds of the 27 parts of a box (as `box_bound` per
    part, each widened by PART_SLACK of its edge), from which the rays skip samples in the
    parts of a cell that are below the level; without it only whole cells are skipped. And
    `side4(f, o, d, ts, level)`, for the marching kernels, which need only each sample's side
    of the level: the value, or -1 for "below, value unknown", or +inf for "at or above,
    value unknown" (default: `value4_level`). And `part_bounds_lane(f, lo, hi, lane, lanes)
    -> PartBounds`, lane `lane` of `lanes`' share of the part bounds, the shares adding up to
    them: a small molecule's few cells are then walked by several threads each.
    """

    name: str
    field: Any
    value: Any
    value_grad: Any
    sample: Any
    box_bound: Any
    value4: Any = None
    value_grad4: Any = None
    value4_level: Any = None
    value_grad4_level: Any = None
    part_bounds: Any = None
    side4: Any = None
    part_bounds_lane: Any = None


GAUSSIAN = DensityModel(
    name="gaussian",
    field=GaussianField,
    value=gaussian_value,
    value_grad=gaussian_value_grad,
    sample=gaussian_sample,
    box_bound=gaussian_box_bound,
    value4=gaussian_value4,
    value_grad4=gaussian_value_grad4,
    part_bounds=gaussian_part_bounds,
    part_bounds_lane=gaussian_part_bounds_lane,
)
