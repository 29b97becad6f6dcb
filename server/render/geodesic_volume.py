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
  * the gate (`_gate_points`): points whose bound (the classical density times `Routes.gate`)
    is below CUT times the level hold 0 and walk no route: their value is below a fifth of the
    level, where the interpolant near the surface barely feels it;
  * the bricks of 4 x 4 x 2 points that hold such a point are listed (a scan), and each
    brick's points are taken by one warp's 32 threads (`_fill_points`): every thread walks the
    routes of the atoms within reach of the whole brick, so the warp reads the same routes
    together, and keeps its point's value, colour and largest contributor (the atoms beyond
    its own reach add exact zeros: the values are those of a walk around the point alone);
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

from server.render import device as _device
from server.render.cells import GridInfo, cell_at
from server.render.density import (
    DensityModel,
    LanePoint,
    PartBounds,
    Sample,
    cell_rows,
    empty_sample,
    first_of_lane,
    gaussian_value,
    unpack_rgb,
)
from server.render.geodesic_field import (
    GeodesicField,
    geodesic_box_bound,
    geodesic_part_bounds,
    geodesic_part_bounds_lane,
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
POINTS_PER_PIXEL = 160.0
"""The grid is used when it has at most this many points a pixel of the image (on CUDA): a
grid point is filled once a frame, where the routes per sample walk again for every sample a
ray takes near the surface. One NVIDIA H200, the routes per sample the control in the same run
(render_h200_geodesic_grid_or_routes.json): 100,000 atoms (a grid of some 23M points) at
1280x720, 800x450, 480x270 and 320x180, 25, 64, 177 and 398 points a pixel, took 0.55, 0.81,
0.98 and 1.02 of the routes' time from the grid; 10,000 atoms at 160x120 (137 points a pixel)
0.19. The rule stops below 177, where the grid still took 0.98 of the routes' time."""
CPU_POINTS_PER_PIXEL = 6.0
"""The same rule on the CPU device, whose threads walk each grid point alone: two CPU cores,
villin, the routes per sample the control in the same run
(render_cpu_2core_geodesic_grid_or_routes.json): from the grid 0.25, 0.94, 2.5 and 5.0 times
the routes' time at 1.8, 7.3, 20 and 46 points a pixel (320x240, 160x120, 96x72, 64x48), and
2,500 atoms at 96x72 (65 points a pixel) 6.3."""
MAX_POINTS = 1 << 25
"""Most grid points a plan takes: with SLACK, buffers of up to 50M points (16 bytes each, and
about one more for the bricks)."""
REACH_STEPS = 6.0
"""Grid steps past an atom's cutoff that its value reaches through the spline (two) and the
prefilter (whose recursion decays by 0.27 a step): what a device that keeps only the atoms near
its part of the image (`grid.Cull`) must keep beyond them."""
SLACK = 1.5
"""Points allocated per point the plan expects (the molecule moves between frames)."""
CELL_GATE = 1
"""The gate reads each point's atom-grid cell bound first (1), and evaluates the classical
density only where that reaches the cut (0: at every point, the same flags)."""
BRICK_X = 4
BRICK_Y = 4
BRICK_Z = 2
"""The fill takes the grid in bricks of 4 x 4 x 2 points, one warp's 32 threads (`_fill_points`)."""
BRICK_POINTS = BRICK_X * BRICK_Y * BRICK_Z
BRICKS_PER_POINT = 3.1 / BRICK_POINTS
"""Bricks allocated per grid point: a grid at least 5 points wide on every axis has at most
3.072 / 32 bricks a point, at 5 x 5 x 5 (12 bricks of 125 points), fewer as it grows (a test
counts them). `setup_kernel` still checks the count: a grid past it is not valid, and its
frames walk the routes."""
WARPS_PER_SM = 64
"""Groups of 32 threads the fill launches per multiprocessor on CUDA (each takes listed bricks
in turn): a full device's worth, whatever the count of bricks listed this frame."""
LISTED_BRICKS = 0.25
"""Listed bricks per brick of the grid the plan expects (villin to 100,000 atoms at sigma
1.5 A: 0.19-0.25)."""
MAX_LANES = 8
"""Most groups of 32 threads one brick's points take together (each a share of every row's
atoms): a small molecule lists too few bricks to fill the device, one group a brick."""
FILL_REGISTERS = 64
"""Register cap of the fill's kernel on CUDA (0: the compiler's, 89 with fast math). One NVIDIA
H200, the same run (render_h200_geodesic_fill_registers.json): 64 took the grid stage 0.92x at
100,000 atoms and 0.96x at 10,000, within 3 % of the compiler's below; 72, 80 and 96 were no
faster anywhere."""
FILL_TARGET = 3.0
"""Groups a brick double while twice the groups would stay within this many launches' worth
(`GeodesicVolume.lanes_for`): 8, 8, 4, 2, 1 and 1 for villin, 1,049, 2,500, 5,684, 10,000
atoms at 500x500 and 100,000 at 1920x1080. One NVIDIA H200, 1, 2, 4 and 8 groups in the same
run (render_h200_geodesic_fill_lanes.json, the fill with fast math): the rule's choice took
1.00-1.025x the fastest setting's time at every size (8 groups at villin and 1,049 atoms, 4 at
2,500 and 10,000, 2 at 5,684 and 100,000). More groups keep more lanes' shares (24 bytes a
point and group: 2 groups would hold about 225 MB at 100,000 atoms to save 2.4 %)."""
_Ints8 = wp.types.vector(length=8, dtype=wp.int32)

_POLE = wp.constant(math.sqrt(3.0) - 2.0)  # type: ignore[no-untyped-call]


def points_per_pixel(cuda: bool) -> float:
    """Most grid points a pixel at which the rays read the grid rather than walk the routes."""
    return POINTS_PER_PIXEL if cuda else CPU_POINTS_PER_PIXEL


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
    bricks: int
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
def keep_largest(s: Sample, t: float, a: int, order: wp.array[wp.int32]) -> Sample:
    """`s` with sorted atom a's term t taken as its largest contributor where t is larger
    than the one it holds (ties: the lower original index, whatever the order they come in)."""
    out = s
    if t > s.weight:
        out.weight = t
        out.atom = a
    elif t == s.weight and order[a] < order[s.atom]:
        out.atom = a
    return out


@wp.func
@no_type_check
def row_pick(f: GeodesicField, q: LanePoint, j0: int, j1: int, acc: Sample) -> Sample:
    """The lane's share of the routes' terms at q.p over sorted atoms [j0, j1) (those whose
    index is the lane's, `first_of_lane`): their sum, contribution-weighted colour and largest
    term, `atom` its sorted index (`keep_largest`)."""
    s = acc
    g = f.gauss
    j = first_of_lane(q, j0)
    while j < j1:
        t = term(f, j, q.p)
        if t > 0.0:
            s.value = s.value + t
            s.color = s.color + unpack_rgb(g.colors[g.order[j]]) * t
            s = keep_largest(s, t, j, g.order)
        j += q.lanes
    return s


_walk_pick = cell_rows("geodesic_pick", row_pick, LanePoint, Sample, field=GeodesicField)


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
    s = empty_sample()
    s.weight = 0.0
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


@wp.func
@no_type_check
def volume_part_bounds_lane(
    f: GeodesicVolumeField, lo: wp.vec3, hi: wp.vec3, lane: int, lanes: int
) -> PartBounds:
    return geodesic_part_bounds_lane(f.geo, lo, hi, lane, lanes)


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
    part_bounds_lane=volume_part_bounds_lane,
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
def setup_kernel(
    info: wp.array[GridInfo],
    h: float,
    capacity: int,
    brick_capacity: int,
    vol: wp.array[VolumeInfo],
):
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
    v.bricks = 0
    v.dims = wp.vec3i(1, 1, 1)
    size = wp.float64(fx) * wp.float64(fy) * wp.float64(fz)
    if g.valid != 0 and size <= wp.float64(capacity):
        nx = int(fx)
        ny = int(fy)
        nz = int(fz)
        bricks = (
            ((nx + BRICK_X - 1) // BRICK_X)
            * ((ny + BRICK_Y - 1) // BRICK_Y)
            * ((nz + BRICK_Z - 1) // BRICK_Z)
        )
        v.points = nx * ny * nz
        if bricks <= brick_capacity:
            v.dims = wp.vec3i(nx, ny, nz)
            v.bricks = bricks
            v.valid = 1
    elif g.valid != 0:
        # what the plan must make room for (capped: only compared on the host)
        v.points = int(wp.min(size, wp.float64(2.0e9)))
    vol[0] = v


@no_type_check
def _gate_points(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    cut: float,
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
    flags: wp.array[wp.int32],
    cells: int,
):
    """flags[i] = 1 where point i's bound reaches `cut` (its routes are walked), and every
    point's value 0 (no colour, no atom) until then. With `cells`, a point whose atom-grid
    cell's bound (over the whole cell) is below the cut is not evaluated: its own is too."""
    i = wp.tid()
    v = vol[0]
    flag = 0
    if v.valid != 0 and i < v.points:
        coef[i] = 0.0
        tint[i] = wp.uint32(0)
        atoms[i] = -1
        p = point_of(v, i)
        # a point beyond the atom grid lies beyond every cutoff: its clamped cell is as good
        if cells == 0 or f.bound[cell_at(f.info[0], p)] >= cut:
            b = gaussian_value(f.gauss, p) * f.routes.gate
            if b > 0.0 and b >= cut:
                flag = 1
    flags[i] = flag


@wp.func
@no_type_check
def brick_corner(v: VolumeInfo, b: int) -> wp.vec3i:
    """The grid point (x, y, z) at brick b's lowest corner (bricks x fastest)."""
    bx_count = (v.dims[0] + BRICK_X - 1) // BRICK_X
    by_count = (v.dims[1] + BRICK_Y - 1) // BRICK_Y
    return wp.vec3i(
        (b % bx_count) * BRICK_X,
        ((b // bx_count) % by_count) * BRICK_Y,
        (b // (bx_count * by_count)) * BRICK_Z,
    )


@wp.func
@no_type_check
def brick_point(v: VolumeInfo, c: wp.vec3i, k: int) -> int:
    """The grid index of point k (0-31, x fastest) of the brick whose corner is c (-1 outside
    the grid)."""
    nx = v.dims[0]
    ny = v.dims[1]
    x = c[0] + k % BRICK_X
    y = c[1] + (k // BRICK_X) % BRICK_Y
    z = c[2] + k // (BRICK_X * BRICK_Y)
    i = -1
    if x < nx and y < ny and z < v.dims[2]:
        i = (z * ny + y) * nx + x
    return i


@wp.kernel
@no_type_check
def brick_kernel(vol: wp.array[VolumeInfo], flags: wp.array[wp.int32], out: wp.array[wp.int32]):
    """out[b] = 1 where brick b holds a point whose routes are walked."""
    b = wp.tid()
    v = vol[0]
    flag = int(0)  # noqa: RUF046  (a warp variable the loop may change)
    if v.valid != 0 and b < v.bricks:
        c = brick_corner(v, b)
        for k in range(BRICK_POINTS):
            i = brick_point(v, c, k)
            if i >= 0:
                flag = wp.max(flag, flags[i])
    out[b] = flag


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


@wp.struct
class Fill:
    """How one fill launch takes the listed bricks: `lanes` groups of 32 threads a brick (each
    its share of every row's atoms), bricks [first, min(count, last)), `warps` groups in all
    taking (brick, lane) pairs in turn; `together` walks the atoms within reach of the whole
    brick, not of each point alone."""

    warps: int
    together: int
    lanes: int
    first: int
    last: int


@no_type_check
def _fill_points(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    flags: wp.array[wp.int32],
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
    how: Fill,
    partial: wp.array[float],
    partial_tint: wp.array[wp.vec4],
    partial_atom: wp.array[wp.int32],
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
):
    """Thread `t % 32` of group `t // 32` takes point `t % 32` of (brick, lane) pairs
    `t // 32`, `t // 32 + warps`, ...: a walked point's value, colour and largest term over
    the atoms within reach of its brick (`together`: a group's threads read the same atoms'
    routes in the same order) or of itself (the same terms in the same order, so the same
    values bit for bit). One lane keeps the point; several leave their shares in `partial`
    for `sum_kernel`."""
    t = wp.tid()
    group = t // BRICK_POINTS
    k = t - group * BRICK_POINTS
    v = vol[0]
    span = wp.vec3(float(BRICK_X - 1), float(BRICK_Y - 1), float(BRICK_Z - 1)) * v.h
    n = wp.min(count[0], how.last)
    q = LanePoint()
    q.lanes = how.lanes
    u = group
    while how.first + u // how.lanes < n:
        c = brick_corner(v, listed[how.first + u // how.lanes])
        i = brick_point(v, c, k)
        # nested: warp evaluates both operands of `and`, and i < 0 is no index
        if i >= 0:  # noqa: SIM102
            if flags[i] != 0:
                q.p = point_of(v, i)
                q.lane = u % how.lanes
                lo = q.p
                hi = q.p
                if how.together != 0:
                    lo = v.origin + wp.vec3(float(c[0]), float(c[1]), float(c[2])) * v.h
                    hi = lo + span
                s = _walk_pick(f, lo, hi, q, empty_sample())
                if how.lanes == 1:
                    keep_point(i, s, coef, tint, atoms)
                else:
                    w = u * BRICK_POINTS + k
                    partial[w] = s.value
                    partial_tint[w] = wp.vec4(s.color[0], s.color[1], s.color[2], s.weight)
                    partial_atom[w] = s.atom
        u += how.warps


@wp.kernel
@no_type_check
def sum_kernel(
    f: GeodesicField,
    vol: wp.array[VolumeInfo],
    flags: wp.array[wp.int32],
    listed: wp.array[wp.int32],
    count: wp.array[wp.int32],
    how: Fill,
    partial: wp.array[float],
    partial_tint: wp.array[wp.vec4],
    partial_atom: wp.array[wp.int32],
    coef: wp.array[float],
    tint: wp.array[wp.uint32],
    atoms: wp.array[wp.int32],
):
    """Point `t % 32` of listed brick `t // 32`: its lanes' shares added in lane order; the
    largest term the largest of theirs (ties: the lower original index, as one lane's
    walk)."""
    t = wp.tid()
    c = t // BRICK_POINTS
    k = t - c * BRICK_POINTS
    if c < wp.min(count[0], how.last):
        v = vol[0]
        i = brick_point(v, brick_corner(v, listed[c]), k)
        if i >= 0:  # noqa: SIM102  (as in _fill_points)
            if flags[i] != 0:
                s = empty_sample()
                order = f.gauss.order
                for q in range(how.lanes):
                    w = (c * how.lanes + q) * BRICK_POINTS + k
                    s.value += partial[w]
                    pt = partial_tint[w]
                    s.color = s.color + wp.vec3(pt[0], pt[1], pt[2])
                    a = partial_atom[w]
                    if a >= 0:
                        s = keep_largest(s, pt[3], a, order)
                keep_point(i, s, coef, tint, atoms)


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


_ALL = 2**31 - 1


def _fill(warps: int, together: bool, lanes: int, first: int, last: int) -> Fill:
    how = Fill()
    how.warps = warps
    how.together = int(together)
    how.lanes = lanes
    how.first = first
    how.last = last
    return how


class GeodesicVolume:
    """The grid's buffers on one device and the plan of their size."""

    def __init__(
        self,
        device: str,
        together: bool,
        lanes: int | None = None,
        fast_math: bool = True,
        registers: int = FILL_REGISTERS,
        threads: int | None = None,
    ) -> None:
        self.device = device
        self.fill = _device.compiled(_fill_points, fast_math, registers)
        self.gate = _device.compiled(_gate_points, fast_math)
        self.together = bool(together)
        """A brick's threads walk the atoms within reach of the brick, not each its own
        point's (the same values; on CUDA a group of 32 then reads the same routes together)."""
        self.fixed_lanes = lanes
        """Groups a brick (None: `lanes_for` the grid's size)."""
        dev = _wp.get_device(device)
        self.cuda = bool(dev.is_cuda)
        self.warps = int(dev.sm_count) * WARPS_PER_SM if self.cuda else 1
        self.threads = 1 if self.cuda else max(int(threads or _device.host_threads()), 1)
        """Host threads the fill is split across (the CPU device; 1 on CUDA)."""
        self.vol = _wp.zeros(1, dtype=VolumeInfo, device=device)
        self.count = _wp.zeros(1, dtype=_wp.int32, device=device)
        self.capacity = 0
        self.brick_capacity = 0
        self.lanes = 1
        self.planned = 0
        """Listed bricks the lanes' shares have room for; the rest one group each."""
        self.built: tuple[float, int] | None = None
        """(spacing, capacity) of the last build, so the next plan reads what it needed."""
        self._need: tuple[float, int, int] | None = None
        """`last_need` once read: frames that keep the grid (a camera turning over still
        positions) plan from it without reading the device again."""
        self._alloc(0)

    def lanes_for(self, points: int) -> int:
        """Groups of 32 threads a brick for a grid of `points`, from the bricks the plan
        expects (FILL_TARGET; 1 on the CPU)."""
        if self.fixed_lanes is not None:
            return max(int(self.fixed_lanes), 1)
        if not self.cuda:
            return 1
        bricks = max(LISTED_BRICKS * points / BRICK_POINTS, 1.0)
        lanes = 1
        while lanes < MAX_LANES and 2 * lanes * bricks <= FILL_TARGET * self.warps:
            lanes *= 2
        return lanes

    def _planned_for(self, points: int, lanes: int) -> int:
        """Listed bricks the lanes' shares make room for in a grid of `points` (with its
        SLACK already): none for one group a brick."""
        if lanes == 1:
            return 0
        return int(LISTED_BRICKS * points / BRICK_POINTS) + 64

    def _alloc(self, points: int) -> None:
        dev = self.device
        n = max(points, 1)
        bricks = int(points * BRICKS_PER_POINT) + 1
        self.lanes = self.lanes_for(points)
        self.planned = self._planned_for(points, self.lanes)
        shares = max(self.planned * self.lanes * BRICK_POINTS, 1)
        self.coef = _wp.zeros(n, dtype=float, device=dev)
        self.tint = _wp.zeros(n, dtype=_wp.uint32, device=dev)
        self.atoms = _wp.zeros(n, dtype=_wp.int32, device=dev)
        self.flags = _wp.zeros(n, dtype=_wp.int32, device=dev)
        self.brick_flags = _wp.zeros(bricks, dtype=_wp.int32, device=dev)
        self.brick_scan = _wp.zeros(bricks, dtype=_wp.int32, device=dev)
        self.listed = _wp.zeros(bricks, dtype=_wp.int32, device=dev)
        self.partial = _wp.zeros(shares, dtype=float, device=dev)
        self.partial_tint = _wp.zeros(shares, dtype=_wp.vec4, device=dev)
        self.partial_atom = _wp.zeros(shares, dtype=_wp.int32, device=dev)
        self.capacity = points
        self.brick_capacity = bricks

    @property
    def nbytes(self) -> int:
        arrays = (
            self.coef,
            self.tint,
            self.atoms,
            self.flags,
            self.brick_flags,
            self.brick_scan,
            self.listed,
            self.partial,
            self.partial_tint,
            self.partial_atom,
        )
        return sum(int(a.capacity) for a in arrays)

    def last_need(self) -> tuple[float, int, int] | None:
        """(spacing, points, listed bricks) the last build needed (synchronises; call once
        that build is done); bricks 0 when its grid did not fit (it listed nothing)."""
        if self.built is None:
            return None
        if self._need is not None:
            return self._need
        v = self.vol.numpy()[0]
        listed = int(self.count.numpy()[0]) if int(v["valid"]) else 0
        self._need = (self.built[0], int(v["points"]), listed)
        return self._need

    def fits(self, points: int) -> bool:
        """Whether the buffers hold `points` grid points."""
        return points <= self.capacity

    def bytes_for(self, points: int) -> int:
        """Device bytes of buffers for `points` grid points."""
        n = int(points * SLACK + 64)
        lanes = self.lanes_for(n)
        shares = self._planned_for(n, lanes) * lanes * BRICK_POINTS
        return n * 16 + (int(n * BRICKS_PER_POINT) + 1) * 12 + shares * 24

    def reserve(self, points: int) -> None:
        """Buffers for `points` grid points, with SLACK (graphs and fields that hold the old
        ones must be let go first)."""
        self._alloc(0)  # the old buffers go before the new ones are made
        self._alloc(int(points * SLACK) + 64)

    def build(self, f: GeodesicField, info: Any, h: float, cut: float) -> None:
        """This frame's coefficients from the routes in `f` (launches only)."""
        dev = self.device
        cap, bricks = self.capacity, self.brick_capacity
        self.built = (h, cap)
        self._need = None
        setup = (info, float(h), cap, bricks, self.vol)
        _wp.launch(setup_kernel, 1, setup, device=dev)
        if cap == 0:
            return
        gate = (f, self.vol, float(cut), self.coef, self.tint, self.atoms, self.flags, CELL_GATE)
        _wp.launch(self.gate, cap, gate, device=dev)
        _wp.launch(brick_kernel, bricks, (self.vol, self.flags, self.brick_flags), device=dev)
        _wp.utils.array_scan(self.brick_flags, self.brick_scan, inclusive=False)
        compact = (self.brick_flags, self.brick_scan, bricks - 1, self.listed, self.count)
        _wp.launch(compact_kernel, bricks, compact, device=dev)
        where = (f, self.vol, self.flags, self.listed, self.count)
        parts = (self.partial, self.partial_tint, self.partial_atom)
        keep = (self.coef, self.tint, self.atoms)
        threads = self.warps * BRICK_POINTS
        last = self.planned if self.lanes > 1 else _ALL
        how = _fill(self.warps, self.together, self.lanes, 0, last)
        if self.threads > 1 and self.lanes == 1:
            self._fill_on_threads(where, parts, keep)
        else:
            _wp.launch(self.fill, threads, (*where, how, *parts, *keep), device=dev)
        if self.lanes > 1:
            _wp.launch(sum_kernel, last * BRICK_POINTS, (*where, how, *parts, *keep), device=dev)
            # bricks past the plan (the molecule grew since): one group each
            rest = _fill(self.warps, self.together, 1, last, _ALL)
            _wp.launch(self.fill, threads, (*where, rest, *parts, *keep), device=dev)
        lines = cap // 5 + 1
        for axis in range(3):
            _wp.launch(prefilter_kernel, lines, (self.coef, self.vol, axis), device=dev)

    def _fill_on_threads(
        self, where: tuple[Any, ...], parts: tuple[Any, ...], keep: tuple[Any, ...]
    ) -> None:
        """The fill on the CPU device as runs of the listed bricks (`device.run_cuts`), each its
        own launch on a thread of the pool: a brick's points are its own, so the runs write
        apart, and the values are those of one launch bit for bit (the CPU device runs a launch
        on the thread that makes it; the fill is most of a geodesic frame there)."""
        listed = int(self.count.numpy()[0])  # the CPU device has run the scan already
        threads = self.warps * BRICK_POINTS
        launches = [
            (threads, (*where, _fill(self.warps, self.together, 1, lo, hi), *parts, *keep))
            for lo, hi in _device.run_cuts(listed, self.threads)
        ]
        _device.split_launch(self.fill, launches, self.device, self.threads)

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
