"""Direct ray casting of a density, one thread per pixel, generated for a `DensityModel`.

Every kernel that evaluates the density is made by `kernels_for(model)`, which closes over
the model's `@wp.func`s: another density gets its own kernels without a change here.
(This module keeps real annotations: warp resolves kernel annotations of closures eagerly.)

Per ray: clip to the grid box (and t >= 0), walk the cells front to back (3D DDA), skip cells
whose density bound says nothing there can matter, and sample the density only at the global
lattice t_k = k * dt inside the other cells. A fixed lattice (not one anchored at the box
entry) keeps images stable while the molecule moves and lets tests reproduce every sample.

Samples are taken four lattice steps at a time through the model's `value4`, which visits the
neighbours of the short segment once for all four points.

Iso mode: the marching kernels find the lattice interval of the first sign change of
S - iso (its index and the values at its ends); the shading kernel then cuts it into five
`REFINE_PASSES` times (four inner samples per pass, keeping the first sub-interval that
changes sign) and finishes with a secant step, so the hit is within dt / 5^passes of the
crossing; a Newton step from the shading sample (kept inside that bracket) then takes the
depth of most rays to within about 1e-5 dt of the surface. Refining in the shading kernel,
where all rays of a warp refine together, instead of in the march, where each ray refined
while its neighbours were still marching, took 13 % off the 1M-atom frame. A ray that
starts inside the surface (camera inside the molecule) looks for the first way out instead;
shading is two-sided.
Volume mode: emission-absorption front to back over the segments between consecutive
samples, each the transfer function integrated along the density's ramp from one sample to the
next (pre-integrated, segments.py), stopping at accumulated alpha >= 0.99; a density where the
transfer function is clear counts as its clear level, so skipped samples leave every segment as
it was. A ray's first segment starts at its origin when that lies inside the grid's box (the
camera inside the molecule), and its last ends at its depth limit (a cloud layer stopped at an
opaque surface), each sampled there. Its lattice (`tuning.VOLUME_STEPS` iso steps) is shifted
per pixel by a fixed hash (`pixel_jitter`) so thin transfer-function features do not alias
into rings.
"""

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, no_type_check

import numpy as np
import warp as wp

from protocol import RenderParams
from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.camera import CameraFrame
from server.render.cells import BRICK, PART_BITS, WALKED, GridInfo, cell_box, part_at
from server.render.density import GAUSSIAN, DensityModel, PartBounds
from server.render.segments import part, ramp

wp.set_module_options({"enable_backward": False})

TILE_W = 8
TILE_H = 4
TILE = TILE_W * TILE_H
REFINE_PASSES = 1
"""One pass, then the secant and Newton steps: on villin at 128x128 the depth stays within
2e-4 A of four passes' (two: 8e-5 A) and the image within one 8-bit level, on the classical and
geodesic densities; one pass fewer is one `value4` less per pixel (render_h200_refine.json)."""
REFINE_SHRINK = 5**REFINE_PASSES
"""Each refinement pass samples the bracket at 4 inner points (one `value4`), so the hit ends
within dt / 5^passes of the true crossing, then a secant step."""
STOP_ALPHA = 0.99
DEPTH_ALPHA = 0.5
"""Volume mode reports depth and atom id where accumulated opacity first reaches this."""

_STOP_ALPHA = wp.constant(STOP_ALPHA)  # type: ignore[no-untyped-call]
_DEPTH_ALPHA = wp.constant(DEPTH_ALPHA)  # type: ignore[no-untyped-call]

PART_MARGIN = 1.0 + 1.0e-4
"""Part bounds are raised by this relative margin before they are compared with the level:
float rounding in their sums must not put a part below it that a sample reaches."""

_PART_MARGIN = wp.constant(PART_MARGIN)  # type: ignore[no-untyped-call]
_PART_BITS = wp.constant(PART_BITS)  # type: ignore[no-untyped-call]
_WALKED = wp.constant(WALKED)  # type: ignore[no-untyped-call]
_BRICK = wp.constant(BRICK)  # type: ignore[no-untyped-call]
_TILE_W = wp.constant(TILE_W)  # type: ignore[no-untyped-call]
_TILE = wp.constant(TILE)  # type: ignore[no-untyped-call]
_NO_HIT = wp.constant(2147483647)  # type: ignore[no-untyped-call]
"""`hit_k` of a ray without a crossing (larger than any lattice index, for atomic minima)."""


@wp.struct
class CameraData:
    eye: wp.vec3
    right: wp.vec3
    up: wp.vec3
    forward: wp.vec3
    scale: float
    aspect: float
    ortho: int
    width: int
    height: int
    tiles_x: int
    x0: int
    y0: int
    full_width: int
    full_height: int
    part_axis: int
    """A part's slab of space (sort-last, `sortlast.py`): rays sample only where
    part_lo <= p[part_axis] < part_hi, and one lattice step past it (-1: everywhere)."""
    part_lo: float
    part_hi: float
    part_open: int
    """1: a ray may start inside the surface (the camera near the atoms), so a part entered at
    its near boundary with its first sample inside still looks for the way out; 0: it ends
    there, the part in front holding the crossing."""
    scene: int
    """1: the depth cue spans `scene_lo`..`scene_hi` (the whole system's grid box) rather than
    this grid's box, which holds only a part of it."""
    scene_lo: wp.vec3
    scene_hi: wp.vec3
    first_tile: int
    """The 8x4 tile of the image thread 0 of a launch takes (0 but in a run of the CPU
    device's launches split across host threads, `Renderer._ray_runs`)."""


@wp.struct
class Shading:
    background: wp.vec3
    uniform_color: wp.vec3
    key_dir: wp.vec3
    ambient: float
    diffuse: float
    specular: float
    shininess: float
    head_weight: float
    key_weight: float
    ao: int
    ao_step: float
    iso: float
    depth_cue: float
    coverage: int
    """1: write coverage to the alpha byte over no background (premultiplied colour), for
    images that are composited with others (layers); 0: an opaque image over the background."""


@wp.struct
class March:
    iso: float
    dt: float
    skip_below: float
    refine: int
    budget: int


@wp.struct
class Volume:
    """What volume mode reads: the pre-integrated segments (segments.py), the factor from
    density to their table entry, and the levels below which the transfer function is clear."""

    seg: wp.array2d[wp.vec4]
    last: int
    x_to_u: float
    flat: float
    """Densities at or below it are transparent (-1: none are): a segment end there counts as
    this level, so a segment reads the same whether its clear end was sampled or skipped."""
    ramps: int
    """1: a segment's density runs from its front sample's to its back one's; 0: its back
    sample's is held over it (the sample sum, a baseline)."""
    clear_level: float
    shade: int
    limit: wp.array[float]
    """Per pixel, where the march stops (`clip` = 1): the nearest opaque surface of another
    layer, so a cloud around a surface is drawn only in front of it."""
    clip: int


@wp.func
@no_type_check
def pixel_of(cam: CameraData, tid: int):
    """Thread -> pixel in 8x4 tiles, so a 32-thread warp casts neighbouring rays."""
    tile = tid // _TILE + cam.first_tile
    local = tid % _TILE
    x = (tile % cam.tiles_x) * _TILE_W + local % _TILE_W
    y = (tile // cam.tiles_x) * (_TILE // _TILE_W) + local // _TILE_W
    ok = wp.int32(0)
    if x < cam.width and y < cam.height:
        ok = 1
    return x, y, ok


@wp.func
@no_type_check
def camera_ray(cam: CameraData, x: int, y: int):
    """The ray of pixel (x, y) of the image (or tile: `x0`, `y0` place it in the full image,
    whose rays it computes with the same arithmetic, so tiles join into the same picture)."""
    u = (2.0 * (float(x + cam.x0) + 0.5) / float(cam.full_width) - 1.0) * cam.aspect * cam.scale
    v = (1.0 - 2.0 * (float(y + cam.y0) + 0.5) / float(cam.full_height)) * cam.scale
    if cam.ortho != 0:
        return cam.eye + cam.right * u + cam.up * v, cam.forward
    return cam.eye, wp.normalize(cam.forward + cam.right * u + cam.up * v)


@wp.func
@no_type_check
def slab(o: float, d: float, lo: float, hi: float, t0: float, t1: float):
    """Intersect [t0, t1] with the ray's parameter range inside one axis slab."""
    a = t0
    b = t1
    if wp.abs(d) < 1.0e-20:
        if o < lo or o > hi:
            a = 1.0
            b = 0.0
    else:
        inv = 1.0 / d
        ta = (lo - o) * inv
        tb = (hi - o) * inv
        a = wp.max(a, wp.min(ta, tb))
        b = wp.min(b, wp.max(ta, tb))
    return a, b


@wp.func
@no_type_check
def clip_box(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    t0, t1 = slab(o[0], d[0], lo[0], hi[0], 0.0, wp.inf)
    t0, t1 = slab(o[1], d[1], lo[1], hi[1], t0, t1)
    t0, t1 = slab(o[2], d[2], lo[2], hi[2], t0, t1)
    return t0, t1


@wp.func
@no_type_check
def part_range(cam: CameraData, o: wp.vec3, d: wp.vec3, t0: float, t1: float, ext: float):
    """[t0, t1] cut to the camera's part of space (`part_axis`), its far end `ext` (one
    lattice step) beyond the part's exit: the sample after a crossing or a volume segment that
    straddles the boundary to the next part is taken by this part, whose atoms reach that far.
    Also returns 1 when the part's near boundary, not `t0`, starts the range: the segment
    ending at the first sample there belongs to the part in front."""
    if cam.part_axis < 0:
        return t0, t1, wp.int32(0)
    ax = cam.part_axis
    a, b = slab(o[ax], d[ax], cam.part_lo, cam.part_hi, 0.0, wp.inf)
    if a > b:
        return t1, t0, wp.int32(0)
    entered = wp.int32(0)
    if a > t0:
        entered = 1
    return wp.max(t0, a), wp.min(t1, b + ext), entered


@wp.func
@no_type_check
def dda_axis(o: float, d: float, t: float, origin: float, h: float, n: int):
    """Start cell, step, parameter of the next cell boundary and boundary spacing."""
    q = wp.clamp((o + d * t - origin) / h, 0.0, float(n) - 0.5)
    c = wp.clamp(int(wp.floor(q)), 0, n - 1)
    step = wp.int32(0)
    t_next = float(wp.inf)
    t_delta = float(wp.inf)
    if d > 1.0e-20:
        step = 1
        t_next = (origin + float(c + 1) * h - o) / d
        t_delta = h / d
    elif d < -1.0e-20:
        step = -1
        t_next = (origin + float(c) * h - o) / d
        t_delta = -h / d
    return c, step, t_next, t_delta


@wp.func
@no_type_check
def axis_next(o: float, d: float, s: int, origin: float, h: float, c: int) -> float:
    """Ray parameter where it leaves slab c (of width h) along one axis, moving by s."""
    if s > 0:
        return (origin + float(c + 1) * h - o) / d
    if s < 0:
        return (origin + float(c) * h - o) / d
    return wp.inf


@wp.func
@no_type_check
def brick_exit(
    o: wp.vec3, d: wp.vec3, g: GridInfo, cx: int, cy: int, cz: int, sx: int, sy: int, sz: int
):
    """Leave the brick holding cell (cx, cy, cz): the exit parameter and the first cell past
    it (computed on the exit axis, so the walk always moves forward)."""
    bx = cx // _BRICK
    by = cy // _BRICK
    bz = cz // _BRICK
    hb = g.h * float(_BRICK)
    tbx = axis_next(o[0], d[0], sx, g.origin[0], hb, bx)
    tby = axis_next(o[1], d[1], sy, g.origin[1], hb, by)
    tbz = axis_next(o[2], d[2], sz, g.origin[2], hb, bz)
    tb = wp.min(wp.min(tbx, tby), tbz)
    p = o + d * tb
    nx = wp.clamp(int(wp.floor((p[0] - g.origin[0]) * g.inv_h)), bx * _BRICK, bx * _BRICK + 3)
    ny = wp.clamp(int(wp.floor((p[1] - g.origin[1]) * g.inv_h)), by * _BRICK, by * _BRICK + 3)
    nz = wp.clamp(int(wp.floor((p[2] - g.origin[2]) * g.inv_h)), bz * _BRICK, bz * _BRICK + 3)
    if tbx <= tby and tbx <= tbz:
        nx = bx * _BRICK + _BRICK
        if sx < 0:
            nx = bx * _BRICK - 1
    elif tby <= tbz:
        ny = by * _BRICK + _BRICK
        if sy < 0:
            ny = by * _BRICK - 1
    else:
        nz = bz * _BRICK + _BRICK
        if sz < 0:
            nz = bz * _BRICK - 1
    return tb, nx, ny, nz


@wp.func
@no_type_check
def in_grid(g: GridInfo, cx: int, cy: int, cz: int) -> bool:
    return cx >= 0 and cy >= 0 and cz >= 0 and cx < g.dims[0] and cy < g.dims[1] and cz < g.dims[2]


@wp.func
@no_type_check
def brick_of(g: GridInfo, cx: int, cy: int, cz: int) -> int:
    return ((cz // _BRICK) * g.bdims[1] + cy // _BRICK) * g.bdims[0] + cx // _BRICK


@wp.func
@no_type_check
def pixel_jitter(x: int, y: int) -> float:
    """A fixed per-pixel offset in [0, 1) (integer hash, identical on every device): volume
    samples sit at (k + jitter) dt, which turns the rings a shared lattice draws through thin
    transfer-function features into fine noise that does not flicker."""
    h = wp.uint32(x) * wp.uint32(1973) + wp.uint32(y) * wp.uint32(9277) + wp.uint32(26699)
    h = (h ^ (h >> wp.uint32(16))) * wp.uint32(0x7FEB352D)
    # 0x846CA68B in two halves: warp writes an integer literal as an int32, and the C++
    # compiler warns of one past its range (the bits are the same)
    h = (h ^ (h >> wp.uint32(15))) * (wp.uint32(0x846C) * wp.uint32(65536) + wp.uint32(0xA68B))
    h = h ^ (h >> wp.uint32(16))
    return float(h >> wp.uint32(8)) * (1.0 / 16777216.0)


@wp.func
@no_type_check
def pack_rgba(c: wp.vec3) -> wp.uint32:
    r = wp.uint32(wp.clamp(c[0], 0.0, 1.0) * 255.0 + 0.5)
    g = wp.uint32(wp.clamp(c[1], 0.0, 1.0) * 255.0 + 0.5)
    b = wp.uint32(wp.clamp(c[2], 0.0, 1.0) * 255.0 + 0.5)
    return r | (g << wp.uint32(8)) | (b << wp.uint32(16)) | (wp.uint32(255) << wp.uint32(24))


@wp.func
@no_type_check
def unpack_rgba(c: wp.uint32):
    """A packed RGBA8 pixel as its colour and alpha in [0, 1]."""
    col = wp.vec3(
        float(c & wp.uint32(255)),
        float((c >> wp.uint32(8)) & wp.uint32(255)),
        float((c >> wp.uint32(16)) & wp.uint32(255)),
    )
    return col / 255.0, float((c >> wp.uint32(24)) & wp.uint32(255)) / 255.0


@wp.func
@no_type_check
def pack_premultiplied(c: wp.vec3, a: float) -> wp.uint32:
    """A premultiplied colour with its coverage `a` in the alpha byte."""
    rgb = pack_rgba(c) & wp.uint32(0x00FFFFFF)
    return rgb | (wp.uint32(wp.clamp(a, 0.0, 1.0) * 255.0 + 0.5) << wp.uint32(24))


@wp.func
@no_type_check
def facing(n_raw: wp.vec3, d: wp.vec3) -> wp.vec3:
    """Outward normal from a density gradient, turned towards the viewer (two-sided)."""
    gl = wp.length(n_raw)
    n = -d
    if gl > 1.0e-30:
        n = -n_raw / gl
    if wp.dot(n, d) > 0.0:
        n = -n
    return n


@wp.func
@no_type_check
def lit(sh: Shading, base: wp.vec3, n: wp.vec3, v: wp.vec3, ao: float) -> wp.vec3:
    """Blinn-Phong: a headlight at the eye plus an optional key light fixed to the camera."""
    dh = wp.max(wp.dot(n, v), 0.0)
    diff = sh.head_weight * dh
    spec = sh.head_weight * wp.pow(dh, sh.shininess)
    if sh.key_weight > 0.0:
        dk = wp.max(wp.dot(n, sh.key_dir), 0.0)
        if dk > 0.0:
            hk = wp.normalize(sh.key_dir + v)
            diff += sh.key_weight * dk
            spec += sh.key_weight * wp.pow(wp.max(wp.dot(n, hk), 0.0), sh.shininess)
    c = base * (sh.ambient * ao + sh.diffuse * diff * (0.5 + 0.5 * ao))
    s = sh.specular * spec * ao
    return wp.vec3(
        wp.clamp(c[0] + s, 0.0, 1.0), wp.clamp(c[1] + s, 0.0, 1.0), wp.clamp(c[2] + s, 0.0, 1.0)
    )


@wp.func
@no_type_check
def fog(sh: Shading, g: GridInfo, cam: CameraData, t: float, c: wp.vec3) -> wp.vec3:
    """Depth cue: blend towards the background across the grid box's depth range."""
    if sh.depth_cue <= 0.0:
        return c
    lo = g.origin
    hi = g.box_hi
    if cam.scene != 0:
        lo = cam.scene_lo
        hi = cam.scene_hi
    center = (lo + hi) * 0.5
    radius = wp.length(hi - lo) * 0.5
    dc = wp.dot(center - cam.eye, cam.forward)
    near = wp.max(dc - radius, 0.0)
    far = dc + radius
    f = sh.depth_cue * wp.clamp((t - near) / wp.max(far - near, 1.0e-6), 0.0, 1.0)
    return c * (1.0 - f) + sh.background * f


@wp.func
@no_type_check
def add_segment(
    vol: Volume,
    sh: Shading,
    g: GridInfo,
    cam: CameraData,
    d: wp.vec3,
    n_raw: wp.vec3,
    t: float,
    vf: float,
    vb: float,
    fraction: float,
    acc: wp.vec3,
    alpha: float,
    t_depth: float,
):
    """Composite the segment ending at ray parameter t, its density running from vf to vb,
    behind what `acc` and `alpha` hold; its shading normal from the gradient `n_raw`. A
    segment cut short by the ray's ends is `fraction` of a step long (1: a whole step)."""
    uf = wp.max(vf * vol.x_to_u, 0.0)
    ub = wp.max(vb * vol.x_to_u, 0.0)
    e = ramp(vol.seg, vol.last, uf, ub)
    if fraction < 1.0:
        e = part(e, fraction)
    a_s = wp.clamp(e[3], 0.0, 1.0)
    out_acc = acc
    out_alpha = alpha
    out_depth = t_depth
    if a_s > 0.0:
        col = wp.vec3(e[0], e[1], e[2]) / a_s
        if vol.shade != 0:
            col = lit(sh, col, facing(n_raw, d), -d, 1.0)
        col = fog(sh, g, cam, t, col)
        out_acc = acc + col * ((1.0 - alpha) * a_s)
        out_alpha = alpha + (1.0 - alpha) * a_s
        if t_depth == wp.inf and out_alpha >= _DEPTH_ALPHA:
            out_depth = t
    return out_acc, out_alpha, out_depth


@wp.func
@no_type_check
def close_segment(
    vol: Volume,
    sh: Shading,
    g: GridInfo,
    cam: CameraData,
    d: wp.vec3,
    prev_k: int,
    prev_v: float,
    prev_g: wp.vec3,
    k_first: int,
    lead: float,
    jit: float,
    dt: float,
    t1: float,
    acc: wp.vec3,
    alpha: float,
    t_depth: float,
):
    """The segment after the last sample composited (lattice index `prev_k`), whose back sample
    the walk skipped as clear: it runs from `prev_v` down to the clear level, when that sample
    lies before the ray's end and the last one was above the level (segments only). Also
    returns whether it did."""
    out_acc = acc
    out_alpha = alpha
    out_depth = t_depth
    closed = wp.int32(0)
    t_next = (float(prev_k + 1) + jit) * dt
    if vol.ramps != 0 and prev_v > vol.flat and t_next < t1:
        closed = 1
        fr = float(1.0)
        if prev_k + 1 == k_first:
            fr = lead
        out_acc, out_alpha, out_depth = add_segment(
            vol, sh, g, cam, d, prev_g, t_next, prev_v, vol.flat, fr, acc, alpha, t_depth
        )
    return out_acc, out_alpha, out_depth, closed


@wp.func
@no_type_check
def clear(b: float, level: float, inclusive: int) -> bool:
    """A bound that says the density there cannot matter: below `level` (or at it)."""
    return b < level or (inclusive != 0 and b == level)


@wp.func
@no_type_check
def sample_clear(
    bound: wp.array[float],
    parts: wp.array[wp.int32],
    g: GridInfo,
    p: wp.vec3,
    level: float,
    inclusive: int,
    split: int,
) -> bool:
    """Whether a bound says the density at sample point p cannot matter: its cell's bound,
    or (`split` = 1) the bound of the part of the cell it lies in. The part is taken from the
    sample's own position, not from a cell walk, so it is exact."""
    c, bit = part_at(g, p)
    return clear(bound[c], level, inclusive) or (split != 0 and (parts[c] >> bit) & 1 != 0)


@wp.func
@no_type_check
def clear_samples(
    bound: wp.array[float],
    parts: wp.array[wp.int32],
    g: GridInfo,
    o: wp.vec3,
    d: wp.vec3,
    k: int,
    shift: float,
    dt: float,
    level: float,
    split: int,
) -> int:
    """How many of the lattice samples k, k + 1, k + 2, k + 3 (t = (k + shift) dt), counted
    from k, lie where a bound says the density is below `level`: in a cell whose bound is,
    or in a part of a cell whose part bound is (`split` = 1)."""
    n = wp.int32(0)
    going = wp.int32(1)
    while going != 0 and n < 4:
        if sample_clear(bound, parts, g, o + d * ((float(k + n) + shift) * dt), level, 0, split):
            n += 1
        else:
            going = 0
    return n


@wp.func
@no_type_check
def walk_start(o: wp.vec3, d: wp.vec3, t: float, g: GridInfo):
    """The state `walk` starts from at ray parameter t: the cell, the step, the parameters of
    the next cell boundary and the boundary spacing on each axis, and the most cells a walk
    can visit."""
    cx0, sx, tx0, dtx = dda_axis(o[0], d[0], t, g.origin[0], g.h, g.dims[0])
    cy0, sy, ty0, dty = dda_axis(o[1], d[1], t, g.origin[1], g.h, g.dims[1])
    cz0, sz, tz0, dtz = dda_axis(o[2], d[2], t, g.origin[2], g.h, g.dims[2])
    left = g.dims[0] + g.dims[1] + g.dims[2] + 3
    return (
        int(cx0), int(cy0), int(cz0), sx, sy, sz,
        float(tx0), float(ty0), float(tz0), dtx, dty, dtz, left,
    )  # fmt: skip


@wp.func
@no_type_check
def next_cell(
    g: GridInfo,
    cx: int,
    cy: int,
    cz: int,
    tx: float,
    ty: float,
    tz: float,
    sx: int,
    sy: int,
    sz: int,
    dtx: float,
    dty: float,
    dtz: float,
):
    """One DDA step: the cell the ray enters next, the parameters of its next boundaries,
    and 1 while that cell is inside the grid."""
    inside = wp.int32(1)
    if tx <= ty and tx <= tz:
        cx += sx
        tx += dtx
        if cx < 0 or cx >= g.dims[0]:
            inside = 0
    elif ty <= tz:
        cy += sy
        ty += dty
        if cy < 0 or cy >= g.dims[1]:
            inside = 0
    else:
        cz += sz
        tz += dtz
        if cz < 0 or cz >= g.dims[2]:
            inside = 0
    return cx, cy, cz, tx, ty, tz, inside


@wp.func
@no_type_check
def walk(
    bound: wp.array[float],
    parts: wp.array[wp.int32],
    brick_bound: wp.array[float],
    g: GridInfo,
    o: wp.vec3,
    d: wp.vec3,
    t1: float,
    dt: float,
    shift: float,
    level: float,
    inclusive: int,
    skip: int,
    split: int,
    k: int,
    cx: int,
    cy: int,
    cz: int,
    sx: int,
    sy: int,
    sz: int,
    tx: float,
    ty: float,
    tz: float,
    dtx: float,
    dty: float,
    dtz: float,
    left: int,
):
    """Walk the cells (3D DDA, whole bricks where their bound allows) from the current cell
    to the first lattice sample t_k = (k + shift) dt that lies in a cell whose bound does not
    let it be skipped, and not in a part of it whose bound does (`parts`, when `split` = 1;
    `skip` = 0: nothing is skipped). Returns the new walk state, whether samples were jumped
    (the previous sample's value is then unknown) and whether the ray is still in the grid
    with a sample to take."""
    jumped = wp.int32(0)
    active = wp.int32(1)
    ready = wp.int32(0)
    while ready == 0 and active != 0:
        if (
            skip != 0
            and g.bricks != 0
            and clear(brick_bound[brick_of(g, cx, cy, cz)], level, inclusive)
        ):
            tb, nx, ny, nz = brick_exit(o, d, g, cx, cy, cz, sx, sy, sz)
            k_end = int(wp.ceil(wp.min(tb, t1) / dt - shift))
            if k_end > k:
                jumped = 1
                k = k_end
            left -= 1
            if tb >= t1 or not in_grid(g, nx, ny, nz) or left <= 0:
                active = 0
            else:
                cx = nx
                cy = ny
                cz = nz
                tx = axis_next(o[0], d[0], sx, g.origin[0], g.h, cx)
                ty = axis_next(o[1], d[1], sy, g.origin[1], g.h, cy)
                tz = axis_next(o[2], d[2], sz, g.origin[2], g.h, cz)
            continue
        t_exit = wp.min(wp.min(tx, ty), wp.min(tz, t1))
        cell = (cz * g.dims[1] + cy) * g.dims[0] + cx
        if skip != 0 and clear(bound[cell], level, inclusive):
            k_end = int(wp.ceil(t_exit / dt - shift))
            if k_end > k:
                jumped = 1
                k = k_end
        elif (float(k) + shift) * dt < t_exit:
            ready = 1
            if skip != 0 and split != 0 and (parts[cell] & _PART_BITS) != 0:
                # the cell's samples in its parts below the level
                going = wp.int32(1)
                while going != 0 and (float(k) + shift) * dt < t_exit:
                    p = o + d * ((float(k) + shift) * dt)
                    if sample_clear(bound, parts, g, p, level, inclusive, 1):
                        k += 1
                        jumped = 1
                    else:
                        going = 0
                ready = 1 - going
        if ready == 0:
            left -= 1
            if t_exit >= t1 or left <= 0:
                active = 0
            else:
                cx, cy, cz, tx, ty, tz, active = next_cell(
                    g, cx, cy, cz, tx, ty, tz, sx, sy, sz, dtx, dty, dtz
                )
    return k, cx, cy, cz, tx, ty, tz, left, jumped, active


@wp.func
@no_type_check
def side_of(v: float, iso: float) -> int:
    """1 above (or at) the iso level, 0 below."""
    above = wp.int32(0)
    if v >= iso:
        above = 1
    return above


@wp.func
@no_type_check
def side_change(v4: wp.vec4, iso: float, inside: int, q_from: int) -> int:
    """The first of the four samples, from `q_from` on, on the other side of the iso level
    than `inside`; -1 when none is."""
    hit = wp.int32(-1)
    for q in range(4):
        if hit < 0 and q >= q_from and side_of(v4[q], iso) != inside:
            hit = q
    return hit


@wp.func
@no_type_check
def parts_below(bounds: PartBounds, stop_above: float):
    """A walked cell's bound and part bits from its parts' bounds: the largest bound, and
    the bits of the parts below `stop_above` (each bound raised by PART_MARGIN for float
    rounding) with WALKED."""
    v = bounds * _PART_MARGIN
    mask = wp.int32(0)
    for s in range(27):
        if v[s] < stop_above:
            mask = mask | (1 << s)
    return wp.max(v), mask | _WALKED


def _make(
    model: DensityModel,
    fast_math: bool,
    max_registers: int,
    volume_max_registers: int,
    parts: bool,
    count: bool,
) -> "RaycastKernels":
    Field = model.field
    # whether the walked cells mark their parts and the rays skip samples in them: a
    # constant of the generated code, so kernels without parts carry none of it
    split = 1 if parts and model.part_bounds is not None else 0
    # whether the marching kernels write each ray's density passes to `counts`: a constant
    # of the generated code, so the kernels that draw compile without the writes
    counting = 1 if count else 0
    options = {"fast_math": bool(fast_math)}
    # the ray-marching and shading kernels carry many live values; capping their registers
    # trades a few spills for more resident warps to hide the latency of the neighbour gathers
    regs = max_registers if max_registers > 0 else None
    volume_regs = volume_max_registers if volume_max_registers > 0 else None
    value = model.value
    value_grad = model.value_grad
    sample = model.sample
    box_bound = model.box_bound
    part_bounds = model.part_bounds
    value4 = model.value4
    value_grad4 = model.value_grad4
    if value4 is None:

        @wp.func
        @no_type_check
        def value4_each(f: Field, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
            return wp.vec4(
                value(f, o + d * ts[0]),
                value(f, o + d * ts[1]),
                value(f, o + d * ts[2]),
                value(f, o + d * ts[3]),
            )

        value4 = value4_each
    if value_grad4 is None:

        @wp.func
        @no_type_check
        def value_grad4_each(f: Field, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
            return (
                value_grad(f, o + d * ts[0]),
                value_grad(f, o + d * ts[1]),
                value_grad(f, o + d * ts[2]),
                value_grad(f, o + d * ts[3]),
            )

        value_grad4 = value_grad4_each
    value4_level = model.value4_level
    if value4_level is None:

        @wp.func
        @no_type_check
        def value4_exact(f: Field, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float) -> wp.vec4:
            return value4(f, o, d, ts)

        value4_level = value4_exact
    value_grad4_level = model.value_grad4_level
    if value_grad4_level is None:

        @wp.func
        @no_type_check
        def value_grad4_exact(f: Field, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float):
            return value_grad4(f, o, d, ts)

        value_grad4_level = value_grad4_exact
    side4 = model.side4 if model.side4 is not None else value4_level

    @wp.func
    @no_type_check
    def refine(
        f: Field,
        o: wp.vec3,
        d: wp.vec3,
        t_lo: float,
        t_hi: float,
        v_lo: float,
        v_hi: float,
        iso: float,
        inside: int,
        passes: int,
    ):
        """Narrow [t_lo, t_hi] (side of t_lo = `inside`) to its first fifth that changes side,
        `passes` times, then one secant step. A negative or infinite v_lo or v_hi means its
        value was never computed (a skipped cell, a side the march decided without it): it
        is computed only if the last bracket still ends there. Returns the secant point and
        the final bracket."""
        lo = float(t_lo)
        hi = float(t_hi)
        vlo = float(v_lo)
        vhi = float(v_hi)
        for _i in range(passes):
            w = (hi - lo) * 0.2
            v4 = value4(f, o, d, wp.vec4(lo + w, lo + 2.0 * w, lo + 3.0 * w, lo + 4.0 * w))
            first = wp.int32(4)
            for q in range(4):
                side = wp.int32(0)
                if v4[3 - q] >= iso:
                    side = 1
                if side != inside:
                    first = 3 - q
            if first == 4:
                lo = lo + 4.0 * w
                vlo = v4[3]
            else:
                hi = lo + float(first + 1) * w
                vhi = v4[first]
                if first > 0:
                    vlo = v4[first - 1]
                lo = lo + float(first) * w
        if vlo < 0.0 or vlo == wp.inf:
            vlo = value(f, o + d * lo)
        if vhi == wp.inf:
            vhi = value(f, o + d * hi)
        u = wp.float32(0.5)
        den = vhi - vlo
        if wp.abs(den) > 1.0e-30:
            u = wp.clamp((iso - vlo) / den, 0.0, 1.0)
        return lo + (hi - lo) * u, lo, hi

    @wp.func
    @no_type_check
    def occlusion(f: Field, p: wp.vec3, n: wp.vec3, sh: Shading) -> float:
        """Density-based ambient occlusion: how much density lies just outside the surface."""
        a = sh.ao_step
        v = value4(f, p, n, wp.vec4(a, 2.0 * a, 3.0 * a, 4.0 * a)) / sh.iso
        occ = wp.min(v[0], 1.0) + wp.min(v[1], 1.0) + wp.min(v[2], 1.0) + wp.min(v[3], 1.0)
        return 1.0 - 0.8 * occ * 0.25

    @wp.func
    @no_type_check
    def walked_whole(f: Field, c: int, stop_above: float):
        """The bound of cell c from a walk over the atoms within reach of it; no part is
        known to be below the level."""
        lo, hi = cell_box(f.info[0], c)
        return box_bound(f, lo, hi, stop_above), wp.int32(0)

    walked = walked_whole
    bound_lanes_kernel = None
    if split != 0:

        @wp.func
        @no_type_check
        def walked_parts(f: Field, c: int, stop_above: float):
            """The bound of cell c from a walk over the atoms within reach of it: the
            largest of its parts' bounds, and the bits of the parts below `stop_above`
            (with a relative margin of PART_MARGIN for float rounding) with WALKED."""
            lo, hi = cell_box(f.info[0], c)
            return parts_below(part_bounds(f, lo, hi, stop_above), stop_above)

        walked = walked_parts
        part_bounds_lane = model.part_bounds_lane
        if part_bounds_lane is not None:

            @wp.kernel(enable_backward=False, module="unique", module_options=options)
            @no_type_check
            def bound_lanes_kernel(
                f: Field,
                stop_above: float,
                blocks: int,
                lanes: int,
                work: wp.array[wp.int32],
                work_count: wp.array[wp.int32],
                out: wp.array[float],
                parts: wp.array[wp.int32],
            ):
                """`bound_kernel`'s part walk with `lanes` threads a listed cell: a tiled
                launch of `blocks` blocks of `lanes` threads, each block striding over the
                list, each lane taking its share of the cell's atoms and the block adding
                the shares (in the same order every launch: a frame's bounds do not vary)."""
                b, lane = wp.tid()
                n = wp.min(work_count[0], work.shape[0])
                i = b
                while i < n:
                    c = work[i]
                    lo, hi = cell_box(f.info[0], c)
                    share = part_bounds_lane(f, lo, hi, lane, lanes)
                    total = wp.tile_reduce(wp.add, wp.tile(share, preserve_type=True))[0]
                    if lane == 0:
                        bound, mask = parts_below(total, stop_above)
                        out[c] = bound
                        parts[c] = mask
                    i += blocks

    bound_settle_kernel, bound_kernel = _bound_kernels(Field, walked, options)
    whole_settle_kernel, whole_bound_kernel = bound_settle_kernel, bound_kernel
    if split != 0:
        whole_settle_kernel, whole_bound_kernel = _bound_kernels(Field, walked_whole, options)

    @wp.kernel(enable_backward=False, module="unique", module_options=options)
    @no_type_check
    def evaluate_kernel(
        f: Field,
        points: wp.array[wp.vec3],
        values: wp.array[float],
        value_grads: wp.array[wp.vec4],
        colors: wp.array[wp.vec4],
        atoms: wp.array[wp.int32],
    ):
        i = wp.tid()
        p = points[i]
        values[i] = value(f, p)
        value_grads[i] = value_grad(f, p)
        s = sample(f, p)
        c = s.color
        if s.weight > 0.0:
            c = s.color / s.weight
        colors[i] = wp.vec4(c[0], c[1], c[2], s.value)
        atoms[i] = s.atom

    @wp.kernel(enable_backward=False, module="unique", module_options=options)
    @no_type_check
    def histogram_kernel(
        f: Field, n_side: int, x_scale: float, bins: int, counts: wp.array[wp.int32]
    ):
        i, j, k = wp.tid()
        g = f.info[0]
        if g.valid == 0:
            return
        s = 1.0 / float(n_side)
        frac = wp.vec3((float(i) + 0.5) * s, (float(j) + 0.5) * s, (float(k) + 0.5) * s)
        p = g.origin + wp.cw_mul(g.box_hi - g.origin, frac)
        v = value(f, p)
        if v > 0.0:
            b = int(wp.min(v * x_scale, float(bins - 1)))
            wp.atomic_add(counts, b, 1)

    @wp.func
    @no_type_check
    def march_iso(
        f: Field,
        m: March,
        o: wp.vec3,
        d: wp.vec3,
        t_from: float,
        t1: float,
        k: int,
        first: int,
        inside: int,
        prev_v: float,
        budget: int,
        stop_inside: int,
    ):
        """March one ray from lattice sample k (the walk starts in the cell at `t_from`) to
        its first crossing, taking at most `budget` density passes (0: no limit). Returns
        the crossing's lattice index (-1: none) with the values on both sides of it (-1 or
        +inf: unknown, as `side4` gives them), whether the ray still has work (budget spent)
        and the state that resumes it: k, first, inside and the last sample's value, and the
        density passes taken. Refinement is left to the shading kernel, where every ray of a warp
        refines at once. `stop_inside` = 1: a first sample inside the surface ends the ray
        without a hit (a sort-last part entered at its near boundary: the crossing lies in
        the part in front of it)."""
        g = f.info[0]
        dt = m.dt
        s_hit = wp.int32(-1)
        v_hi = float(-1.0)
        cx, cy, cz, sx, sy, sz, tx, ty, tz, dtx, dty, dtz, left = walk_start(o, d, t_from, g)
        active = wp.int32(1)
        more = wp.int32(0)
        passes = wp.int32(0)
        # one density pass per outer iteration: the cheap cell walk to the next lattice
        # sample that needs the density diverges, the expensive pass does not
        while active != 0:
            k, cx, cy, cz, tx, ty, tz, left, jumped, active = walk(
                f.bound, f.parts, f.brick_bound, g, o, d, t1, dt, 0.0, m.skip_below, 0,
                1 - inside, split, k, cx, cy, cz, sx, sy, sz, tx, ty, tz, dtx, dty, dtz, left,
            )  # fmt: skip
            if jumped != 0:
                first = 0
                prev_v = -1.0
            if active != 0 and budget > 0 and passes >= budget:
                more = 1
                active = 0
            if active != 0:
                passes += 1
                # four lattice samples; the pass may run past this cell, which only means
                # the next cells start with k already beyond their entry
                ts = wp.vec4(float(k) * dt, float(k + 1) * dt, float(k + 2) * dt, float(k + 3) * dt)
                v4 = side4(f, o, d, ts, m.iso)
                q_from = wp.int32(0)
                if first == 1:  # the ray's first sample says which side it starts on
                    first = 0
                    inside = side_of(v4[0], m.iso)
                    q_from = 1
                    if inside != 0 and stop_inside != 0:
                        q_from = 4  # nothing to look for: the ray ends
                        active = 0
                q_hit = side_change(v4, m.iso, inside, q_from)
                if active == 0:
                    q_hit = -1
                if q_hit >= 0:
                    if q_hit > 0:
                        prev_v = v4[q_hit - 1]
                    s_hit = k + q_hit
                    v_hi = v4[q_hit]
                    active = 0
                else:
                    prev_v = v4[3]
                    k += 4
        return s_hit, wp.vec2(prev_v, v_hi), more, k, first, inside, prev_v, passes

    @wp.kernel(
        enable_backward=False, module="unique", module_options=options, cuda_max_registers=regs
    )
    @no_type_check
    def iso_march_kernel(
        f: Field,
        cam: CameraData,
        m: March,
        hit_k: wp.array[wp.int32],
        hit_v: wp.array[wp.vec2],
        queue: wp.array[wp.vec4i],
        queue_v: wp.array[float],
        queue_len: wp.array[wp.int32],
        found: wp.array[wp.int32],
        counts: wp.array[wp.int32],
        resume: int,
    ):
        """March rays to the lattice interval of their first crossing (`hit_k`, `hit_v`).

        First phase (`resume` = 0, a thread per pixel): every ray marches up to `m.budget`
        passes; rays with more to do go to the queue, so the few long ones (grazing the
        surface) continue in full warps. Second phase (`resume` = 1, a thread per queued ray;
        threads past the queue's length return at once): each queued ray to its end."""
        tid = wp.tid()
        g = f.info[0]
        ray = tid
        k = wp.int32(0)
        first = wp.int32(1)
        inside = wp.int32(0)
        prev_v = float(-1.0)
        budget = m.budget
        if resume != 0:
            if tid >= queue_len[0]:
                return
            e = queue[tid]
            ray = e[0]
            k = e[1]
            first = e[2]
            inside = e[3]
            prev_v = queue_v[tid]
            budget = 0
        x, y, ok = pixel_of(cam, ray)
        if ok == 0:
            return
        pix = y * cam.width + x
        o, d = camera_ray(cam, x, y)
        t0, t1 = clip_box(o, d, g.origin, g.box_hi)
        t0, t1, entered = part_range(cam, o, d, t0, t1, m.dt)
        stop_inside = wp.int32(0)
        if entered != 0 and cam.part_open == 0 and resume == 0:
            stop_inside = 1
        s_hit = wp.int32(-1)
        v = wp.vec2(-1.0, -1.0)
        passes = wp.int32(0)
        if resume != 0:
            t0 = float(k) * m.dt
        elif g.valid != 0 and t0 < t1:
            k = int(wp.ceil(t0 / m.dt))
        if resume != 0 or (g.valid != 0 and t0 < t1):
            s_hit, v, more, k, first, inside, prev_v, passes = march_iso(
                f, m, o, d, t0, t1, k, first, inside, prev_v, budget, stop_inside
            )
            if more != 0:
                slot = wp.atomic_add(queue_len, 0, 1)
                queue[slot] = wp.vec4i(tid, k, first, inside)
                queue_v[slot] = prev_v
                found[slot] = _NO_HIT
        if counting != 0:
            if resume == 0:
                counts[pix] = passes
            else:
                counts[pix] = counts[pix] + passes
        if resume == 0:
            hit_k[pix] = _NO_HIT
        if s_hit >= 0:
            hit_k[pix] = s_hit
            hit_v[pix] = v
        elif resume == 0:
            hit_v[pix] = v

    @wp.kernel(
        enable_backward=False, module="unique", module_options=options, cuda_max_registers=regs
    )
    @no_type_check
    def iso_split_kernel(
        f: Field,
        cam: CameraData,
        m: March,
        hit_k: wp.array[wp.int32],
        hit_v: wp.array[wp.vec2],
        queue: wp.array[wp.vec4i],
        queue_v: wp.array[float],
        queue_len: wp.array[wp.int32],
        found: wp.array[wp.int32],
        counts: wp.array[wp.int32],
        lanes: int,
        rays_per_launch: int,
    ):
        """Second phase with `lanes` threads per queued ray: lane j of round r takes the
        four samples from k + 3 (r lanes + j) (neighbouring groups share a sample, so every
        interval is inside one group), skips them when their cells' bounds clear them, and
        reports its first change of side; the smallest sample index wins (`found`, and an
        atomic minimum into `hit_k` whichever lane finishes first). The values at the
        winning interval stay unknown (the first phase left -1): shading computes them."""
        tid = wp.tid()
        lane = tid % lanes
        i = tid // lanes
        n_queued = queue_len[0]
        while i < n_queued:
            e = queue[i]
            x, y, _ok = pixel_of(cam, e[0])
            pix = y * cam.width + x
            g = f.info[0]
            o, d = camera_ray(cam, x, y)
            t0, t1 = clip_box(o, d, g.origin, g.box_hi)
            _t0, t1, _entered = part_range(cam, o, d, t0, t1, m.dt)
            dt = m.dt
            k0 = e[1]
            inside = e[3]
            rnd = wp.int32(0)
            going = wp.int32(1)
            while going != 0:
                gs = k0 + 3 * (rnd * lanes + lane)
                rnd += 1
                if float(gs) * dt >= t1 or wp.atomic_add(found, i, 0) < gs:
                    going = 0
                    continue
                ts = wp.vec4(
                    float(gs) * dt, float(gs + 1) * dt, float(gs + 2) * dt, float(gs + 3) * dt
                )
                need = wp.int32(1)
                if inside == 0:
                    clear_n = clear_samples(
                        f.bound, f.parts, g, o, d, gs, 0.0, dt, m.skip_below, split
                    )
                    need = 4 - clear_n
                if need != 0:
                    if counting != 0:
                        wp.atomic_add(counts, pix, 1)
                    v4 = side4(f, o, d, ts, m.iso)
                    q_from = wp.int32(1)
                    if gs == k0:
                        q_from = 0
                    q_hit = side_change(v4, m.iso, inside, q_from)
                    if q_hit >= 0:
                        s_hit = gs + q_hit
                        wp.atomic_min(found, i, s_hit)
                        wp.atomic_min(hit_k, pix, s_hit)
                        going = 0
            i += rays_per_launch

    @wp.kernel(
        enable_backward=False, module="unique", module_options=options, cuda_max_registers=regs
    )
    @no_type_check
    def iso_shade_kernel(
        f: Field,
        cam: CameraData,
        m: March,
        sh: Shading,
        hit_k: wp.array[wp.int32],
        hit_v: wp.array[wp.vec2],
        rgba: wp.array[wp.uint32],
        depth: wp.array[float],
        ids: wp.array[wp.int32],
    ):
        """Refine each ray's crossing inside its lattice interval, then shade it. Refining
        here rather than in the march keeps a warp's refinement passes together: in the
        march, each ray would refine while its neighbours were still marching."""
        x, y, ok = pixel_of(cam, wp.tid())
        if ok == 0:
            return
        pix = y * cam.width + x
        s_hit = hit_k[pix]
        if s_hit == _NO_HIT:
            rgba[pix] = pack_rgba(sh.background)
            if sh.coverage != 0:
                rgba[pix] = wp.uint32(0)
            depth[pix] = wp.inf
            ids[pix] = -1
            return
        o, d = camera_ray(cam, x, y)
        t_lo = float(s_hit - 1) * m.dt
        t_hi = float(s_hit) * m.dt
        v = hit_v[pix]
        v_lo = v[0]
        v_hi = v[1]
        if v_hi < 0.0:
            ends = value4(f, o, d, wp.vec4(t_lo, t_lo, t_hi, t_hi))
            v_lo = ends[0]
            v_hi = ends[3]
        inside = wp.int32(0)
        if v_hi < m.iso:
            inside = 1
        t, b_lo, b_hi = refine(f, o, d, t_lo, t_hi, v_lo, v_hi, m.iso, inside, m.refine)
        p = o + d * t
        s = sample(f, p)
        # one Newton step along the ray from the sample shading needs anyway: the depth
        # lands much closer to the surface than the secant point (kept in the bracket)
        slope = wp.dot(s.grad, d)
        if wp.abs(slope) > 1.0e-30:
            t = wp.clamp(t + (m.iso - s.value) / slope, b_lo, b_hi)
        n = facing(s.grad, d)
        base = sh.uniform_color
        if s.weight > 0.0:
            base = s.color / s.weight
        ao = wp.float32(1.0)
        if sh.ao != 0:
            ao = occlusion(f, p, n, sh)
        c = fog(sh, f.info[0], cam, t, lit(sh, base, n, -d, ao))
        rgba[pix] = pack_rgba(c)
        depth[pix] = t
        ids[pix] = s.atom

    @wp.kernel(
        enable_backward=False,
        module="unique",
        module_options=options,
        cuda_max_registers=volume_regs,
    )
    @no_type_check
    def volume_kernel(
        f: Field,
        cam: CameraData,
        m: March,
        vol: Volume,
        sh: Shading,
        rgba: wp.array[wp.uint32],
        depth: wp.array[float],
        ids: wp.array[wp.int32],
        counts: wp.array[wp.int32],
    ):
        x, y, ok = pixel_of(cam, wp.tid())
        if ok == 0:
            return
        pix = y * cam.width + x
        passes = wp.int32(0)
        acc = wp.vec3(0.0, 0.0, 0.0)
        alpha = wp.float32(0.0)
        t_depth = float(wp.inf)
        g = f.info[0]
        o, d = camera_ray(cam, x, y)
        t0, t_box = clip_box(o, d, g.origin, g.box_hi)
        t0, t_box, entered = part_range(cam, o, d, t0, t_box, m.dt)
        t1 = t_box
        if vol.clip != 0:
            t1 = wp.min(t1, vol.limit[pix])
        if g.valid != 0 and t0 < t1:
            dt = m.dt
            flat = vol.flat
            jit = pixel_jitter(x + cam.x0, y + cam.y0)  # the whole image's pixel
            k = int(wp.ceil(t0 / dt - jit))
            cx, cy, cz, sx, sy, sz, tx, ty, tz, dtx, dty, dtz, left = walk_start(o, d, t0, g)
            # the last sample composited: its lattice index (-2: none yet), value, gradient
            prev_k = wp.int32(-2)
            prev_v = float(0.0)
            prev_g = wp.vec3(0.0, 0.0, 0.0)
            # a ray that starts inside the grid's box (the camera inside the molecule) starts
            # with a sample at its origin: its first segment runs from there to its first
            # lattice sample, a `lead` of a step (outside the box the density is zero)
            k_first = k
            lead = float(1.0)
            if vol.ramps != 0 and t0 <= 0.0:
                s0 = value_grad(f, o + d * t0)
                prev_k = k_first - 1
                prev_v = wp.max(s0[3], flat)
                prev_g = wp.vec3(s0[0], s0[1], s0[2])
                lead = (float(k_first) + jit) - t0 / dt
            active = wp.int32(1)
            while active != 0:
                k, cx, cy, cz, tx, ty, tz, left, _jumped, active = walk(
                    f.bound, f.parts, f.brick_bound, g, o, d, t1, dt, jit, vol.clear_level, 1,
                    1, split, k, cx, cy, cz, sx, sy, sz, tx, ty, tz, dtx, dty, dtz, left,
                )  # fmt: skip
                if prev_k != -2 and k != prev_k + 1:
                    # the walk skipped the sample after the last one (clear there): close the
                    # segment that sample would have ended, at the clear level
                    acc, alpha, t_depth, closed = close_segment(
                        vol, sh, g, cam, d, prev_k, prev_v, prev_g, k_first, lead, jit, dt, t1,
                        acc, alpha, t_depth,
                    )  # fmt: skip
                    if closed != 0:
                        prev_k = -2
                        if alpha >= _STOP_ALPHA:
                            active = 0
                if active != 0:
                    passes += 1
                    # four samples per pass, with gradients when shaded
                    ts = wp.vec4(
                        (float(k) + jit) * dt,
                        (float(k + 1) + jit) * dt,
                        (float(k + 2) + jit) * dt,
                        (float(k + 3) + jit) * dt,
                    )
                    g0 = wp.vec4(0.0, 0.0, 0.0, 0.0)
                    g1 = wp.vec4(0.0, 0.0, 0.0, 0.0)
                    g2 = wp.vec4(0.0, 0.0, 0.0, 0.0)
                    g3 = wp.vec4(0.0, 0.0, 0.0, 0.0)
                    vals = wp.vec4(0.0, 0.0, 0.0, 0.0)
                    # below the clear level the transfer function is transparent: a model
                    # may answer there with any value below it (value4_level)
                    if vol.shade != 0:
                        g0, g1, g2, g3 = value_grad4_level(f, o, d, ts, vol.clear_level)
                        vals = wp.vec4(g0[3], g1[3], g2[3], g3[3])
                    else:
                        vals = value4_level(f, o, d, ts, vol.clear_level)
                    for q in range(4):
                        tq = ts[q]
                        if active != 0 and tq < t1:
                            gq = g0
                            if q == 1:
                                gq = g1
                            elif q == 2:
                                gq = g2
                            elif q == 3:
                                gq = g3
                            grad = wp.vec3(gq[0], gq[1], gq[2])
                            vq = wp.max(vals[q], flat)
                            # the segment from the sample before: its value when it was taken,
                            # else the clear level (it was skipped), else this one's (a ray's
                            # first sample where nothing is clear). Its normal sums the
                            # gradients of its ends above the clear level, which a skipped
                            # sample is not: skipping leaves every segment as it was.
                            vf = vq
                            n_raw = grad
                            fr = float(1.0)
                            skip_first = entered != 0 and k + q == k_first
                            if vol.ramps != 0:
                                if vq <= flat:
                                    n_raw = wp.vec3(0.0, 0.0, 0.0)
                                if prev_k == k + q - 1:
                                    vf = prev_v
                                    if prev_v > flat:
                                        n_raw = n_raw + prev_g
                                elif flat >= 0.0:
                                    vf = flat
                                if k + q == k_first:
                                    fr = lead
                            if not skip_first:
                                acc, alpha, t_depth = add_segment(
                                    vol, sh, g, cam, d, n_raw, tq, vf, vq, fr, acc, alpha,
                                    t_depth,
                                )  # fmt: skip
                            prev_k = k + q
                            prev_v = vq
                            prev_g = grad
                            if alpha >= _STOP_ALPHA:
                                active = 0
                    k += 4
            if prev_k != -2 and alpha < _STOP_ALPHA:
                # the walk skipped the rest of the ray: close the last segment likewise
                acc, alpha, t_depth, closed = close_segment(
                    vol, sh, g, cam, d, prev_k, prev_v, prev_g, k_first, lead, jit, dt, t1, acc,
                    alpha, t_depth,
                )  # fmt: skip
                if closed != 0:
                    prev_k = -2
            if vol.ramps != 0 and alpha < _STOP_ALPHA and t1 < t_box:
                # the ray ends at its depth limit (an opaque surface in front of the box's far
                # side): the segment from the last lattice point before it to the limit, whose
                # density is sampled there
                s1 = value_grad(f, o + d * t1)
                v1 = wp.max(s1[3], flat)
                n_raw = wp.vec3(0.0, 0.0, 0.0)
                if v1 > flat:
                    n_raw = wp.vec3(s1[0], s1[1], s1[2])
                vf = flat
                t_front = t0
                if prev_k != -2 and (float(prev_k + 1) + jit) * dt >= t1:
                    # the last lattice point before the limit was composited (or the ray's
                    # origin, when no lattice point lies before the limit)
                    vf = prev_v
                    if prev_k + 1 != k_first:
                        t_front = (float(prev_k) + jit) * dt
                    if prev_v > flat:
                        n_raw = n_raw + prev_g
                else:
                    # it was skipped (clear there), or none lies before the limit
                    k_last = int(wp.ceil(t1 / dt - jit)) - 1
                    if (float(k_last + 1) + jit) * dt < t1:
                        k_last += 1
                    if (float(k_last) + jit) * dt >= t1:
                        k_last -= 1
                    if k_last >= k_first:
                        t_front = (float(k_last) + jit) * dt
                fr = wp.clamp((t1 - t_front) / dt, 0.0, 1.0)
                # placed midway, in front of the surface that set the limit
                t_mid = t_front + 0.5 * (t1 - t_front)
                acc, alpha, t_depth = add_segment(
                    vol, sh, g, cam, d, n_raw, t_mid, vf, v1, fr, acc, alpha, t_depth
                )
        if sh.coverage != 0:
            rgba[pix] = pack_premultiplied(acc, alpha)
        else:
            rgba[pix] = pack_rgba(acc + sh.background * (1.0 - alpha))
        depth[pix] = t_depth
        if counting != 0:
            counts[pix] = passes
        atom = wp.int32(-1)
        if t_depth < wp.inf:
            atom = sample(f, o + d * t_depth).atom
        ids[pix] = atom

    return RaycastKernels(
        model=model,
        parts=split != 0,
        counts=count,
        bound_settle=bound_settle_kernel,
        bound=bound_kernel,
        bound_lanes=bound_lanes_kernel,
        whole_settle=whole_settle_kernel,
        whole_bound=whole_bound_kernel,
        evaluate=evaluate_kernel,
        histogram=histogram_kernel,
        iso_march=iso_march_kernel,
        iso_split=iso_split_kernel,
        iso_shade=iso_shade_kernel,
        volume=volume_kernel,
    )


@dataclass(frozen=True)
class RaycastKernels:
    """The kernels generated for one density model."""

    model: DensityModel
    parts: bool
    """The walked cells mark their parts below the level and the rays skip samples there."""
    counts: bool
    """The marching kernels write each ray's density passes to their `counts` argument."""
    bound_settle: Any
    bound: Any
    bound_lanes: Any
    """`bound`'s part walk with several threads a listed cell (`Renderer._walk_listed_parts`
    chooses); None where the model has no `part_bounds_lane` or the kernels no parts."""
    whole_settle: Any
    whole_bound: Any
    """The cell-bound kernels without parts (the same as the two above when `parts` is
    False): with part bounds for the view, every cell takes these first, and the cells the
    view reaches then walk again with `bound` (visibility.py)."""
    evaluate: Any
    histogram: Any
    iso_march: Any
    iso_split: Any
    iso_shade: Any
    volume: Any


_KERNELS: dict[tuple[str, bool, int, int, bool, bool], RaycastKernels] = {}


def _bound_kernels(field: Any, walked: Any, options: dict[str, Any]) -> tuple[Any, Any]:
    """The cell-bound kernels over one walk, `walked(f, c, stop_above) -> (bound, parts)`:
    kernels of their own for each walk, so the plain one carries none of the part walk's
    registers."""
    Field = field

    @wp.kernel(enable_backward=False, module="unique", module_options=options)
    @no_type_check
    def bound_settle_kernel(
        f: Field,
        stop_above: float,
        keep_from: float,
        threads: int,
        cell_start: wp.array[wp.int32],
        coarse: wp.array[float],
        out: wp.array[float],
        parts: wp.array[wp.int32],
        work: wp.array[wp.int32],
        work_count: wp.array[wp.int32],
    ):
        """An upper bound of the density in each cell (see `clear`), walked only where that
        can decide anything. A cell that holds an atom is given infinity: the density there
        reaches the level in all but contrived cases (a lone atom lighter than the level). A
        cell whose coarse bound (CellGrid.build_coarse, no walk) is already below the level
        keeps it, and so does one whose coarse bound is `keep_from` or more: a walk there
        rarely ends below the level. The other cells, empty ones near the atoms, are listed
        in `work` for the `bound_kernel` made with the same walk to walk in full warps
        (walked here only when the list is full). Only walked cells know parts below the
        level (`parts`, which may share the memory of `coarse`: each cell reads its coarse
        bound before it writes its parts).
        `threads` threads stride over the grid's cells (grid.cell_threads)."""
        c = wp.tid()
        g = f.info[0]
        if g.valid == 0:
            return
        while c < g.ncells:
            if cell_start[c + 1] > cell_start[c]:
                out[c] = wp.inf
                parts[c] = 0
            else:
                b = coarse[c]
                if b < stop_above or b >= keep_from:
                    out[c] = b
                    parts[c] = 0
                else:
                    slot = wp.atomic_add(work_count, 0, 1)
                    if slot < work.shape[0]:
                        work[slot] = c
                    else:
                        bound, mask = walked(f, c, stop_above)
                        out[c] = bound
                        parts[c] = mask
            c += threads

    @wp.kernel(enable_backward=False, module="unique", module_options=options)
    @no_type_check
    def bound_kernel(
        f: Field,
        stop_above: float,
        threads: int,
        work: wp.array[wp.int32],
        work_count: wp.array[wp.int32],
        out: wp.array[float],
        parts: wp.array[wp.int32],
    ):
        """Walk the cells `bound_settle_kernel` listed, `threads` threads striding over the
        list."""
        i = wp.tid()
        n = wp.min(work_count[0], work.shape[0])
        while i < n:
            c = work[i]
            bound, mask = walked(f, c, stop_above)
            out[c] = bound
            parts[c] = mask
            i += threads

    return bound_settle_kernel, bound_kernel


def kernels_for(
    model: DensityModel = GAUSSIAN,
    fast_math: bool = True,
    max_registers: int = 0,
    volume_max_registers: int = 0,
    parts: bool = True,
    count: bool = False,
) -> RaycastKernels:
    """The kernels of `model`, generated once per process. `fast_math` lets CUDA use its
    hardware exp/divide/sqrt approximations (a few ulp); `max_registers` and
    `volume_max_registers` (0 = compiler's choice) cap the registers of the iso (marching
    and shading) and volume kernels on CUDA. CPU builds ignore them. `parts`: the walked
    cells mark which of their parts are below the level and the rays skip the samples there
    (for models with `part_bounds`). `count`: the iso march and volume kernels write the
    density passes of each ray (a measurement of the work; the image is the same)."""
    split = bool(parts) and model.part_bounds is not None
    regs, volume_regs = int(max_registers), int(volume_max_registers)
    key = (model.name, bool(fast_math), regs, volume_regs, split, bool(count))
    k = _KERNELS.get(key)
    if k is None or k.model is not model:
        k = _make(model, bool(fast_math), regs, volume_regs, split, bool(count))
        _KERNELS[key] = k
    return k


def camera_data(
    frame: CameraFrame,
    tile: tuple[int, int, int, int] | None = None,
    region: tuple[Any, ...] | None = None,
    scene: tuple[Sequence[float], Sequence[float]] | None = None,
) -> CameraData:
    """The device struct of a numpy camera frame; `tile` (x0, y0, width, height) casts only
    that rectangle of the frame's image; `region` (axis, lo, hi, open) samples only that slab of
    space (`CameraData.part_open`: 1 when left out) and `scene` (lo, hi) spans the depth cue over
    that box (the parts of a sort-last frame)."""
    x0, y0, w, h = tile if tile is not None else (0, 0, frame.width, frame.height)
    c = CameraData()
    c.eye = wp.vec3(*(float(v) for v in frame.eye))
    c.right = wp.vec3(*(float(v) for v in frame.right))
    c.up = wp.vec3(*(float(v) for v in frame.up))
    c.forward = wp.vec3(*(float(v) for v in frame.forward))
    c.scale = float(frame.scale)
    c.aspect = float(frame.aspect)
    c.ortho = int(frame.ortho)
    c.width = int(w)
    c.height = int(h)
    c.tiles_x = tiles(w, h)[0]
    c.x0 = int(x0)
    c.y0 = int(y0)
    c.full_width = int(frame.width)
    c.full_height = int(frame.height)
    c.part_axis = -1
    c.part_open = 1
    c.first_tile = 0
    if region is not None:
        c.part_axis = int(region[0])
        c.part_lo = float(region[1])
        c.part_hi = float(region[2])
        c.part_open = int(region[3]) if len(region) > 3 else 1
    c.scene = int(scene is not None)
    if scene is not None:
        c.scene_lo = wp.vec3(*(float(v) for v in scene[0]))
        c.scene_hi = wp.vec3(*(float(v) for v in scene[1]))
    return c


def tiles(width: int, height: int) -> tuple[int, int]:
    return -(-width // TILE_W), -(-height // TILE_H)


def launch_size(width: int, height: int) -> int:
    """Threads for an image: whole 8x4 tiles."""
    tx, ty = tiles(width, height)
    return tx * ty * TILE


def shading(
    params: RenderParams,
    frame: CameraFrame,
    *,
    iso: float = 0.0,
    ao_step: float = 0.0,
    coverage: bool = False,
) -> Shading:
    """The device struct of the lighting: a headlight, the key light fixed to the camera,
    ambient occlusion when `ao_step` > 0 asks for it, the depth cue, coverage output."""
    light = params.lighting
    sh = Shading()
    sh.background = wp.vec3(*(float(v) for v in params.background))
    sh.uniform_color = wp.vec3(*(float(v) for v in params.uniform_color))
    sh.key_dir = wp.vec3(*(float(v) for v in key_light_direction(frame)))
    sh.ambient = float(light.ambient)
    sh.diffuse = float(light.diffuse)
    sh.specular = float(light.specular)
    sh.shininess = float(light.shininess)
    sh.head_weight = 0.6 if light.key_light else 1.0
    sh.key_weight = 0.55 if light.key_light else 0.0
    sh.ao = int(light.ambient_occlusion and ao_step > 0.0)
    sh.ao_step = float(ao_step)
    sh.iso = float(iso)
    sh.depth_cue = float(light.depth_cue)
    sh.coverage = int(coverage)
    return sh


def key_light_direction(frame: CameraFrame) -> np.ndarray:
    """World direction towards the key light: upper left, in front of the camera."""
    d = -0.45 * frame.right + 0.55 * frame.up - 0.70 * frame.forward
    out: np.ndarray = d / np.linalg.norm(d)
    return out
