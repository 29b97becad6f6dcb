"""The geodesic density sampled on a grid of its own and read by cubic B-spline.

A ray's samples ask the geodesic density for its value several times per pixel (the march,
the refinement, the shading's gradient), and each value walks every route of some forty atoms
(`geodesic_field`). Neighbouring pixels ask at nearly the same points. This model evaluates
the routes once per point of a regular grid instead (spacing `spacing_of`: half of sigma at
the default smoothing), after each frame's route distances, and the rays read the grid by
cubic B-spline (64 coefficients a point, C2: no crease, smooth shading normals). The field is
smooth at the scale of sigma and of its smoothing tau, so the interpolant is within a small
fraction of the surface's accuracy bound (tests/render/test_geodesic_volume.py holds it to
max(0.05 A, 1 % sigma) against the routes evaluated per sample).

What a frame does (launches only, graph-safe; the renderer's plan reads two numbers of the
frame before, once it is done):
  * `setup_kernel`: the grid over the atom grid's box (atoms plus the cutoff, where every
    Gaussian ends) and two zero points more on every side; if it has more points than were
    allocated, `valid` is 0 and every function below falls back to the routes per sample, so
    the image is the same, only slower (the host plans the size from the last frame, `plan`).
  * `gate_kernel`: points whose bound (the classical density times `Routes.gate`) is below
    CUT times the level hold 0 and walk no route: their value is below a fifth of the level,
    where the interpolant near the surface barely feels it;
  * the others are listed (a scan) and their routes walked by `lanes` threads each, as the mean
    density is, FILL_CHUNK points a launch (`fill_kernel`, `sum_kernel`; points past the planned
    count one thread each): each point's value, colour and largest contributor;
  * `prefilter_kernel` along x, y and z turns values into B-spline coefficients (the causal and
    anticausal recursions of the cubic B-spline's pole, sqrt(3) - 2), so the spline interpolates
    the grid's values rather than blurring them.

The fill also keeps, at every walked point, the routes' contribution-weighted colour and their
largest contributor. A shaded point takes its colour from its cell's eight points
(trilinear) and its atom from those points' largest contributors: their terms are evaluated
there and the largest is picked, so a pixel picks what the routes per sample pick wherever
the largest contributor at the point is one of its cell's (a walk of a few atoms' routes
where the routes per sample walk some forty atoms'). Value and gradient come from the spline.
"""

from __future__ import annotations

import math
from typing import Any, no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import GridInfo
from server.render.density import (
    DensityModel,
    LanePoint,
    PartBounds,
    Sample,
    cell_rows,
    gaussian_value,
    unpack_rgb,
)
from server.render.geodesic_field import (
    GeodesicField,
    geodesic_box_bound,
    geodesic_part_bounds,
    geodesic_sample,
    geodesic_side4,
    geodesic_value,
    geodesic_value4,
    geodesic_value4_level,
    geodesic_value_grad,
    geodesic_value_grad4,
    geodesic_value_grad4_level,
    term,
)

SIGMA_SPACING = 0.5
"""Grid spacing in units of the narrowest atom's sigma: at 0.5 the surface of villin moves by
at most 0.03 A at sigma 1.5 A and 0.047 A at 0.5 A against the routes per sample (float64 study
of the interpolant, render_cpu_geodesic_grid_interpolant.txt; 0.6 sigma missed a thin feature
by 4.7 A)."""
TAU_SPACING = 1.5
"""At most this many smoothing temperatures tau per grid step: a smaller smoothing sharpens the
field where the nearest route changes (0.35 sigma at smoothing 0.2 moved it by 0.052 A, 0.5
sigma by 0.15 A)."""
MAX_SMOOTHING = 1.0
"""The largest smoothing (tau / sigma) the grid draws: its images agree with the routes per
sample at 0.05-1 (villin, sigma 1.5 and 3 A), while at 2 the level falls to the Gaussians'
tapered tails, where the spline rings (two thirds of villin's drawn pixels changed colour at
sigma 1.5 A); past it the routes are walked per sample."""
CUT = 0.2
"""Points whose bound is below this fraction of the level hold 0 (their value is below it)."""
POINTS_PER_PIXEL = 10.75
"""The grid is used when it has at most this many points a pixel of the image. A grid point
costs about what a ray sample does; a pixel costs several samples, fewer where the molecule
covers less of the image. One NVIDIA H200 (render_h200_densities.json, the routes per sample
the control): the grid took 0.07-0.34 of the routes' time at 0.6-10.5 points a pixel (villin
to 10,000 atoms at 500x500) and 1.17 of it at 11.05 (100,000 atoms at 1920x1080): the rule
sits between the two."""
MAX_POINTS = 1 << 25
"""Most grid points a plan takes: with SLACK, buffers of up to 50M points (24 bytes each) and
the lanes' sums of one FILL_CHUNK of their walked ones."""
REACH_STEPS = 6.0
"""Grid steps past an atom's cutoff that its value reaches through the spline (two) and the
prefilter (whose recursion decays by 0.27 a step): what a device that keeps only the atoms near
its part of the image (`grid.Cull`) must keep beyond them."""
LISTED = 0.35
"""Walked points per grid point the plan expects before a frame has counted them (villin and
adenylate kinase at sigma 1.5 A: 0.17-0.23)."""
SLACK = 1.5
"""Points allocated per point the plan expects (the molecule moves between frames)."""
FILL_CHUNK = 1 << 20
"""Listed points one fill launch takes: the lanes' partial sums (value, colour, largest term;
24 bytes a lane, 200 MB a chunk at eight lanes) are held for one chunk at a time, so they do
not grow with the molecule. 2^17 cost 100,000 atoms at 1920x1080 8 % more (a launch's last
wave; one NVIDIA H200); eight lanes a point were as fast as four, and 1.1-2.1x faster than 16
or 32 (`render_h200_geodesic_grid_pick_sweep.json`)."""
_Ints8 = wp.types.vector(length=8, dtype=wp.int32)

_POLE = wp.constant(math.sqrt(3.0) - 2.0)  # type: ignore[no-untyped-call]


def spacing_of(sigma_min: float, tau: float) -> float:
    """The grid's spacing for the narrowest sigma and the smoothing temperature."""
    return min(SIGMA_SPACING * sigma_min, TAU_SPACING * tau)


@wp.struct
class VolumeInfo:
    """This frame's grid: point (x, y, z) at origin + h (x, y, z), x fastest in memory."""

    origin: wp.vec3
    h: float
    inv_h: float
    dims: wp.vec3i
    points: int
    valid: int


@wp.struct
class GeodesicVolumeField:
    """What the sampled geodesic density reads; `info` to `brick_bound` are the atom grid's
    (the caster walks them with the geodesic bounds), `geo` the routes (for the grid's fill
    and the fallback), `coef` the spline's coefficients, `tint` each point's colour (RGB,
    alpha 255 where walked) and `atoms` its largest contributor (sorted index, -1 where not
    walked)."""

    info: wp.array[GridInfo]
    cell_start: wp.array[wp.int32]
    bound: wp.array[float]
    parts: wp.array[wp.int32]
    brick_bound: wp.array[float]
    geo: GeodesicField
    coef: wp.array[float]
    tint: wp.array[wp.uint32]
    atoms: wp.array[wp.int32]
    vol: wp.array[VolumeInfo]


# ------------------------------------------------------------------------- the spline


@wp.func
@no_type_check
def bspline_weights(t: float) -> wp.vec4:
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return wp.vec4(
        s * s * s / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    )


@wp.func
@no_type_check
def bspline_slopes(t: float) -> wp.vec4:
    s = 1.0 - t
    t2 = t * t
    return wp.vec4(-0.5 * s * s, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2)


@wp.func
@no_type_check
def corner(v: VolumeInfo, p: wp.vec3) -> wp.vec4:
    """(i, j, k, 0) of the first of the 4^3 coefficients p reads; -1 (the density is 0 there)
    when p is not well inside the grid."""
    u = (p - v.origin) * v.inv_h
    out = wp.vec4(-1.0, -1.0, -1.0, -1.0)
    # compared as floats first: p may be far outside (or not finite)
    if u[0] >= 1.0 and u[1] >= 1.0 and u[2] >= 1.0:
        hi = wp.vec3(float(v.dims[0] - 2), float(v.dims[1] - 2), float(v.dims[2] - 2))
        if u[0] < hi[0] and u[1] < hi[1] and u[2] < hi[2]:
            i = int(wp.floor(u[0])) - 1
            j = int(wp.floor(u[1])) - 1
            k = int(wp.floor(u[2])) - 1
            out = wp.vec4(float(i), float(j), float(k), 0.0)
    return out


@wp.func
@no_type_check
def spline_value(coef: wp.array[float], v: VolumeInfo, p: wp.vec3) -> float:
    c = corner(v, p)
    s = float(0.0)
    if c[0] >= 0.0:
        i = int(c[0])
        j = int(c[1])
        k = int(c[2])
        u = (p - v.origin) * v.inv_h
        wx = bspline_weights(u[0] - float(i + 1))
        wy = bspline_weights(u[1] - float(j + 1))
        wz = bspline_weights(u[2] - float(k + 1))
        nx = v.dims[0]
        ny = v.dims[1]
        for c2 in range(4):
            for c1 in range(4):
                b = ((k + c2) * ny + j + c1) * nx + i
                row = wx[0] * coef[b] + wx[1] * coef[b + 1] + wx[2] * coef[b + 2]
                row += wx[3] * coef[b + 3]
                s += wz[c2] * wy[c1] * row
    return s


@wp.func
@no_type_check
def spline_value_grad(coef: wp.array[float], v: VolumeInfo, p: wp.vec3) -> wp.vec4:
    """(gradient, value) of the spline at p."""
    c = corner(v, p)
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if c[0] >= 0.0:
        i = int(c[0])
        j = int(c[1])
        k = int(c[2])
        u = (p - v.origin) * v.inv_h
        tx = u[0] - float(i + 1)
        ty = u[1] - float(j + 1)
        tz = u[2] - float(k + 1)
        wx = bspline_weights(tx)
        wy = bspline_weights(ty)
        wz = bspline_weights(tz)
        dx = bspline_slopes(tx)
        dy = bspline_slopes(ty)
        dz = bspline_slopes(tz)
        nx = v.dims[0]
        ny = v.dims[1]
        s = float(0.0)
        gx = float(0.0)
        gy = float(0.0)
        gz = float(0.0)
        for c2 in range(4):
            for c1 in range(4):
                b = ((k + c2) * ny + j + c1) * nx + i
                x4 = wp.vec4(coef[b], coef[b + 1], coef[b + 2], coef[b + 3])
                row = wp.dot(wx, x4)
                slope = wp.dot(dx, x4)
                s += wz[c2] * wy[c1] * row
                gx += wz[c2] * wy[c1] * slope
                gy += wz[c2] * dy[c1] * row
                gz += dz[c2] * wy[c1] * row
        out = wp.vec4(gx * v.inv_h, gy * v.inv_h, gz * v.inv_h, s)
    return out


# ------------------------------------------------------------------------- the model


@wp.func
@no_type_check
def volume_value(f: GeodesicVolumeField, p: wp.vec3) -> float:
    v = f.vol[0]
    out = spline_value(f.coef, v, p) if v.valid != 0 else geodesic_value(f.geo, p)
    return out


@wp.func
@no_type_check
def volume_value_grad(f: GeodesicVolumeField, p: wp.vec3) -> wp.vec4:
    v = f.vol[0]
    out = spline_value_grad(f.coef, v, p) if v.valid != 0 else geodesic_value_grad(f.geo, p)
    return out


@wp.func
@no_type_check
def row_pick_lane(f: GeodesicField, q: LanePoint, j0: int, j1: int, acc: Sample) -> Sample:
    """The lane's share of the routes' terms over sorted atoms [j0, j1) (every `lanes`-th, as
    `row_value_lane`, so the values add up in the same order): their sum, contribution-weighted
    colour and largest term, `atom` its sorted index (ties: the lower original index)."""
    s = acc
    g = f.gauss
    j = j0 + q.lane
    while j < j1:
        t = term(f, j, q.p)
        if t > 0.0:
            s.value = s.value + t
            s.color = s.color + unpack_rgb(g.colors[g.order[j]]) * t
            if t > s.weight:
                s.weight = t
                s.atom = j
            elif t == s.weight and g.order[j] < g.order[s.atom]:
                s.atom = j
        j += q.lanes
    return s


_walk_pick_lane = cell_rows(
    "geodesic_pick_lane", row_pick_lane, LanePoint, Sample, field=GeodesicField
)


@wp.func
@no_type_check
def pick_walk(f: GeodesicField, p: wp.vec3, lane: int, lanes: int) -> Sample:
    """One lane's `row_pick_lane` over every row within reach of p."""
    q = LanePoint()
    q.p = p
    q.lane = lane
    q.lanes = lanes
    s = Sample()
    s.value = 0.0
    s.grad = wp.vec3(0.0, 0.0, 0.0)
    s.color = wp.vec3(0.0, 0.0, 0.0)
    s.weight = -1.0
    s.atom = -1
    return _walk_pick_lane(f, p, p, q, s)


@wp.func
@no_type_check
def pack_tint(c: wp.vec3) -> wp.uint32:
    """A colour in [0, 1]^3 as RGB bytes, alpha 255 (a walked point)."""
    r = wp.uint32(wp.clamp(c[0] * 255.0 + 0.5, 0.0, 255.0))
    g = wp.uint32(wp.clamp(c[1] * 255.0 + 0.5, 0.0, 255.0))
    b = wp.uint32(wp.clamp(c[2] * 255.0 + 0.5, 0.0, 255.0))
    return r | (g << wp.uint32(8)) | (b << wp.uint32(16)) | (wp.uint32(255) << wp.uint32(24))


@wp.func
@no_type_check
def grid_pick(f: GeodesicVolumeField, v: VolumeInfo, p: wp.vec3) -> Sample:
    """Colour (trilinear over the walked points of p's cell, `weight` 1) and the picked atom
    (original index): the largest of the cell's points' largest contributors, their terms
    evaluated at p. `atom` -1 when the cell has no walked point."""
    s = Sample()
    s.value = 0.0
    s.grad = wp.vec3(0.0, 0.0, 0.0)
    s.color = wp.vec3(0.0, 0.0, 0.0)
    s.weight = 0.0
    s.atom = -1
    c = corner(v, p)
    if c[0] >= 0.0:
        i = int(c[0]) + 1
        j = int(c[1]) + 1
        k = int(c[2]) + 1
        u = (p - v.origin) * v.inv_h
        fx = u[0] - float(i)
        fy = u[1] - float(j)
        fz = u[2] - float(k)
        nx = v.dims[0]
        ny = v.dims[1]
        g = f.geo.gauss
        seen = _Ints8()
        best = float(-1.0)
        for n in range(8):
            dx = n & 1
            dy = (n >> 1) & 1
            dz = n >> 2
            at = ((k + dz) * ny + j + dy) * nx + i + dx
            w = wp.where(dx == 1, fx, 1.0 - fx) * wp.where(dy == 1, fy, 1.0 - fy)
            w = w * wp.where(dz == 1, fz, 1.0 - fz)
            t = f.tint[at]
            if (t >> wp.uint32(24)) != wp.uint32(0):
                s.color = s.color + unpack_rgb(t) * w
                s.weight = s.weight + w
            a = f.atoms[at]
            fresh = a >= 0
            for m in range(n):
                if seen[m] == a + 1:
                    fresh = False
            seen[n] = a + 1
            if fresh:
                tv = term(f.geo, a, p)
                oa = int(g.order[a])
                if tv > best:
                    best = tv
                    s.atom = oa
                elif tv == best and oa < s.atom:
                    s.atom = oa
        if s.weight > 0.0:
            s.color = s.color / s.weight
            s.weight = 1.0
    return s


@wp.func
@no_type_check
def volume_sample(f: GeodesicVolumeField, p: wp.vec3) -> Sample:
    """At a shaded point: value and gradient from the spline (the surface and its normal the
    rays found), colour and the picked atom from the grid's points around it (`grid_pick`);
    the routes per sample where the grid does not hold the frame or the cell was not walked."""
    v = f.vol[0]
    s = Sample()
    s.atom = -1
    s.weight = 0.0
    if v.valid != 0:
        s = grid_pick(f, v, p)
    if s.atom >= 0 and s.weight > 0.0:
        g = spline_value_grad(f.coef, v, p)
        s.value = g[3]
        s.grad = wp.vec3(g[0], g[1], g[2])
    else:
        s = geodesic_sample(f.geo, p)
    return s


@wp.func
@no_type_check
def splines4(f: GeodesicVolumeField, v: VolumeInfo, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    return wp.vec4(
        spline_value(f.coef, v, o + d * ts[0]),
        spline_value(f.coef, v, o + d * ts[1]),
        spline_value(f.coef, v, o + d * ts[2]),
        spline_value(f.coef, v, o + d * ts[3]),
    )


@wp.func
@no_type_check
def volume_value4(f: GeodesicVolumeField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
    v = f.vol[0]
    out = splines4(f, v, o, d, ts) if v.valid != 0 else geodesic_value4(f.geo, o, d, ts)
    return out


@wp.func
@no_type_check
def volume_value4_level(
    f: GeodesicVolumeField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float
) -> wp.vec4:
    v = f.vol[0]
    if v.valid != 0:
        return splines4(f, v, o, d, ts)
    return geodesic_value4_level(f.geo, o, d, ts, level)


@wp.func
@no_type_check
def volume_side4(
    f: GeodesicVolumeField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float
) -> wp.vec4:
    v = f.vol[0]
    out = splines4(f, v, o, d, ts) if v.valid != 0 else geodesic_side4(f.geo, o, d, ts, level)
    return out


@wp.func
@no_type_check
def spline_grads4(f: GeodesicVolumeField, v: VolumeInfo, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    return (
        spline_value_grad(f.coef, v, o + d * ts[0]),
        spline_value_grad(f.coef, v, o + d * ts[1]),
        spline_value_grad(f.coef, v, o + d * ts[2]),
        spline_value_grad(f.coef, v, o + d * ts[3]),
    )


@wp.func
@no_type_check
def volume_value_grad4(f: GeodesicVolumeField, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    v = f.vol[0]
    if v.valid != 0:
        return spline_grads4(f, v, o, d, ts)
    return geodesic_value_grad4(f.geo, o, d, ts)


@wp.func
@no_type_check
def volume_value_grad4_level(
    f: GeodesicVolumeField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float
):
    v = f.vol[0]
    if v.valid != 0:
        return spline_grads4(f, v, o, d, ts)
    return geodesic_value_grad4_level(f.geo, o, d, ts, level)


@wp.func
@no_type_check
def volume_box_bound(f: GeodesicVolumeField, lo: wp.vec3, hi: wp.vec3, stop_above: float) -> float:
    return geodesic_box_bound(f.geo, lo, hi, stop_above)


@wp.func
@no_type_check
def volume_part_bounds(
    f: GeodesicVolumeField, lo: wp.vec3, hi: wp.vec3, stop_above: float
) -> PartBounds:
    return geodesic_part_bounds(f.geo, lo, hi, stop_above)


GEODESIC_VOLUME = DensityModel(
    name="geodesic_volume",
    field=GeodesicVolumeField,
    value=volume_value,
    value_grad=volume_value_grad,
    sample=volume_sample,
    box_bound=volume_box_bound,
    value4=volume_value4,
    value_grad4=volume_value_grad4,
    value4_level=volume_value4_level,
    value_grad4_level=volume_value_grad4_level,
    part_bounds=volume_part_bounds,
    side4=volume_side4,
)


# ------------------------------------------------------------------------- the fill


@wp.func
@no_type_check
def point_of(v: VolumeInfo, i: int) -> wp.vec3:
    nx = v.dims[0]
    ny = v.dims[1]
    x = i % nx
    y = (i // nx) % ny
    z = i // (nx * ny)
    return v.origin + wp.vec3(float(x), float(y), float(z)) * v.h


@wp.kernel
@no_type_check
def setup_kernel(info: wp.array[GridInfo], h: float, capacity: int, vol: wp.array[VolumeInfo]):
    """Lay the grid over the atom grid's box with two zero points more on every side."""
    g = info[0]
    v = VolumeInfo()
    v.h = h
    v.inv_h = 1.0 / h
    v.origin = g.origin - wp.vec3(2.0 * h, 2.0 * h, 2.0 * h)
    ext = g.box_hi - g.origin
    fx = wp.floor(ext[0] / h) + 5.0
    fy = wp.floor(ext[1] / h) + 5.0
    fz = wp.floor(ext[2] / h) + 5.0
    v.valid = 0
    v.points = 0
    v.dims = wp.vec3i(1, 1, 1)
    size = wp.float64(fx) * wp.float64(fy) * wp.float64(fz)
    if g.valid != 0 and size <= wp.float64(capacity):
        v.dims = wp.vec3i(int(fx), int(fy), int(fz))
        v.points = int(fx) * int(fy) * int(fz)
        v.valid = 1
    elif g.valid != 0:
        # what the plan must make room for (capped: only compared on the host)
        v.points = int(wp.min(size, wp.float64(2.0e9)))
    vol[0] = v


@wp.kernel
@no_type_check
def gate_kernel(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    cut: float,
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
    flags: wp.array[wp.int32],
):
    """flags[i] = 1 where point i's bound reaches `cut` (its routes are walked), and every
    point's value 0 (no colour, no atom) until then."""
    i = wp.tid()
    v = vol[0]
    flag = 0
    if v.valid != 0 and i < v.points:
        coef[i] = 0.0
        tint[i] = wp.uint32(0)
        atoms[i] = -1
        b = gaussian_value(f.gauss, point_of(v, i)) * f.routes.gate
        if b > 0.0 and b >= cut:
            flag = 1
    flags[i] = flag


@wp.kernel
@no_type_check
def compact_kernel(
    flags: wp.array[wp.int32],
    scan: wp.array[wp.int32],
    last: int,
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
):
    i = wp.tid()
    if flags[i] != 0:
        listed[scan[i]] = i
    if i == last:
        count[0] = scan[i] + flags[i]


@wp.kernel
@no_type_check
def fill_kernel(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
    lanes: int,
    first: int,
    partial: wp.array[float],
    partial_tint: wp.array[wp.vec4],
    partial_atom: wp.array[wp.int32],
):
    """Lane `t % lanes` of listed point `first + t // lanes`: its share of the point's atoms
    (every `lanes`-th of each row, a fixed order): value, colour sum and largest term."""
    t = wp.tid()
    k = t // lanes
    if first + k < count[0]:
        p = point_of(vol[0], listed[first + k])
        s = pick_walk(f, p, t - k * lanes, lanes)
        partial[t] = s.value
        partial_tint[t] = wp.vec4(s.color[0], s.color[1], s.color[2], s.weight)
        partial_atom[t] = s.atom


@wp.func
@no_type_check
def keep_point(
    i: int,
    s: Sample,
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
):
    """Point i's value, colour and largest contributor."""
    coef[i] = s.value
    if s.value > 0.0 and s.atom >= 0:
        tint[i] = pack_tint(s.color / s.value)
        atoms[i] = s.atom


@wp.kernel
@no_type_check
def sum_kernel(
    f: GeodesicField,
    partial: wp.array[float],
    partial_tint: wp.array[wp.vec4],
    partial_atom: wp.array[wp.int32],
    lanes: int,
    first: int,
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
):
    """The lanes' shares of listed point `first + tid` added in lane order; the largest term
    the largest of theirs (ties: the lower original index, as one thread's walk)."""
    k = wp.tid()
    if first + k < count[0]:
        s = Sample()
        s.value = 0.0
        s.color = wp.vec3(0.0, 0.0, 0.0)
        s.weight = -1.0
        s.atom = -1
        order = f.gauss.order
        for q in range(lanes):
            u = k * lanes + q
            s.value += partial[u]
            pt = partial_tint[u]
            s.color = s.color + wp.vec3(pt[0], pt[1], pt[2])
            a = partial_atom[u]
            if a >= 0:
                if pt[3] > s.weight:
                    s.weight = pt[3]
                    s.atom = a
                elif pt[3] == s.weight and order[a] < order[s.atom]:
                    s.atom = a
        keep_point(listed[first + k], s, coef, tint, atoms)


@wp.kernel
@no_type_check
def rest_kernel(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
    first: int,
    threads: int,
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
):
    """Listed points past the planned count (`first`), one thread each in turn: the molecule
    grew since the plan; the next frame's plan makes room."""
    k = first + wp.tid()
    n = count[0]
    v = vol[0]
    while k < n:
        i = listed[k]
        keep_point(i, pick_walk(f, point_of(v, i), 0, 1), coef, tint, atoms)
        k += threads


@wp.kernel
@no_type_check
def prefilter_kernel(coef: wp.array[float], vol: wp.array[VolumeInfo], axis: int):
    """One line of the grid along `axis`: values to cubic B-spline coefficients (gain 6, the
    causal then the anticausal recursion; the line's ends are 0, so both start from 0)."""
    t = wp.tid()
    v = vol[0]
    if v.valid == 0:
        return
    nx = v.dims[0]
    ny = v.dims[1]
    nz = v.dims[2]
    n = nx
    stride = 1
    first = 0
    if axis == 0:
        if t >= ny * nz:
            return
        first = t * nx
    elif axis == 1:
        if t >= nx * nz:
            return
        n = ny
        stride = nx
        first = (t // nx) * nx * ny + t % nx
    else:
        if t >= nx * ny:
            return
        n = nz
        stride = nx * ny
        first = t
    z = _POLE
    c = float(0.0)
    for m in range(n):
        at = first + m * stride
        c = coef[at] + z * c
        coef[at] = c
    c = c * z / (z * z - 1.0)
    coef[first + (n - 1) * stride] = 6.0 * c
    for m in range(n - 1):
        at = first + (n - 2 - m) * stride
        c = z * (c - coef[at])
        coef[at] = 6.0 * c


# ------------------------------------------------------------------------- host side

_wp: Any = wp  # warp's host API is unannotated


class GeodesicVolume:
    """The grid's buffers on one device and the plan of their size."""

    def __init__(self, device: str, lanes: int) -> None:
        self.device = device
        self.lanes = max(int(lanes), 1)
        self.cuda = bool(_wp.get_device(device).is_cuda)
        self.vol = _wp.zeros(1, dtype=VolumeInfo, device=device)
        self.count = _wp.zeros(1, dtype=_wp.int32, device=device)
        self.capacity = 0
        self.listed_capacity = 0
        self.built: tuple[float, int] | None = None
        """(spacing, capacity) of the last build, so the next plan reads what it needed."""
        self._need: tuple[float, int, int] | None = None
        """`last_need` once read: frames that keep the grid (a camera turning over still
        positions) plan from it without reading the device again."""
        self._alloc(0, 0)

    def _alloc(self, points: int, listed: int) -> None:
        dev = self.device
        n = max(points, 1)
        self.coef = _wp.zeros(n, dtype=float, device=dev)
        self.tint = _wp.zeros(n, dtype=_wp.uint32, device=dev)
        self.atoms = _wp.zeros(n, dtype=_wp.int32, device=dev)
        self.flags = _wp.zeros(n, dtype=_wp.int32, device=dev)
        self.scan = _wp.zeros(n, dtype=_wp.int32, device=dev)
        self.listed = _wp.zeros(n, dtype=_wp.int32, device=dev)
        lanes = max(min(listed, FILL_CHUNK), 1) * self.lanes
        self.partial = _wp.zeros(lanes, dtype=float, device=dev)
        self.partial_tint = _wp.zeros(lanes, dtype=_wp.vec4, device=dev)
        self.partial_atom = _wp.zeros(lanes, dtype=_wp.int32, device=dev)
        self.capacity = points
        self.listed_capacity = listed

    @property
    def nbytes(self) -> int:
        arrays = (
            self.coef,
            self.tint,
            self.atoms,
            self.flags,
            self.scan,
            self.listed,
            self.partial,
            self.partial_tint,
            self.partial_atom,
        )
        return sum(int(a.capacity) for a in arrays)

    def last_need(self) -> tuple[float, int, int] | None:
        """(spacing, points, listed points) the last build needed (synchronises; call once
        that build is done); listed 0 when its grid did not fit (it listed nothing)."""
        if self.built is None:
            return None
        if self._need is not None:
            return self._need
        v = self.vol.numpy()[0]
        listed = int(self.count.numpy()[0]) if int(v["valid"]) else 0
        self._need = (self.built[0], int(v["points"]), listed)
        return self._need

    def fits(self, points: int, listed: int) -> bool:
        """Whether the buffers hold `points` grid points and `listed` walked ones."""
        return points <= self.capacity and listed <= self.listed_capacity

    def bytes_for(self, points: int, listed: int) -> int:
        """Device bytes of buffers for `points` grid points and `listed` walked ones."""
        chunk = min(int(listed * SLACK + 64), FILL_CHUNK)
        return int(points * SLACK + 64) * 24 + chunk * 24 * self.lanes

    def reserve(self, points: int, listed: int) -> None:
        """Buffers for `points` grid points and `listed` walked ones, with SLACK (graphs and
        fields that hold the old ones must be let go first)."""
        self._alloc(0, 0)  # the old buffers go before the new ones are made
        self._alloc(int(points * SLACK) + 64, int(listed * SLACK) + 64)

    def build(self, f: GeodesicField, info: Any, h: float, cut: float) -> None:
        """This frame's coefficients from the routes in `f` (launches only)."""
        dev = self.device
        cap = self.capacity
        self.built = (h, cap)
        self._need = None
        _wp.launch(setup_kernel, 1, (info, float(h), cap, self.vol), device=dev)
        if cap == 0:
            return
        gate = (f, self.vol, float(cut), self.coef, self.tint, self.atoms, self.flags)
        _wp.launch(gate_kernel, cap, gate, device=dev)
        _wp.utils.array_scan(self.flags, self.scan, inclusive=False)
        compact = (self.flags, self.scan, cap - 1, self.listed, self.count)
        _wp.launch(compact_kernel, cap, compact, device=dev)
        lanes, listed = self.lanes, self.listed_capacity
        keep = (self.coef, self.tint, self.atoms)
        parts = (self.partial, self.partial_tint, self.partial_atom)
        for first in range(0, listed, FILL_CHUNK):
            n = min(FILL_CHUNK, listed - first)
            fill = (f, self.vol, self.listed, self.count, lanes, first, *parts)
            _wp.launch(fill_kernel, n * lanes, fill, device=dev)
            total = (f, *parts, lanes, first, self.listed, self.count, *keep)
            _wp.launch(sum_kernel, n, total, device=dev)
        rest_threads = 4096 if self.cuda else 1
        rest = (f, self.vol, self.listed, self.count, listed, rest_threads, *keep)
        _wp.launch(rest_kernel, rest_threads, rest, device=dev)
        lines = cap // 5 + 1
        for axis in range(3):
            _wp.launch(prefilter_kernel, lines, (self.coef, self.vol, axis), device=dev)

    def field(self, geo: GeodesicField) -> GeodesicVolumeField:
        f = GeodesicVolumeField()
        f.info = geo.info
        f.cell_start = geo.cell_start
        f.bound = geo.bound
        f.parts = geo.parts
        f.brick_bound = geo.brick_bound
        f.geo = geo
        f.coef = self.coef
        f.tint = self.tint
        f.atoms = self.atoms
        f.vol = self.vol
        return f
