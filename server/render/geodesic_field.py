"""The geodesic density on the device (definition and float64 reference: geodesic.py).

A sample walks the atoms within the cutoff of P (the classical density's cell grid: a route
shorter than the cutoff never leaves it), and for each atom a takes the Boltzmann mean of its
routes (`Routes`: the bonds with an end within graph distance `reach` of a, with the graph
distance of each end), then adds d_a K(((1 - lambda) r^2 + lambda m^2) / 2 s^2): the
classical term at strength 0, and never above it: a route is at least sqrt(r^2 + tau^2) long,
so the classical density times `Routes.gate` bounds this one. Cells and parts of cells take
their classical bounds times the gate, and the marching kernels compute the routes only at
samples where the classical density times the gate reaches the level. There, on the CPU
device, they take only the sample's side of the level (`geodesic_side4`): the near atoms
first, stopping once the side is certain; on CUDA a warp waits for its slowest ray, and the
whole walk is as fast (Tuning.decided_sides).

The route tables are built on the device when the topology, the atom weights or the tables'
reach change (a Dijkstra per atom, `build_kernel`, keeping at most `NODES` graph-nearest atoms),
and their distances follow every frame: each atom keeps its shortest-path tree, and a frame sums
the current bond weights along it (`distances_kernel`), so a route is always the length of a
path of the present molecule.
"""

import math
from typing import Any, no_type_check

import numpy as np
import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.cells import GridInfo
from server.render.density import (
    DensityModel,
    GaussianField,
    LanePoint,
    PartBounds,
    Sample,
    cell_rows,
    dist2,
    empty_sample,
    first_of_lane,
    gaussian_box_bound,
    gaussian_part_bounds,
    gaussian_part_bounds_lane,
    gaussian_value4,
    kernel,
    kernel_slope,
    unpack_rgb,
)
from server.render.errors import CapacityError
from server.render.geodesic import BondGraph

wp.set_module_options({"enable_backward": False})

NODES = 256
"""Most atoms of one atom's graph ball within the tables' reach (its Dijkstra table); beyond it
the graph-farthest are dropped and the build reports how many atoms lost some."""
MEAN_LANES_PER_SAMPLE = 32
"""Threads that take one sampled atom's geodesic density together on a CUDA device (the scale
of relative levels): a sample walks some forty times the classical one's work, and the few
thousand samples of a frame leave the device idle with the classical density's eight
(results/render_h200_geodesic_mean_lanes.json)."""
MAX_ROUTES_PER_SAMPLE = 50_000
"""Most routes a sample of the geodesic density may walk (atoms within the cutoff times the
routes of each, `geodesic.route_work`), checked before the route tables are built. At the
default sigma 1.5 A a protein with hydrogens takes 1,100-1,400 (villin, adenylate kinase); at
3 A 20,000-31,000, at 5 A 65,000-134,000, and at 50 A every atom's routes through every
bond near it. A frame's time follows: adenylate kinase at 160x120 on two CPU cores took 2 s
at sigma 1.5 A and 40 s at 3 A, and one at 50 A held the device's thread for over 20 minutes,
every other render waiting behind it. Past the limit the density is refused, naming it."""
_NODES = wp.constant(NODES)  # type: ignore[no-untyped-call]
_Ints = wp.types.vector(length=NODES, dtype=wp.int32)
_Floats = wp.types.vector(length=NODES, dtype=float)


@wp.struct
class Routes:
    """Every atom's routes (CSR by original atom index) and the bonds they go through.

    Route k this frame: `seg_a[k]` = (a_i, g_i), `seg_v[k]` = (a_j - a_i, g_j) and
    `seg_l[k]` = (|a_j - a_i|, 1 / |a_j - a_i|^2) of its bond (i, j), g the graph distance
    from that end to the route's atom (FAR beyond the tables' reach); a_j - a_i = 0 for an
    atom without bonds (a bond of length 0, 1 / length^2 taken as 0). Each route has its own
    copy of its bond's geometry: independent loads, not a bond index and then the bond
    (`route_bond`), and the length and its inverse made once a frame, not at every point
    that takes the route."""

    start: wp.array[wp.int32]
    seg_a: wp.array[wp.vec4]
    seg_v: wp.array[wp.vec4]
    seg_l: wp.array[wp.vec2]
    tau: float
    inv_tau: float
    tau2: float
    strength: float
    gate: float
    """At least S / (the classical density) anywhere: exp(-strength tau^2 c_min) with
    c_min = 1 / 2 s_max^2 (a route is at least sqrt(r^2 + tau^2) long), with room for
    rounding. Samples, cells and parts whose classical density times this is below the
    level are below it."""


@wp.struct
class GeodesicField:
    """What the geodesic density reads; `info`, `cell_start`, `bound`, `parts` and
    `brick_bound` are the atom grid's (the ray caster walks them with the classical bounds)."""

    info: wp.array[GridInfo]
    cell_start: wp.array[wp.int32]
    bound: wp.array[float]
    parts: wp.array[wp.int32]
    brick_bound: wp.array[float]
    gauss: GaussianField
    routes: Routes


@wp.func
@no_type_check
def smooth_clamp(t: float, w2: float) -> float:
    """ramp(t) - ramp(t - 1) with ramp(x) = (x + sqrt(x^2 + w^2)) / 2, from w^2
    (`geodesic.smooth_clamp`), its two halves' t taken out. With w = 0 and t = 0 (an atom
    without bonds) it is 0.5 + 0.5 (0 - 1) = 0."""
    return 0.5 + 0.5 * (wp.sqrt(t * t + w2) - wp.sqrt((t - 1.0) * (t - 1.0) + w2))


@wp.func
@no_type_check
def ramp_slope(x: float, w2: float) -> float:
    return 0.5 * (1.0 + x / wp.sqrt(x * x + w2))


@wp.struct
class RouteBond:
    """Route k's bond, read once for every point that takes it: its start a_i, vector v,
    length and 1 / length^2 (0 for an atom without bonds), (tau / length)^2, and the graph
    distances of its two ends."""

    ai: wp.vec3
    v: wp.vec3
    length: float
    inv_l2: float
    w2: float
    g: wp.vec2


@wp.func
@no_type_check
def route_bond(r: Routes, k: int) -> RouteBond:
    sa = r.seg_a[k]
    sv = r.seg_v[k]
    sl = r.seg_l[k]
    b = RouteBond()
    b.ai = wp.vec3(sa[0], sa[1], sa[2])
    b.v = wp.vec3(sv[0], sv[1], sv[2])
    b.g = wp.vec2(sa[3], sv[3])
    b.length = sl[0]
    b.inv_l2 = sl[1]
    b.w2 = r.tau2 * sl[1]
    return b


@wp.func
@no_type_check
def pair_at(b: RouteBond, p: wp.vec3, tau2: float) -> wp.vec2:
    """The two routes from p through bond b (via its end i, via its end j). The distance
    across is that of q = e - u v with e = p - a_i (the projection's own difference), not
    |e|^2 + u (u l^2 - 2 e.v): that expansion cancels terms of the bond's length squared near
    an end, an error of some eps l^2 / (2 tau) on the route, 6e-5 A at tau = 0.01 A. An atom
    without bonds (v = 0, 1 / length^2 taken as 0) has t = 0 and w = 0, where u = 0 and the
    route is its straight line, with no branch."""
    e = p - b.ai
    u = smooth_clamp(wp.dot(e, b.v) * b.inv_l2, b.w2)
    q = e - b.v * u
    across = wp.sqrt(wp.dot(q, q) + tau2)
    return wp.vec2(across + u * b.length + b.g[0], across + (1.0 - u) * b.length + b.g[1])


@wp.func
@no_type_check
def route_pair(r: Routes, k: int, p: wp.vec3) -> wp.vec2:
    """The two routes through route k's bond (via its end i, via its end j)."""
    return pair_at(route_bond(r, k), p, r.tau2)


@wp.func
@no_type_check
def boltzmann(acc: wp.vec3, c: float, inv_tau: float) -> wp.vec3:
    """(least route, sum of weights, sum of weighted routes) with route c added; the weights
    are exp(-(c - least) / tau), rescaled when a shorter route comes."""
    out = acc
    if c < acc[0]:
        s = wp.exp((c - acc[0]) * inv_tau)
        out = wp.vec3(c, acc[1] * s + 1.0, acc[2] * s + c)
    elif c < wp.inf:
        e = wp.exp((acc[0] - c) * inv_tau)
        out = wp.vec3(acc[0], acc[1] + e, acc[2] + c * e)
    return out


@wp.func
@no_type_check
def atom_distance(r: Routes, a: int, p: wp.vec3) -> float:
    """m: the Boltzmann mean of atom a's routes from p (every atom has one at least)."""
    acc = wp.vec3(wp.inf, 0.0, 0.0)
    for k in range(r.start[a], r.start[a + 1]):
        c = route_pair(r, k, p)
        acc = boltzmann(acc, c[0], r.inv_tau)
        acc = boltzmann(acc, c[1], r.inv_tau)
    return acc[2] / acc[1]


FLOOR = 1.0e-26
"""Least sum of the weights `atom_distance_near` trusts (about e^-60): below it the routes'
weights relative to the straight line may have lost some to underflow, and the atom's mean is
taken by `atom_distance` instead."""
_FLOOR = wp.constant(FLOOR)  # type: ignore[no-untyped-call]
FAR = 1.0e30
"""The graph distance this frame's tables give an end beyond their reach: finite, so a route
through it weighs exactly 0 in `weigh` with no test (inf would make 0 x inf of its weighted
length), and longer than any route the running least (`boltzmann`) keeps."""
_FAR = wp.constant(FAR)  # type: ignore[no-untyped-call]


@wp.func
@no_type_check
def weigh(acc: wp.vec2, c: wp.vec2, ref: float, inv_tau: float) -> wp.vec2:
    """(sum of weights, sum of weighted routes) with a bond's two routes c added, each
    weighed exp((ref - c) / tau); a route beyond the tables' reach (FAR) weighs 0."""
    e0 = wp.exp((ref - c[0]) * inv_tau)
    e1 = wp.exp((ref - c[1]) * inv_tau)
    return wp.vec2(acc[0] + e0 + e1, acc[1] + c[0] * e0 + c[1] * e1)


@wp.func
@no_type_check
def mean_or_least(acc: wp.vec2, r: Routes, a: int, p: wp.vec3) -> float:
    """The mean from `weigh`'s sums, or `atom_distance` where they fell below `FLOOR`."""
    m = float(0.0)
    if acc[0] > _FLOOR:  # noqa: SIM108  (a ternary would walk the routes again every time)
        m = acc[1] / acc[0]
    else:
        m = atom_distance(r, a, p)
    return m


@wp.func
@no_type_check
def atom_distance_near(r: Routes, a: int, p: wp.vec3, r2: float) -> float:
    """`atom_distance` with every route weighed against sqrt(r2 + tau^2), r2 = |p - a|^2: a
    bound below every route (a route is a path, at least the straight line, and its first leg
    is at least tau), so each weight is one exponential and no branch, where the running
    least rescales at every shorter route (and a warp takes both branches). Where the weights
    sum below `FLOOR` (routes far longer than the line) the running least takes the atom."""
    ref = wp.sqrt(r2 + r.tau2)
    acc = wp.vec2(0.0, 0.0)
    for k in range(r.start[a], r.start[a + 1]):
        acc = weigh(acc, route_pair(r, k, p), ref, r.inv_tau)
    return mean_or_least(acc, r, a, p)


@wp.struct
class Points4:
    """Four points and which of them to evaluate (`live` > 0)."""

    p0: wp.vec3
    p1: wp.vec3
    p2: wp.vec3
    p3: wp.vec3
    live: wp.vec4


@wp.func
@no_type_check
def atom_distance4_near(r: Routes, a: int, q: Points4, live: wp.vec4, r2: wp.vec4) -> wp.vec4:
    """`atom_distance_near` at the four points of q where `live` is positive (0 elsewhere),
    r2 their |p - a|^2: each route's bond is read once for all four."""
    a0 = wp.vec2(0.0, 0.0)
    a1 = wp.vec2(0.0, 0.0)
    a2 = wp.vec2(0.0, 0.0)
    a3 = wp.vec2(0.0, 0.0)
    it = r.inv_tau
    t2 = r.tau2
    ref = wp.vec4(
        wp.sqrt(r2[0] + t2), wp.sqrt(r2[1] + t2), wp.sqrt(r2[2] + t2), wp.sqrt(r2[3] + t2)
    )
    for k in range(r.start[a], r.start[a + 1]):
        b = route_bond(r, k)
        if live[0] > 0.0:
            a0 = weigh(a0, pair_at(b, q.p0, t2), ref[0], it)
        if live[1] > 0.0:
            a1 = weigh(a1, pair_at(b, q.p1, t2), ref[1], it)
        if live[2] > 0.0:
            a2 = weigh(a2, pair_at(b, q.p2, t2), ref[2], it)
        if live[3] > 0.0:
            a3 = weigh(a3, pair_at(b, q.p3, t2), ref[3], it)
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if live[0] > 0.0:
        out[0] = mean_or_least(a0, r, a, q.p0)
    if live[1] > 0.0:
        out[1] = mean_or_least(a1, r, a, q.p1)
    if live[2] > 0.0:
        out[2] = mean_or_least(a2, r, a, q.p2)
    if live[3] > 0.0:
        out[3] = mean_or_least(a3, r, a, q.p3)
    return out


@wp.struct
class Mean:
    """Running Boltzmann mean with its gradient: least route, sums of weights w, w c, w dc,
    w c dc."""

    least: float
    w: float
    wc: float
    wd: wp.vec3
    wcd: wp.vec3


@wp.func
@no_type_check
def mean_add(m: Mean, c: float, dc: wp.vec3, inv_tau: float) -> Mean:
    out = m
    if c < m.least:
        s = wp.exp((c - m.least) * inv_tau)
        out.least = c
        out.w = m.w * s + 1.0
        out.wc = m.wc * s + c
        out.wd = m.wd * s + dc
        out.wcd = m.wcd * s + dc * c
    elif c < wp.inf:
        e = wp.exp((m.least - c) * inv_tau)
        out.w = m.w + e
        out.wc = m.wc + c * e
        out.wd = m.wd + dc * e
        out.wcd = m.wcd + dc * (c * e)
    return out


@wp.func
@no_type_check
def atom_distance_grad(r: Routes, a: int, p: wp.vec3) -> wp.vec4:
    """(dm/dP, m) for atom a at p."""
    m = Mean()
    m.least = wp.inf
    m.w = 0.0
    m.wc = 0.0
    m.wd = wp.vec3(0.0, 0.0, 0.0)
    m.wcd = wp.vec3(0.0, 0.0, 0.0)
    for k in range(r.start[a], r.start[a + 1]):
        b = route_bond(r, k)
        u = float(0.0)
        du = wp.vec3(0.0, 0.0, 0.0)
        if b.inv_l2 > 0.0:
            t = wp.dot(p - b.ai, b.v) * b.inv_l2
            u = smooth_clamp(t, b.w2)
            du = b.v * ((ramp_slope(t, b.w2) - ramp_slope(t - 1.0, b.w2)) * b.inv_l2)
        q = p - (b.ai + b.v * u)
        across = wp.sqrt(wp.dot(q, q) + r.tau2)
        dacross = (q - du * wp.dot(b.v, q)) / across
        length = b.length
        m = mean_add(m, across + u * length + b.g[0], dacross + du * length, r.inv_tau)
        m = mean_add(m, across + (1.0 - u) * length + b.g[1], dacross - du * length, r.inv_tau)
    mean = m.wc / m.w
    grad = m.wd / m.w - (m.wcd / m.w - m.wd * (mean / m.w)) * r.inv_tau
    return wp.vec4(grad[0], grad[1], grad[2], mean)


@wp.func
@no_type_check
def inv2s2_at(g: GaussianField, j: int) -> float:
    c = g.inv2s2_uniform
    if g.per_atom != 0:
        c = g.inv2s2[j]
    return c


@wp.func
@no_type_check
def blended_term(g: GaussianField, w: float, r2: float, m: float, c: float, lam: float) -> float:
    """An atom's term from its straight distance^2 r2 and route mean m: w K(((1 - lambda) r2 +
    lambda m^2) c), zero beyond the cutoff."""
    e = ((1.0 - lam) * r2 + lam * m * m) * c
    out = float(0.0)
    if e < g.half_k2:
        out = w * kernel(e, g.inv_half_k2)
    return out


@wp.func
@no_type_check
def term(f: GeodesicField, j: int, p: wp.vec3) -> float:
    """Sorted atom j's term of the geodesic density at p: zero, its routes not walked, where
    even the shortest a route can be, sqrt(r^2 + tau^2), puts it past the cutoff."""
    g = f.gauss
    lam = f.routes.strength
    a4 = g.atoms[j]
    c = inv2s2_at(g, j)
    r2 = dist2(a4, p)
    out = float(0.0)
    if (r2 + lam * f.routes.tau2) * c < g.half_k2:
        m = atom_distance_near(f.routes, g.order[j], p, r2)
        out = blended_term(g, a4[3], r2, m, c, lam)
    return out


@wp.func
@no_type_check
def row_value(f: GeodesicField, p: wp.vec3, j0: int, j1: int, total: float) -> float:
    s = total
    for j in range(j0, j1):
        s += term(f, j, p)
    return s


@wp.func
@no_type_check
def term_grad(
    g: GaussianField, j: int, a4: wp.vec4, p: wp.vec3, r: Routes, c: float, r2: float
) -> wp.vec4:
    """(gradient, value) of sorted atom j's term at p (zero beyond the cutoff)."""
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    lam = r.strength
    md = atom_distance_grad(r, g.order[j], p)
    m = md[3]
    e = ((1.0 - lam) * r2 + lam * m * m) * c
    if e < g.half_k2:
        k = kernel_slope(e, g.inv_half_k2) * a4[3]
        pa = wp.vec3(a4[0], a4[1], a4[2])
        de = ((p - pa) * (2.0 * (1.0 - lam)) + wp.vec3(md[0], md[1], md[2]) * (2.0 * lam * m)) * c
        grad = de * (-k[1])
        out = wp.vec4(grad[0], grad[1], grad[2], k[0])
    return out


@wp.func
@no_type_check
def row_value_grad(f: GeodesicField, p: wp.vec3, j0: int, j1: int, acc: wp.vec4) -> wp.vec4:
    out = acc
    g = f.gauss
    reach = f.routes.strength * f.routes.tau2
    for j in range(j0, j1):
        a4 = g.atoms[j]
        c = inv2s2_at(g, j)
        r2 = dist2(a4, p)
        if (r2 + reach) * c < g.half_k2:  # as in `term`
            out += term_grad(g, j, a4, p, f.routes, c, r2)
    return out


@wp.func
@no_type_check
def row_sample(f: GeodesicField, p: wp.vec3, j0: int, j1: int, acc: Sample) -> Sample:
    """Value, gradient, contribution-weighted colour and largest contributor (as the classical
    `row_sample`, with the geodesic terms)."""
    s = acc
    g = f.gauss
    reach = f.routes.strength * f.routes.tau2
    for j in range(j0, j1):
        a4 = g.atoms[j]
        c = inv2s2_at(g, j)
        r2 = dist2(a4, p)
        if (r2 + reach) * c < g.half_k2:  # as in `term`
            t = term_grad(g, j, a4, p, f.routes, c, r2)
            term = t[3]
            if term > 0.0:
                s.value = s.value + term
                s.grad = s.grad + wp.vec3(t[0], t[1], t[2])
                oj = int(g.order[j])
                s.color = s.color + unpack_rgb(g.colors[oj]) * term
                if term > s.weight or (term == s.weight and oj < s.atom):
                    s.weight = term
                    s.atom = oj
    return s


@wp.func
@no_type_check
def row_values4(f: GeodesicField, q: Points4, j0: int, j1: int, total: wp.vec4) -> wp.vec4:
    """S at the live points of q from sorted atoms [j0, j1): each atom's routes once."""
    v = total
    g = f.gauss
    lam = f.routes.strength
    least = lam * f.routes.tau2
    for j in range(j0, j1):
        a4 = g.atoms[j]
        c = inv2s2_at(g, j)
        r2 = wp.vec4(dist2(a4, q.p0), dist2(a4, q.p1), dist2(a4, q.p2), dist2(a4, q.p3))
        near = wp.vec4(0.0, 0.0, 0.0, 0.0)
        for t in range(4):
            if q.live[t] > 0.0 and (r2[t] + least) * c < g.half_k2:  # as in `term`
                near[t] = 1.0
        if near[0] + near[1] + near[2] + near[3] > 0.0:
            m = atom_distance4_near(f.routes, g.order[j], q, near, r2)
            for t in range(4):
                if near[t] > 0.0:
                    v[t] = v[t] + blended_term(g, a4[3], r2[t], m[t], c, lam)
    return v


QUEUE = 8
"""Atoms a lane of the mean density holds before it walks their routes (`LaneQueue`)."""
_Queue = wp.types.vector(length=QUEUE, dtype=wp.int32)


@wp.struct
class LaneQueue:
    """One lane's share of a sample of the mean density: the atoms within reach it has met
    and not yet walked, and the sum of those it has. A lane takes the atoms whose sorted
    index is its own modulo the lanes, meeting them row by row, and walks their routes only
    once it holds QUEUE of them or the rows are done: the lanes then walk their routes side
    by side, where walking each row's one or two atoms at once would leave the other lanes
    waiting row after row."""

    total: float
    count: int
    atoms: _Queue  # type: ignore[valid-type]


@wp.func
@no_type_check
def queue_walk(f: GeodesicField, p: wp.vec3, acc: LaneQueue) -> LaneQueue:
    """The held atoms' terms at p added in the order they were met; the queue emptied."""
    s = acc
    for i in range(QUEUE):
        if i < s.count:
            s.total = s.total + term(f, s.atoms[i], p)
    s.count = 0
    return s


@wp.func
@no_type_check
def row_queue_lane(f: GeodesicField, q: LanePoint, j0: int, j1: int, acc: LaneQueue) -> LaneQueue:
    """The lane's atoms of sorted atoms [j0, j1) (index = lane modulo lanes) within the
    cutoff of q.p, held for `queue_walk`."""
    s = acc
    g = f.gauss
    least = f.routes.strength * f.routes.tau2
    j = first_of_lane(q, j0)
    while j < j1:
        if (dist2(g.atoms[j], q.p) + least) * inv2s2_at(g, j) < g.half_k2:  # as in `term`
            if s.count == QUEUE:
                s = queue_walk(f, q.p, s)
            s.atoms[s.count] = j
            s.count = s.count + 1
        j += q.lanes
    return s


_walk_value = cell_rows("geodesic_value", row_value, wp.vec3, float, field=GeodesicField)
_walk_queue_lane = cell_rows(
    "geodesic_queue_lane", row_queue_lane, LanePoint, LaneQueue, field=GeodesicField
)
_walk_values4 = cell_rows("geodesic_values4", row_values4, Points4, wp.vec4, field=GeodesicField)
_walk_value_grad = cell_rows(
    "geodesic_value_grad", row_value_grad, wp.vec3, wp.vec4, field=GeodesicField
)
_walk_sample = cell_rows("geodesic_sample", row_sample, wp.vec3, Sample, field=GeodesicField)


@wp.func
@no_type_check
def geodesic_value(f: GeodesicField, p: wp.vec3) -> float:
    return _walk_value(f, p, p, p, wp.float32(0.0))


@wp.func
@no_type_check
def geodesic_value_grad(f: GeodesicField, p: wp.vec3) -> wp.vec4:
    return _walk_value_grad(f, p, p, p, wp.vec4(0.0, 0.0, 0.0, 0.0))


@wp.func
@no_type_check
def geodesic_sample(f: GeodesicField, p: wp.vec3) -> Sample:
    s = _walk_sample(f, p, p, p, empty_sample())
    s.weight = s.value
    return s


@wp.func
@no_type_check
def values4(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, live: wp.vec4) -> wp.vec4:
    """S at the points o + d ts[t] with live[t] > 0 (ts increasing), in one walk over the
    atoms near their segment; 0 at the others."""
    q = Points4()
    q.p0 = o + d * ts[0]
    q.p1 = o + d * ts[1]
    q.p2 = o + d * ts[2]
    q.p3 = o + d * ts[3]
    q.live = live
    lo = wp.min(q.p0, q.p3)
    hi = wp.max(q.p0, q.p3)
    return _walk_values4(f, lo, hi, q, wp.vec4(0.0, 0.0, 0.0, 0.0))


@wp.func
@no_type_check
def geodesic_value4(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
    return values4(f, o, d, ts, wp.vec4(1.0, 1.0, 1.0, 1.0))


@wp.func
@no_type_check
def bound4(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4) -> wp.vec4:
    """Upper bounds of S at the four points: the classical density times `Routes.gate`."""
    return gaussian_value4(f.gauss, o, d, ts) * f.routes.gate


@wp.func
@no_type_check
def geodesic_value4_level(
    f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float
) -> wp.vec4:
    """The geodesic density where its bound (`bound4`) reaches `level`, -1 elsewhere: the
    routes are walked only where a crossing may be."""
    c = bound4(f, o, d, ts)
    live = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for t in range(4):
        if c[t] >= level:
            live[t] = 1.0
    v = wp.vec4(-1.0, -1.0, -1.0, -1.0)
    if live[0] + live[1] + live[2] + live[3] > 0.0:
        g = values4(f, o, d, ts, live)
        for t in range(4):
            if live[t] > 0.0:
                v[t] = g[t]
    return v


SIDE_BANDS = (1.125, 3.125)
"""When a march needs only a sample's side of the level, the atoms are walked in bands of e =
r^2 / 2 s^2 (within 1.5 sigma, then 2.5 sigma, then the rest), nearest first: the near atoms
hold most of the density and most of what the routes take from it, so the side is mostly
decided before the far atoms' routes are walked. Villin at sigma 1.5 A (float64, the samples
a march takes up to each ray's crossing): 35 % of a whole walk's routes, against 68 % in the
cells' order and 25 % atom by atom nearest first (benchmarks/results/side_walk_work.json)."""
GATE_SLACK = 1.0e-5
"""Room for rounding in `Routes.gate` (an exact bound in real numbers) and in the bound walks'
early return scaled by it."""
SIDE_SLACK = 1.0e-4
"""A sample is decided below the level only when the geodesic terms so far plus the classical
terms of the atoms not yet walked stay below it by this fraction of the classical density:
float32 rounding of that running remainder stays far within it."""


_BAND_FROM = wp.constant(wp.vec4(0.0, SIDE_BANDS[0], SIDE_BANDS[1], 1.0e30))  # type: ignore[no-untyped-call]


@wp.struct
class SideQuery:
    """Four points, the level and the band of e a walk takes, [e_lo, e_hi)."""

    q: Points4
    level: float
    e_lo: float
    e_hi: float


@wp.struct
class Tally4:
    """Per point: geodesic terms so far, classical terms of the atoms not yet walked, the
    slack of the below decision, still undecided (1), decided above (1)."""

    geo: wp.vec4
    rest: wp.vec4
    slack: wp.vec4
    open: wp.vec4
    above: wp.vec4


@wp.func
@no_type_check
def row_side4(f: GeodesicField, s: SideQuery, j0: int, j1: int, acc: Tally4) -> Tally4:
    """Sorted atoms [j0, j1) in the band of `s`, at the points still undecided: each
    atom's routes once for all of them; a point is decided above once its geodesic terms
    reach the level, below once they cannot (the classical terms left, times
    `Routes.gate`, bound the rest)."""
    g = f.gauss
    lam = f.routes.strength
    reach = lam * f.routes.tau2
    geo = acc.geo
    rest = acc.rest
    open = acc.open
    above = acc.above
    for j in range(j0, j1):
        a4 = g.atoms[j]
        c = inv2s2_at(g, j)
        r2 = wp.vec4(dist2(a4, s.q.p0), dist2(a4, s.q.p1), dist2(a4, s.q.p2), dist2(a4, s.q.p3))
        e4 = r2 * c
        walk = wp.vec4(0.0, 0.0, 0.0, 0.0)
        for t in range(4):
            if open[t] > 0.0 and e4[t] < g.half_k2 and e4[t] >= s.e_lo and e4[t] < s.e_hi:
                if (r2[t] + reach) * c < g.half_k2:  # as in `term`
                    walk[t] = 1.0
                else:
                    # no route reaches the cutoff: its geodesic term is zero, its classical
                    # one leaves the bound unwalked
                    rest[t] = rest[t] - a4[3] * kernel(e4[t], g.inv_half_k2)
                    if geo[t] + (rest[t] + acc.slack[t]) * f.routes.gate < s.level:
                        open[t] = 0.0
        if walk[0] + walk[1] + walk[2] + walk[3] > 0.0:
            m = atom_distance4_near(f.routes, g.order[j], s.q, walk, r2)
            for t in range(4):
                if walk[t] > 0.0:
                    geo[t] = geo[t] + blended_term(g, a4[3], r2[t], m[t], c, lam)
                    rest[t] = rest[t] - a4[3] * kernel(e4[t], g.inv_half_k2)
                    if geo[t] >= s.level:
                        open[t] = 0.0
                        above[t] = 1.0
                    elif geo[t] + (rest[t] + acc.slack[t]) * f.routes.gate < s.level:
                        open[t] = 0.0
    out = acc
    out.geo = geo
    out.rest = rest
    out.open = open
    out.above = above
    return out


@wp.func
@no_type_check
def side4_done(s: SideQuery, acc: Tally4) -> bool:
    return acc.open[0] + acc.open[1] + acc.open[2] + acc.open[3] == 0.0


_walk_side4 = cell_rows(
    "geodesic_side4", row_side4, SideQuery, Tally4, stop=side4_done, field=GeodesicField
)


@wp.func
@no_type_check
def geodesic_side4(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float) -> wp.vec4:
    """Each point's side of `level` (the marching kernels need no more): the density where it
    was walked whole, -1 below the level, +inf at or above it. The atoms near the points are
    walked first and each point stops as soon as its side is certain."""
    c = gaussian_value4(f.gauss, o, d, ts)
    gate = f.routes.gate
    s = SideQuery()
    s.q.p0 = o + d * ts[0]
    s.q.p1 = o + d * ts[1]
    s.q.p2 = o + d * ts[2]
    s.q.p3 = o + d * ts[3]
    s.level = level
    acc = Tally4()
    acc.geo = wp.vec4(0.0, 0.0, 0.0, 0.0)
    acc.rest = c
    acc.slack = c * SIDE_SLACK
    acc.above = wp.vec4(0.0, 0.0, 0.0, 0.0)
    gated = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for t in range(4):
        if c[t] * gate >= level:
            gated[t] = 1.0
    acc.open = gated
    out = wp.vec4(-1.0, -1.0, -1.0, -1.0)
    if not side4_done(s, acc):
        lo = wp.min(s.q.p0, s.q.p3)
        hi = wp.max(s.q.p0, s.q.p3)
        for band in range(3):
            if not side4_done(s, acc):
                s.e_lo = _BAND_FROM[band]
                s.e_hi = _BAND_FROM[band + 1]
                acc = _walk_side4(f, lo, hi, s, acc)
        for t in range(4):
            if gated[t] > 0.0:
                if acc.above[t] > 0.0:
                    out[t] = wp.inf
                elif acc.open[t] > 0.0:
                    out[t] = acc.geo[t]
    return out


@wp.func
@no_type_check
def geodesic_value_grad4(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4):
    g0 = geodesic_value_grad(f, o + d * ts[0])
    g1 = geodesic_value_grad(f, o + d * ts[1])
    g2 = geodesic_value_grad(f, o + d * ts[2])
    g3 = geodesic_value_grad(f, o + d * ts[3])
    return g0, g1, g2, g3


@wp.func
@no_type_check
def below_or_grad(f: GeodesicField, p: wp.vec3, c: float, level: float) -> wp.vec4:
    out = wp.vec4(0.0, 0.0, 0.0, -1.0)
    if c >= level:
        out = geodesic_value_grad(f, p)
    return out


@wp.func
@no_type_check
def geodesic_value_grad4_level(f: GeodesicField, o: wp.vec3, d: wp.vec3, ts: wp.vec4, level: float):
    c = bound4(f, o, d, ts)
    g0 = below_or_grad(f, o + d * ts[0], c[0], level)
    g1 = below_or_grad(f, o + d * ts[1], c[1], level)
    g2 = below_or_grad(f, o + d * ts[2], c[2], level)
    g3 = below_or_grad(f, o + d * ts[3], c[3], level)
    return g0, g1, g2, g3


@wp.func
@no_type_check
def geodesic_box_bound(f: GeodesicField, lo: wp.vec3, hi: wp.vec3, stop_above: float) -> float:
    """The classical bound times `Routes.gate`. The classical walk stops a little past the
    level over the gate (GATE_SLACK), so an early answer stays above the level once scaled,
    not equal to it by rounding."""
    gate = f.routes.gate
    return gaussian_box_bound(f.gauss, lo, hi, stop_above / gate * (1.0 + GATE_SLACK)) * gate


@wp.func
@no_type_check
def geodesic_part_bounds(
    f: GeodesicField, lo: wp.vec3, hi: wp.vec3, stop_above: float
) -> PartBounds:
    gate = f.routes.gate
    return gaussian_part_bounds(f.gauss, lo, hi, stop_above / gate * (1.0 + GATE_SLACK)) * gate


@wp.func
@no_type_check
def geodesic_part_bounds_lane(
    f: GeodesicField, lo: wp.vec3, hi: wp.vec3, lane: int, lanes: int
) -> PartBounds:
    return gaussian_part_bounds_lane(f.gauss, lo, hi, lane, lanes) * f.routes.gate


GEODESIC = DensityModel(
    name="geodesic",
    field=GeodesicField,
    value=geodesic_value,
    value_grad=geodesic_value_grad,
    sample=geodesic_sample,
    box_bound=geodesic_box_bound,
    value4=geodesic_value4,
    value_grad4=geodesic_value_grad4,
    value4_level=geodesic_value4_level,
    value_grad4_level=geodesic_value_grad4_level,
    part_bounds=geodesic_part_bounds,
    side4=geodesic_side4,
    part_bounds_lane=geodesic_part_bounds_lane,
)


# ---------------------------------------------------------------- per frame and per table


@wp.kernel
@no_type_check
def bonds_kernel(
    positions: wp.array[wp.vec3],
    ends: wp.array[wp.vec2i],
    densities: wp.array[float],
    gain: float,
    seg_a: wp.array[wp.vec4],
    seg_v: wp.array[wp.vec4],
    weight: wp.array[float],
):
    """Each bond this frame: its start, vector, length and 1 / length, and its graph weight,
    the arclength of the densities across it."""
    b = wp.tid()
    e = ends[b]
    ai = positions[e[0]]
    v = positions[e[1]] - ai
    length = wp.length(v)
    inv = float(0.0)
    if length > 0.0:
        inv = 1.0 / length
    seg_a[b] = wp.vec4(ai[0], ai[1], ai[2], length)
    seg_v[b] = wp.vec4(v[0], v[1], v[2], inv)
    jump = gain * (densities[e[0]] - densities[e[1]])
    weight[b] = wp.sqrt(length * length + jump * jump)


@wp.kernel
@no_type_check
def distances_kernel(
    node_start: wp.array[wp.int32],
    node_parent: wp.array[wp.int32],
    node_edge: wp.array[wp.int32],
    weight: wp.array[float],
    node_g: wp.array[float],
    route_start: wp.array[wp.int32],
    route_nodes: wp.array[wp.vec2i],
    route_g: wp.array[wp.vec2],
):
    """An atom's graph distances this frame: the current bond weights summed along its
    shortest-path tree (nodes in the order the build settled them), then each route's ends
    (FAR for an end beyond the tables' reach)."""
    a = wp.tid()
    n0 = node_start[a]
    node_g[n0] = 0.0
    for k in range(n0 + 1, node_start[a + 1]):
        node_g[k] = node_g[n0 + node_parent[k]] + weight[node_edge[k]]
    for r in range(route_start[a], route_start[a + 1]):
        kk = route_nodes[r]
        gi = _FAR
        gj = _FAR
        if kk[0] >= 0:
            gi = node_g[n0 + kk[0]]
        if kk[1] >= 0:
            gj = node_g[n0 + kk[1]]
        route_g[r] = wp.vec2(gi, gj)


@wp.kernel
@no_type_check
def geometry_kernel(
    bond: wp.array[wp.int32],
    seg_a: wp.array[wp.vec4],
    seg_v: wp.array[wp.vec4],
    route_g: wp.array[wp.vec2],
    route_a: wp.array[wp.vec4],
    route_v: wp.array[wp.vec4],
    route_l: wp.array[wp.vec2],
):
    """Each route's copy of its bond's geometry this frame, with its ends' graph distances
    (a thread a route: the writes of one atom's routes in a loop of one thread took 6 ms at
    1M atoms)."""
    r = wp.tid()
    sa = seg_a[bond[r]]
    sv = seg_v[bond[r]]
    g = route_g[r]
    route_a[r] = wp.vec4(sa[0], sa[1], sa[2], g[0])
    route_v[r] = wp.vec4(sv[0], sv[1], sv[2], g[1])
    route_l[r] = wp.vec2(sa[3], sv[3] * sv[3])


@wp.kernel
@no_type_check
def build_kernel(
    adj_start: wp.array[wp.int32],
    adj_atom: wp.array[wp.int32],
    adj_bond: wp.array[wp.int32],
    ends: wp.array[wp.vec2i],
    point_bond: wp.array[wp.int32],
    weight: wp.array[float],
    reach: float,
    fill: int,
    node_start: wp.array[wp.int32],
    route_start: wp.array[wp.int32],
    node_count: wp.array[wp.int32],
    route_count: wp.array[wp.int32],
    node_parent: wp.array[wp.int32],
    node_edge: wp.array[wp.int32],
    route_bond: wp.array[wp.int32],
    route_nodes: wp.array[wp.vec2i],
    overflow: wp.array[wp.int32],
):
    """Atom a's graph ball within `reach` by Dijkstra on a table of at most NODES atoms (when
    full, a nearer atom replaces the farthest unsettled one, and `overflow` counts the atom),
    then its routes: every bond with an end in the ball, once, with the settled rank of each
    end (-1 outside the ball). Counts first (`fill` 0), then writes at the scanned offsets."""
    a = wp.tid()
    ids = _Ints()
    dist = _Floats()
    parent = _Ints()
    edge = _Ints()
    state = _Ints()  # -1 unsettled, else the settled rank
    order = _Ints()
    ids[0] = a
    dist[0] = 0.0
    parent[0] = -1
    edge[0] = -1
    state[0] = -1
    count = wp.int32(1)
    settled = wp.int32(0)
    lost = wp.int32(0)
    going = wp.int32(1)
    while going != 0:
        best = wp.int32(-1)
        for q in range(count):
            if state[q] < 0 and (best < 0 or dist[q] < dist[best]):
                best = q
        if best < 0:
            going = 0
        else:
            state[best] = settled
            order[settled] = best
            settled += 1
            u = ids[best]
            du = dist[best]
            for e in range(adj_start[u], adj_start[u + 1]):
                v = adj_atom[e]
                dv = du + weight[adj_bond[e]]
                if dv < reach:
                    at = wp.int32(-1)
                    for q in range(count):
                        if ids[q] == v:
                            at = q
                    if at >= 0:
                        if state[at] < 0 and dv < dist[at]:
                            dist[at] = dv
                            parent[at] = best
                            edge[at] = adj_bond[e]
                    elif count < _NODES:
                        ids[count] = v
                        dist[count] = dv
                        parent[count] = best
                        edge[count] = adj_bond[e]
                        state[count] = -1
                        count += 1
                    else:
                        lost = 1
                        far = wp.int32(-1)
                        for q in range(count):
                            if state[q] < 0 and (far < 0 or dist[q] > dist[far]):
                                far = q
                        if far >= 0 and dv < dist[far]:
                            ids[far] = v
                            dist[far] = dv
                            parent[far] = best
                            edge[far] = adj_bond[e]
    routes = wp.int32(0)
    n0 = wp.int32(0)
    r0 = wp.int32(0)
    if fill != 0:
        n0 = node_start[a]
        r0 = route_start[a]
    for s in range(settled):
        q = order[s]
        if fill != 0:
            p = wp.int32(0)
            if parent[q] >= 0:
                p = state[parent[q]]
            node_parent[n0 + s] = p
            node_edge[n0 + s] = edge[q]
        atom = ids[q]
        for e in range(adj_start[atom], adj_start[atom + 1]):
            other = adj_atom[e]
            rank = wp.int32(-1)
            for t in range(count):
                if ids[t] == other and state[t] >= 0:
                    rank = state[t]
            if rank < 0 or s < rank:
                if fill != 0:
                    b = adj_bond[e]
                    pair = wp.vec2i(s, rank)
                    if ends[b][0] != atom:
                        pair = wp.vec2i(rank, s)
                    route_bond[r0 + routes] = b
                    route_nodes[r0 + routes] = pair
                routes += 1
    if point_bond[a] >= 0:
        if fill != 0:
            route_bond[r0 + routes] = point_bond[a]
            route_nodes[r0 + routes] = wp.vec2i(0, 0)
        routes += 1
    if fill == 0:
        node_count[a] = settled
        route_count[a] = routes
        if lost != 0:
            wp.atomic_add(overflow, 0, 1)


@no_type_check
def sampled_values(
    f: GeodesicField, positions: wp.array[wp.vec3], stride: int, lanes: int, values: wp.array[float]
):
    """The geodesic density at every `stride`-th atom (the scale of relative levels), taken by
    `lanes` threads each (`values` holds the lanes' sums, sample by sample): one thread alone
    walks every route of some forty atoms while a few hundred samples leave the device idle.
    Each lane holds its atoms until it has several (`LaneQueue`)."""
    t = wp.tid()
    k = t // lanes
    q = LanePoint()
    q.p = positions[k * stride]
    q.lane = t - k * lanes
    q.lanes = lanes
    held = LaneQueue()
    held.total = 0.0
    held.count = 0
    values[t] = queue_walk(f, q.p, _walk_queue_lane(f, q.p, q.p, q, held)).total


@wp.kernel
@no_type_check
def rescale_kernel(atoms: wp.array[wp.vec4], total: wp.array[float], samples: float, count: int):
    """Divide the sorted atoms' weights by the mean density at the sampled atoms."""
    i = wp.tid()
    if i < count:
        t = total[0]
        if t > 0.0:
            a = atoms[i]
            atoms[i] = wp.vec4(a[0], a[1], a[2], a[3] * samples / t)


_wp: Any = wp  # warp's host API is unannotated: the table buffers are handled through it

NODE_BYTES = 4 + 4 + 4
"""A node of an atom's shortest-path tree: its parent, its edge and its distance (the node
arrays of `GeodesicTables._alloc`)."""
ROUTE_BYTES = 4 + 8 + 8 + 16 + 16 + 8
"""A route: its bond, its ends' nodes and distances, and its copy of the bond's geometry (the
route arrays of `GeodesicTables._alloc`)."""


def _size(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n / 1e3:.1f} kB"


def free_bytes(device: str) -> int | None:
    """Device memory free now (None on the CPU, whose tables are the host's to hold)."""
    if not device.startswith("cuda"):
        return None
    return int(_wp.get_device(device).free_memory)


class GeodesicTables:
    """One topology's bonds and route tables on a device: the bonds' geometry and weights are
    refreshed every frame (`refresh`), the routes built again when the atom weights or the
    tables' reach change (`build`)."""

    def __init__(self, device: str, graph: BondGraph) -> None:
        self.device = device
        self.graph = graph
        n = graph.n_atoms
        m = len(graph.ends)
        self.n = n
        self.bond_total = m
        self.ends = _wp.array(graph.ends, dtype=_wp.vec2i, device=device)
        self.adj_start = _wp.array(graph.adj_start, dtype=_wp.int32, device=device)
        self.adj_atom = _wp.array(
            graph.adj_atom if len(graph.adj_atom) else np.zeros(1, np.int32),
            dtype=_wp.int32,
            device=device,
        )
        self.adj_bond = _wp.array(
            graph.adj_bond if len(graph.adj_bond) else np.zeros(1, np.int32),
            dtype=_wp.int32,
            device=device,
        )
        point = np.full(n, -1, np.int32)
        lonely = graph.ends[graph.bond_count :, 0]
        point[lonely] = graph.bond_count + np.arange(len(lonely), dtype=np.int32)
        self.point_bond = _wp.array(point, dtype=_wp.int32, device=device)
        self.seg_a = _wp.zeros(max(m, 1), dtype=_wp.vec4, device=device)
        self.seg_v = _wp.zeros(max(m, 1), dtype=_wp.vec4, device=device)
        self.weight = _wp.zeros(max(m, 1), dtype=float, device=device)
        self.node_count = _wp.zeros(max(n, 1), dtype=_wp.int32, device=device)
        self.route_count = _wp.zeros(max(n, 1), dtype=_wp.int32, device=device)
        self.node_start = _wp.zeros(n + 1, dtype=_wp.int32, device=device)
        self.route_start = _wp.zeros(n + 1, dtype=_wp.int32, device=device)
        self.overflow = _wp.zeros(1, dtype=_wp.int32, device=device)
        self._alloc(0, 0)
        self.route_total = 0
        self.reach = 0.0
        self.key: tuple[object, ...] | None = None
        self.lost = 0
        """Atoms whose graph ball held more than NODES atoms within the reach at the last
        build (their farthest routes are missing)."""

    def _alloc(self, nodes: int, routes: int) -> None:
        d = self.device
        self.node_parent = _wp.zeros(max(nodes, 1), dtype=_wp.int32, device=d)
        self.node_edge = _wp.zeros(max(nodes, 1), dtype=_wp.int32, device=d)
        self.node_g = _wp.zeros(max(nodes, 1), dtype=float, device=d)
        self.route_bond = _wp.zeros(max(routes, 1), dtype=_wp.int32, device=d)
        self.route_nodes = _wp.zeros(max(routes, 1), dtype=_wp.vec2i, device=d)
        self.route_g = _wp.zeros(max(routes, 1), dtype=_wp.vec2, device=d)
        self.route_a = _wp.zeros(max(routes, 1), dtype=_wp.vec4, device=d)
        self.route_v = _wp.zeros(max(routes, 1), dtype=_wp.vec4, device=d)
        self.route_l = _wp.zeros(max(routes, 1), dtype=_wp.vec2, device=d)

    def _tables(self) -> tuple[Any, ...]:
        """The arrays `_alloc` sizes to the nodes and routes (NODE_BYTES, ROUTE_BYTES)."""
        nodes = (self.node_parent, self.node_edge, self.node_g)
        geometry = (self.route_a, self.route_v, self.route_l)
        return (*nodes, self.route_bond, self.route_nodes, self.route_g, *geometry)

    def _check_room(self, nodes: int, routes: int, reach: float) -> None:
        """Refuse tables the device cannot hold (they replace the ones it holds now), naming
        the sizes, rather than fail the allocation half way."""
        free = free_bytes(self.device)
        if free is None:
            return
        need = nodes * NODE_BYTES + routes * ROUTE_BYTES
        held = sum(int(a.capacity) for a in self._tables())
        if need > free + held:
            raise CapacityError(
                f"geodesic density: the route tables of {self.n:,} atoms, each reaching "
                f"{reach:.1f} A along the bonds ({routes:,} routes), need {_size(need)}; "
                f"{self.device} has {_size(free + held)} for them. A smaller sigma or cutoff, "
                "or the classical or carved density, needs less"
            )

    @property
    def nbytes(self) -> int:
        arrays = (
            self.ends,
            self.adj_start,
            self.adj_atom,
            self.adj_bond,
            self.point_bond,
            self.seg_a,
            self.seg_v,
            self.weight,
            self.node_count,
            self.route_count,
            self.node_start,
            self.route_start,
            *self._tables(),
        )
        return sum(int(a.capacity) for a in arrays)

    def _bonds(self, positions: Any, densities: Any, gain: float) -> None:
        if self.bond_total:
            args = (positions, self.ends, densities, float(gain), self.seg_a, self.seg_v)
            _wp.launch(bonds_kernel, self.bond_total, (*args, self.weight), device=self.device)

    def build(self, positions: Any, densities: Any, gain: float, reach: float) -> None:
        """Every atom's graph ball and routes within `reach` of the present bond weights (two
        passes, counting then writing; synchronises once to size the tables)."""
        dev = self.device
        n = self.n
        self._bonds(positions, densities, gain)
        self.overflow.zero_()
        outputs = (self.node_parent, self.node_edge, self.route_bond, self.route_nodes)
        head = (self.adj_start, self.adj_atom, self.adj_bond, self.ends, self.point_bond)
        counts = (self.node_start, self.route_start, self.node_count, self.route_count)
        if n:
            args = (*head, self.weight, float(reach), 0, *counts, *outputs, self.overflow)
            _wp.launch(build_kernel, n, args, device=dev)
        # the new starts go to arrays of their own: a build refused below leaves the tables
        # it would have replaced whole
        starts = []
        for count in (self.node_count, self.route_count):
            padded = _wp.zeros(n + 1, dtype=_wp.int32, device=dev)
            if n:
                _wp.copy(padded, count, count=n)
            start = _wp.zeros(n + 1, dtype=_wp.int32, device=dev)
            _wp.utils.array_scan(padded, start, inclusive=False)
            starts.append(start)
        totals = (int(starts[0].numpy()[n]), int(starts[1].numpy()[n]))
        self._check_room(*totals, reach)
        self.node_start, self.route_start = starts
        counts = (self.node_start, self.route_start, self.node_count, self.route_count)
        self._alloc(0, 0)  # the old tables go before the new ones are made
        self._alloc(*totals)
        self.route_total = totals[1]
        if n:
            outputs = (self.node_parent, self.node_edge, self.route_bond, self.route_nodes)
            args = (*head, self.weight, float(reach), 1, *counts, *outputs, self.overflow)
            _wp.launch(build_kernel, n, args, device=dev)
        self.lost = int(self.overflow.numpy()[0])
        self.reach = float(reach)

    def refresh(self, positions: Any, densities: Any, gain: float) -> None:
        """This frame's bonds and route distances (launches only)."""
        self._bonds(positions, densities, gain)
        if self.n:
            args = (
                self.node_start,
                self.node_parent,
                self.node_edge,
                self.weight,
                self.node_g,
                self.route_start,
                self.route_nodes,
                self.route_g,
            )
            _wp.launch(distances_kernel, self.n, args, device=self.device)
        if self.route_total:
            copy = (
                self.route_bond,
                self.seg_a,
                self.seg_v,
                self.route_g,
                self.route_a,
                self.route_v,
                self.route_l,
            )
            _wp.launch(geometry_kernel, self.route_total, copy, device=self.device)

    def routes(self, tau: float, strength: float, c_min: float) -> Routes:
        """The tables as the kernels read them; `c_min` = 1 / 2 s^2 of the widest atom."""
        r = Routes()
        r.start = self.route_start
        r.seg_a = self.route_a
        r.seg_v = self.route_v
        r.seg_l = self.route_l
        r.tau = float(tau)
        r.inv_tau = 1.0 / float(tau)
        r.tau2 = float(tau) * float(tau)
        r.strength = float(strength)
        r.gate = math.exp(-float(strength) * float(tau) ** 2 * float(c_min)) * (1.0 + GATE_SLACK)
        return r
