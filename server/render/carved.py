"""The carved density on the device (definition and reference: skeleton.py): a Gaussian
density of 0.6 sigma at full strength, carved away from the bond skeleton. It is not the
thesis's warped density (that is the geodesic density, geodesic_field.py): no distance here is
measured through the graph, and with uniform weights its along-graph smoothing returns the
weights unchanged, so it is a narrower classical density times a skeleton factor.

    S(P) = G(P) exp(-atten phi(P)^2)

G is the Gaussian density of the sorted atoms (weights already smoothed along the bond graph,
spatial scale s3), phi^2 the smooth squared distance to the bond skeleton. The skeleton's
segments have a cell grid of their own, rebuilt every frame like the atoms' one, so phi^2 is one
short walk over the segments near P (within R, a fraction of the atoms' cutoff reach).

Also here: the kernels that gather the segments into cell order each frame and smooth the atom
densities along the bond graph (a truncated Dijkstra per atom, when the topology, the weights
or the scales change; nothing of it runs per frame).
"""

from typing import no_type_check

import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import GridInfo
from server.render.density import (
    DensityModel,
    GaussianField,
    Sample,
    cell_rows,
    gaussian_box_bound,
    gaussian_sample,
    gaussian_value,
    gaussian_value4,
    gaussian_value_grad,
    gaussian_value_grad4,
)
from server.render.skeleton import GRAPH_TABLE, SKELETON_POWER

wp.set_module_options({"enable_backward": False})

assert SKELETON_POWER == 4, "the kernels raise to the 4th power by squaring twice"
FLOOR = 1.0e-9
"""Distances below sqrt(FLOOR) R count as on the segment (keeps R^8/d^8 finite in float32)."""

_TABLE = wp.constant(GRAPH_TABLE)  # type: ignore[no-untyped-call]
_FLOOR = wp.constant(FLOOR)  # type: ignore[no-untyped-call]
_NodeIds = wp.types.vector(length=GRAPH_TABLE, dtype=wp.int32)
_NodeDist = wp.types.vector(length=GRAPH_TABLE, dtype=float)


@wp.struct
class SkeletonField:
    """The bond segments in cell order: seg_a = (a, 0), seg_b = (b - a, 1/|b - a|^2) (0 for an
    atom without bonds, a point)."""

    info: wp.array[GridInfo]
    cell_start: wp.array[wp.int32]
    seg_a: wp.array[wp.vec4]
    seg_b: wp.array[wp.vec4]
    r2: float  # R^2
    atten: float  # lambda^2 kappa^2 / (2 sigma^2)


@wp.struct
class CarvedField:
    """What the carved density reads; `info`, `bound` and `brick_bound` are the atom grid's
    (the ray caster walks them), `gauss` the atoms, `skel` the segments."""

    info: wp.array[GridInfo]
    bound: wp.array[float]
    parts: wp.array[wp.int32]
    brick_bound: wp.array[float]
    gauss: GaussianField
    skel: SkeletonField


@wp.func
@no_type_check
def segment_offset(s: SkeletonField, j: int, p: wp.vec3) -> wp.vec3:
    """p minus its nearest point on segment j."""
    a4 = s.seg_a[j]
    b4 = s.seg_b[j]
    a = wp.vec3(a4[0], a4[1], a4[2])
    ab = wp.vec3(b4[0], b4[1], b4[2])
    u = wp.clamp(wp.dot(p - a, ab) * b4[3], 0.0, 1.0)
    return p - (a + ab * u)


@wp.func
@no_type_check
def skeleton_term(r2: float, d2: float) -> wp.vec2:
    """(c (R^2/d^2)^4, its derivative in d^2) of one segment at squared distance d2 < R^2."""
    x = 1.0 - d2 / r2
    c = x * x * x
    dc = -3.0 * x * x / r2
    dd = wp.max(d2, _FLOOR * r2)
    q = r2 / dd
    q = q * q
    q = q * q
    dq = float(0.0)
    if d2 > _FLOOR * r2:
        dq = -4.0 * q / dd
    return wp.vec2(c * q, dc * q + c * dq)


@wp.func
@no_type_check
def row_skeleton(s: SkeletonField, p: wp.vec3, j0: int, j1: int, h: float) -> float:
    out = h
    for j in range(j0, j1):
        off = segment_offset(s, j, p)
        d2 = wp.dot(off, off)
        if d2 < s.r2:
            out += skeleton_term(s.r2, d2)[0]
    return out


@wp.func
@no_type_check
def row_skeleton_grad(s: SkeletonField, p: wp.vec3, j0: int, j1: int, acc: wp.vec4) -> wp.vec4:
    """(grad H, H) over segments [j0, j1)."""
    out = acc
    for j in range(j0, j1):
        off = segment_offset(s, j, p)
        d2 = wp.dot(off, off)
        if d2 < s.r2:
            t = skeleton_term(s.r2, d2)
            g = off * (2.0 * t[1])
            out += wp.vec4(g[0], g[1], g[2], t[0])
    return out


@wp.struct
class Points4:
    p0: wp.vec3
    p1: wp.vec3
    p2: wp.vec3
    p3: wp.vec3


@wp.func
@no_type_check
def skeleton_h(r2: float, off: wp.vec3) -> float:
    d2 = wp.dot(off, off)
    h = float(0.0)
    if d2 < r2:
        h = skeleton_term(r2, d2)[0]
    return h


@wp.func
@no_type_check
def row_skeleton4(s: SkeletonField, q: Points4, j0: int, j1: int, h: wp.vec4) -> wp.vec4:
    out = h
    for j in range(j0, j1):
        out[0] = out[0] + skeleton_h(s.r2, segment_offset(s, j, q.p0))
        out[1] = out[1] + skeleton_h(s.r2, segment_offset(s, j, q.p1))
        out[2] = out[2] + skeleton_h(s.r2, segment_offset(s, j, q.p2))
        out[3] = out[3] + skeleton_h(s.r2, segment_offset(s, j, q.p3))
    return out


@wp.func
@no_type_check
def skeleton_hgrad(r2: float, off: wp.vec3) -> wp.vec4:
    d2 = wp.dot(off, off)
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if d2 < r2:
        t = skeleton_term(r2, d2)
        g = off * (2.0 * t[1])
        out = wp.vec4(g[0], g[1], g[2], t[0])
    return out


@wp.func
@no_type_check
def row_skeleton_grad4(s: SkeletonField, q: Points4, j0: int, j1: int, acc: wp.mat44) -> wp.mat44:
    a0 = acc[0]
    a1 = acc[1]
    a2 = acc[2]
    a3 = acc[3]
    for j in range(j0, j1):
        a0 += skeleton_hgrad(s.r2, segment_offset(s, j, q.p0))
        a1 += skeleton_hgrad(s.r2, segment_offset(s, j, q.p1))
        a2 += skeleton_hgrad(s.r2, segment_offset(s, j, q.p2))
        a3 += skeleton_hgrad(s.r2, segment_offset(s, j, q.p3))
    return wp.matrix_from_rows(a0, a1, a2, a3)


_walk_h = cell_rows("skeleton", row_skeleton, wp.vec3, float, field=SkeletonField)
_walk_hgrad = cell_rows("skeleton_grad", row_skeleton_grad, wp.vec3, wp.vec4, field=SkeletonField)
_walk_h4 = cell_rows("skeleton4", row_skeleton4, Points4, wp.vec4, field=SkeletonField)
_walk_hgrad4 = cell_rows(
    "skeleton_grad4", row_skeleton_grad4, Points4, wp.mat44, field=SkeletonField
)


@wp.func
@no_type_check
def phi2_of(s: SkeletonField, h: float) -> float:
    """phi^2 = R^2 (H + 1)^(-1/4)."""
    return s.r2 / wp.sqrt(wp.sqrt(h + 1.0))


@wp.func
@no_type_check
def attenuation(s: SkeletonField, h: float) -> float:
    return wp.exp(-s.atten * phi2_of(s, h))


@wp.func
@no_type_check
def attenuation_grad(s: SkeletonField, hg: wp.vec4) -> wp.vec4:
    """(grad a, a) for a = exp(-atten phi^2) from (grad H, H)."""
    h1 = hg[3] + 1.0
    root = wp.sqrt(wp.sqrt(h1))
    a = wp.exp(-s.atten * s.r2 / root)
    # d phi2 / dH = -R^2 / 4 (H + 1)^(-5/4); d a = -atten a d phi2
    k = s.atten * a * s.r2 * 0.25 / (root * h1)
    return wp.vec4(hg[0] * k, hg[1] * k, hg[2] * k, a)


@wp.func
@no_type_check
def points4(o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> Points4:
    q = Points4()
    q.p0 = o + d * ts[0]
    q.p1 = o + d * ts[1]
    q.p2 = o + d * ts[2]
    q.p3 = o + d * ts[3]
    return q


@wp.func
@no_type_check
def carved_value(f: CarvedField, p: wp.vec3) -> float:
    v = gaussian_value(f.gauss, p)
    if v > 0.0 and f.skel.atten > 0.0:
        v = v * attenuation(f.skel, _walk_h(f.skel, p, p, p, wp.float32(0.0)))
    return v


@wp.func
@no_type_check
def carved_value_grad(f: CarvedField, p: wp.vec3) -> wp.vec4:
    vg = gaussian_value_grad(f.gauss, p)
    out = vg
    if vg[3] > 0.0 and f.skel.atten > 0.0:
        ag = attenuation_grad(f.skel, _walk_hgrad(f.skel, p, p, p, wp.vec4(0.0, 0.0, 0.0, 0.0)))
        out = vg * ag[3] + wp.vec4(ag[0], ag[1], ag[2], 0.0) * vg[3]
    return out


@wp.func
@no_type_check
def carved_value4(f: CarvedField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
    v = gaussian_value4(f.gauss, o, d, ts)
    if f.skel.atten > 0.0 and (v[0] > 0.0 or v[1] > 0.0 or v[2] > 0.0 or v[3] > 0.0):
        pa = o + d * ts[0]
        pb = o + d * ts[3]
        zero = wp.vec4(0.0, 0.0, 0.0, 0.0)
        h = _walk_h4(f.skel, wp.min(pa, pb), wp.max(pa, pb), points4(o, d, ts), zero)
        for q in range(4):
            v[q] = v[q] * attenuation(f.skel, h[q])
    return v


@wp.func
@no_type_check
def carved_value4_level(
    f: CarvedField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float
) -> wp.vec4:
    """`carved_value4`, but -1 where the Gaussian part alone is below `level` (the factor
    never exceeds 1): the skeleton walk runs only where the density may reach the level."""
    v = gaussian_value4(f.gauss, o, d, ts)
    if f.skel.atten > 0.0 and (v[0] >= level or v[1] >= level or v[2] >= level or v[3] >= level):
        pa = o + d * ts[0]
        pb = o + d * ts[3]
        zero = wp.vec4(0.0, 0.0, 0.0, 0.0)
        h = _walk_h4(f.skel, wp.min(pa, pb), wp.max(pa, pb), points4(o, d, ts), zero)
        for q in range(4):
            if v[q] >= level:
                v[q] = v[q] * attenuation(f.skel, h[q])
            else:
                v[q] = -1.0
    elif f.skel.atten > 0.0:
        v = wp.vec4(-1.0, -1.0, -1.0, -1.0)
    return v


@wp.func
@no_type_check
def carved_value_grad4_level(f: CarvedField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float):
    """`carved_value_grad4`, with value -1 where the Gaussian part is below `level`."""
    g0, g1, g2, g3 = gaussian_value_grad4(f.gauss, o, d, ts)
    if f.skel.atten > 0.0:
        if g0[3] >= level or g1[3] >= level or g2[3] >= level or g3[3] >= level:
            pa = o + d * ts[0]
            pb = o + d * ts[3]
            zero = wp.mat44(0.0)
            m = _walk_hgrad4(f.skel, wp.min(pa, pb), wp.max(pa, pb), points4(o, d, ts), zero)
            g0 = attenuated(g0, attenuation_grad(f.skel, m[0]))
            g1 = attenuated(g1, attenuation_grad(f.skel, m[1]))
            g2 = attenuated(g2, attenuation_grad(f.skel, m[2]))
            g3 = attenuated(g3, attenuation_grad(f.skel, m[3]))
        g0 = below(g0, level)
        g1 = below(g1, level)
        g2 = below(g2, level)
        g3 = below(g3, level)
    return g0, g1, g2, g3


@wp.func
@no_type_check
def below(g: wp.vec4, level: float) -> wp.vec4:
    out = g
    if g[3] < level:
        out = wp.vec4(g[0], g[1], g[2], -1.0)
    return out


@wp.func
@no_type_check
def attenuated(vg: wp.vec4, ag: wp.vec4) -> wp.vec4:
    return vg * ag[3] + wp.vec4(ag[0], ag[1], ag[2], 0.0) * vg[3]


@wp.func
@no_type_check
def carved_value_grad4(f: CarvedField, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    g0, g1, g2, g3 = gaussian_value_grad4(f.gauss, o, d, ts)
    if f.skel.atten > 0.0 and (g0[3] > 0.0 or g1[3] > 0.0 or g2[3] > 0.0 or g3[3] > 0.0):
        pa = o + d * ts[0]
        pb = o + d * ts[3]
        zero = wp.mat44(0.0)
        m = _walk_hgrad4(f.skel, wp.min(pa, pb), wp.max(pa, pb), points4(o, d, ts), zero)
        g0 = attenuated(g0, attenuation_grad(f.skel, m[0]))
        g1 = attenuated(g1, attenuation_grad(f.skel, m[1]))
        g2 = attenuated(g2, attenuation_grad(f.skel, m[2]))
        g3 = attenuated(g3, attenuation_grad(f.skel, m[3]))
    return g0, g1, g2, g3


@wp.func
@no_type_check
def carved_sample(f: CarvedField, p: wp.vec3) -> Sample:
    s = gaussian_sample(f.gauss, p)
    if s.value > 0.0 and f.skel.atten > 0.0:
        ag = attenuation_grad(f.skel, _walk_hgrad(f.skel, p, p, p, wp.vec4(0.0, 0.0, 0.0, 0.0)))
        a = ag[3]
        s.grad = s.grad * a + wp.vec3(ag[0], ag[1], ag[2]) * s.value
        s.value = s.value * a
        s.color = s.color * a
        s.weight = s.weight * a
    return s


@wp.struct
class BoxNear:
    """A box as its centre and half diagonal: a point of the box is within `half` of `center`."""

    center: wp.vec3
    half: float


@wp.func
@no_type_check
def row_skeleton_box(s: SkeletonField, q: BoxNear, j0: int, j1: int, h: float) -> float:
    """H at its largest over the box: every segment counted at a lower bound of its distance
    to the box (H only grows as distances shrink)."""
    out = h
    for j in range(j0, j1):
        off = segment_offset(s, j, q.center)
        dmin = wp.max(wp.length(off) - q.half, 0.0)
        d2 = dmin * dmin
        if d2 < s.r2:
            out += skeleton_term(s.r2, d2)[0]
    return out


_walk_h_box = cell_rows("skeleton_box", row_skeleton_box, BoxNear, float, field=SkeletonField)


@wp.func
@no_type_check
def carved_box_bound(f: CarvedField, lo: wp.vec3, hi: wp.vec3, stop_above: float) -> float:
    """The Gaussian bound times the largest factor anywhere in the box (the smallest phi^2 a
    point of the box can have): cells away from every bond, such as a ring's middle or the gap
    between two strands, are skipped where the factor empties them."""
    amax = float(1.0)
    if f.skel.atten > 0.0:
        q = BoxNear()
        q.center = (lo + hi) * 0.5
        q.half = wp.length(hi - lo) * 0.5
        amax = attenuation(f.skel, _walk_h_box(f.skel, lo, hi, q, wp.float32(0.0)))
    bound = float(0.0)
    if amax > 0.0:
        # a sum that passes stop_above / amax already puts the bound above stop_above
        bound = gaussian_box_bound(f.gauss, lo, hi, stop_above / amax) * amax
    return bound


CARVED = DensityModel(
    name="carved",
    field=CarvedField,
    value=carved_value,
    value_grad=carved_value_grad,
    sample=carved_sample,
    box_bound=carved_box_bound,
    value4=carved_value4,
    value_grad4=carved_value_grad4,
    value4_level=carved_value4_level,
    value_grad4_level=carved_value_grad4_level,
)


# ---------------------------------------------------------------- per frame and per topology


@wp.kernel
@no_type_check
def segment_mids_kernel(
    positions: wp.array[wp.vec3], ends: wp.array[wp.vec2i], mids: wp.array[wp.vec3]
):
    s = wp.tid()
    e = ends[s]
    mids[s] = (positions[e[0]] + positions[e[1]]) * 0.5


@wp.kernel
@no_type_check
def gather_segments_kernel(
    positions: wp.array[wp.vec3],
    ends: wp.array[wp.vec2i],
    order: wp.array[wp.int32],
    seg_a: wp.array[wp.vec4],
    seg_b: wp.array[wp.vec4],
):
    """Segments into cell order, each as its start and its vector (with 1/length^2)."""
    i = wp.tid()
    e = ends[order[i]]
    a = positions[e[0]]
    ab = positions[e[1]] - a
    len2 = wp.dot(ab, ab)
    inv = float(0.0)
    if len2 > 0.0:
        inv = 1.0 / len2
    seg_a[i] = wp.vec4(a[0], a[1], a[2], 0.0)
    seg_b[i] = wp.vec4(ab[0], ab[1], ab[2], inv)


@wp.kernel
@no_type_check
def smooth_densities_kernel(
    adj_start: wp.array[wp.int32],
    adj_atom: wp.array[wp.int32],
    adj_length: wp.array[float],
    cells: wp.array[float],
    densities: wp.array[float],
    scale: float,
    limit: float,
    out: wp.array[float],
):
    """dt_i: the normalised Gaussian (std `scale`) of the warped geodesic distance over the
    graph-nearest atoms within `limit` (at most GRAPH_TABLE of them), by Dijkstra on a
    per-thread table; an entry closer than the farthest unsettled one replaces it when the
    table is full, so the table ends with the graph-nearest atoms."""
    i = wp.tid()
    ids = _NodeIds()
    dist = _NodeDist()
    settled = _NodeIds()
    ids[0] = i
    dist[0] = 0.0
    settled[0] = 0
    count = wp.int32(1)
    going = wp.int32(1)
    while going != 0:
        best = wp.int32(-1)
        for q in range(count):
            if settled[q] == 0 and (best < 0 or dist[q] < dist[best]):
                best = q
        if best < 0:
            going = 0
        else:
            settled[best] = 1
            u = ids[best]
            du = dist[best]
            for e in range(adj_start[u], adj_start[u + 1]):
                v = adj_atom[e]
                dv = du + adj_length[e]
                if dv <= limit:
                    at = wp.int32(-1)
                    for q in range(count):
                        if ids[q] == v:
                            at = q
                    if at >= 0:
                        if settled[at] == 0 and dv < dist[at]:
                            dist[at] = dv
                    elif count < _TABLE:
                        ids[count] = v
                        dist[count] = dv
                        settled[count] = 0
                        count += 1
                    else:
                        far = wp.int32(-1)
                        for q in range(count):
                            if settled[q] == 0 and (far < 0 or dist[q] > dist[far]):
                                far = q
                        if far >= 0 and dv < dist[far]:
                            ids[far] = v
                            dist[far] = dv
    inv2 = 0.5 / (scale * scale)
    num = float(0.0)
    den = float(0.0)
    for q in range(count):
        v = ids[q]
        k = cells[v] * wp.exp(-dist[q] * dist[q] * inv2)
        num += k * densities[v]
        den += k
    out[i] = num / den
