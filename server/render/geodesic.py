"""The geodesic density: the thesis's warped molecular density (section 5.3, eqs. 5.2-5.5),
made smooth and safe on rings. Its tables, and its float64 reference.

The thesis measures the distance from a point P to an atom a *through the molecule*: from P to
its projection I_b on a bond b (eq. 5.3, clamped to the bond), along the bond to one of its ends
e, then along the bond graph to a (eq. 5.2), taking the shortest such route (eq. 5.4):

    dist(P, a) = min over bonds b = (i, j) and ends e of b:  D(P, b) + |I_b - a_e| + G(e, a)

with D = |P - I_b| and G the shortest path through the bond graph whose edge weights are the
arclength of the atom densities across each bond, w = sqrt(l^2 + (g (d_i - d_j))^2) (a bond
lengthens where the density jumps: chapters 3-4's arclength warp on the skeleton). The density
is eq. 5.5, S(P) = sum_a d_a g_sigma(dist(P, a)).

The minimum and the clamp crease that field (where the winning route changes, at the ends of a
bond's span, and along every bond, where D is a cone), and on rings the routes of the two ways
round meet in creases (the thesis's figure 5.8). The smooth field replaces each non-smooth piece
by a smooth counterpart that never undercuts it, at a temperature tau = smoothing * sigma:

* the projection parameter t = (P - a_i).(a_j - a_i) / l^2 is clamped smoothly,
  u = ramp(t) - ramp(t - 1) with ramp(x) = (x + sqrt(x^2 + w^2)) / 2 and w = tau / l: smooth,
  increasing with a slope below 1, so u stays in (0, 1), and the clamp as tau -> 0;
* D becomes sqrt(|P - I|^2 + tau^2) (no cone on the bond);
* the minimum over the (bond, end) routes becomes their Boltzmann mean at temperature tau,
  sum c exp(-c / tau) / sum exp(-c / tau).

Every route is the length of a path P -> I -> a_e -> ... -> a, at least |P - a| (and its
smoothed length only longer), and a mean never undercuts the least of what it averages: the
geodesic distance is never shorter than the straight line, so at equal sigma and weights the
field never exceeds the classical density. As tau -> 0 each piece tends to the thesis's own,
and the field to eq. 5.5 (with an atom without bonds standing for a bond of length 0: its own
Gaussian). Strength lambda blends the squared distances, (1 - lambda) |P - a|^2 + lambda
dist(P, a)^2 (a blend of the distances themselves would crease at every atom's centre, where
|P - a| is a cone): 0 is the classical density exactly.

Which routes an atom has: the bonds with an end within graph distance `reach` (the Gaussian's
cutoff) of it. A route through any other bond is longer than the cutoff, where every Gaussian is
zero. Every path of length below the cutoff stays within the cutoff of P, so the atoms and bonds
a sample needs are those near it, and the tables are per atom: its routes' bonds, with the graph
distance of each end (`AtomRoutes`).

This module is plain numpy (scipy for the graph distances of the reference tables); the device
model lives in `geodesic_field.py`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol import Topology

F64 = npt.NDArray[np.float64]
I32 = npt.NDArray[np.int32]

GAIN = 0.25
"""g: angstrom of bond length per unit of density difference across a bond (with electron
weights a C-H bond of 1.09 A is 1.66 A long in the graph)."""
SMOOTHING = 0.6
"""tau / sigma of the rendered field (`geodesic_smoothing`): at 0.6 the creases of the minimum
over routes are rounded over about half the scale, which is what makes rings and bends look
smooth on screen (at 0.1 the spokes of a ring's centre still show as creases)."""


@dataclass(frozen=True)
class BondGraph:
    """The bonds of a topology as the geodesic density walks them.

    `ends` (m, 2): every bond once as (i, j), i < j, then every atom without a bond as (i, i), a
    bond of length 0 (its routes are its own Gaussian); `bond_count` of them are real bonds.
    `adj_start`, `adj_atom`, `adj_bond`: each atom's neighbours and the bonds to them (CSR)."""

    n_atoms: int
    ends: I32
    bond_count: int
    adj_start: I32
    adj_atom: I32
    adj_bond: I32

    @classmethod
    def of(cls, topology: Topology) -> BondGraph:
        return cls.from_bonds(int(topology.n_atoms), topology.bonds.to_numpy().reshape(-1, 2))

    @classmethod
    def from_bonds(cls, n: int, bonds: npt.ArrayLike) -> BondGraph:
        raw = np.asarray(bonds, dtype=np.int64).reshape(-1, 2)
        raw = raw[raw[:, 0] != raw[:, 1]]
        if len(raw) and (raw.min() < 0 or raw.max() >= n):
            raise ValueError(f"a bond names an atom outside 0..{n - 1}")
        real = np.unique(np.sort(raw, axis=1), axis=0).astype(np.int32).reshape(-1, 2)
        degree = np.bincount(real.ravel(), minlength=n) if len(real) else np.zeros(n, np.int64)
        lonely = np.nonzero(degree == 0)[0].astype(np.int32)
        ends = np.concatenate([real, np.stack([lonely, lonely], axis=1)]).astype(np.int32)
        a = np.concatenate([real[:, 0], real[:, 1]])
        b = np.concatenate([real[:, 1], real[:, 0]])
        ids = np.concatenate([np.arange(len(real)), np.arange(len(real))])
        order = np.lexsort((b, a))
        start = np.zeros(n + 1, dtype=np.int64)
        np.add.at(start, a + 1, 1)
        return cls(
            n_atoms=n,
            ends=ends,
            bond_count=len(real),
            adj_start=np.cumsum(start).astype(np.int32),
            adj_atom=b[order].astype(np.int32),
            adj_bond=ids[order].astype(np.int32),
        )

    def weights(self, positions: npt.ArrayLike, densities: npt.ArrayLike, gain: float) -> F64:
        """Each real bond's graph length: the arclength of the densities across it,
        sqrt(l^2 + (gain (d_i - d_j))^2)."""
        pos = np.asarray(positions, dtype=np.float64)
        d = np.asarray(densities, dtype=np.float64)
        real = self.ends[: self.bond_count]
        length = np.linalg.norm(pos[real[:, 0]] - pos[real[:, 1]], axis=1)
        jump = gain * (d[real[:, 0]] - d[real[:, 1]])
        out: F64 = np.sqrt(length * length + jump * jump)
        return out


def route_work(
    graph: BondGraph,
    positions: npt.ArrayLike,
    reach: float,
    table_reach: float,
    nodes: int,
    samples: int = 8,
) -> tuple[float, float]:
    """What a sample of the geodesic density costs, before its route tables are built: the
    atoms within `reach` of an atom and the bonds its table would hold (those with an end among
    its `nodes` graph-nearest atoms within `table_reach`), each averaged over `samples` atoms
    spread through the system. A sample walks about the product of the two. Bond lengths stand
    for the bonds' graph lengths (never longer), so the tables are estimated no smaller than
    they are. Each estimate searches a subgraph: the atoms within `table_reach` in space, which
    hold every atom that near along the bonds."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = graph.n_atoms
    if n == 0:
        return 0.0, 0.0
    real = graph.ends[: graph.bond_count]
    lonely = graph.ends[graph.bond_count :, 0]
    near: list[float] = []
    routes: list[float] = []
    for a in np.unique(np.linspace(0, n - 1, min(n, samples)).astype(np.int64)):
        d2 = ((pos - pos[a]) ** 2).sum(axis=1)
        near.append(float(np.count_nonzero(d2 <= reach * reach)))
        ball = np.nonzero(d2 <= table_reach * table_reach)[0]
        within = np.zeros(n, dtype=bool)
        within[ball] = True
        local = real[within[real[:, 0]] & within[real[:, 1]]]
        rows = np.searchsorted(ball, local[:, 0])
        cols = np.searchsorted(ball, local[:, 1])
        length = np.linalg.norm(pos[local[:, 0]] - pos[local[:, 1]], axis=1)
        w = np.maximum(length, np.finfo(np.float64).tiny)
        adjacency = csr_matrix((w, (rows, cols)), shape=(len(ball), len(ball)))
        source = int(np.searchsorted(ball, a))
        dist = dijkstra(adjacency, directed=False, indices=source, limit=float(table_reach))
        reached = np.nonzero(dist < table_reach)[0]
        kept = reached[np.argsort(dist[reached], kind="stable")[:nodes]]
        inside = np.zeros(n, dtype=bool)
        inside[ball[kept]] = True
        count = np.count_nonzero(inside[real[:, 0]] | inside[real[:, 1]])
        routes.append(float(count + np.count_nonzero(inside[lonely])))
    return float(np.mean(near)), float(np.mean(routes))


@dataclass(frozen=True)
class AtomRoutes:
    """For every atom (CSR by `start`), the bonds its routes go through: `bond` (an index into
    `BondGraph.ends`) and the graph distance from each end of it to the atom (`g_i`, `g_j`; inf
    for an end beyond `reach`, whose routes are longer than the cutoff)."""

    start: I32
    bond: I32
    g_i: F64
    g_j: F64
    reach: float

    @property
    def count(self) -> int:
        return int(self.start[-1])

    def of_atom(self, a: int) -> tuple[I32, F64, F64]:
        s, e = int(self.start[a]), int(self.start[a + 1])
        return self.bond[s:e], self.g_i[s:e], self.g_j[s:e]


def atom_routes(graph: BondGraph, weights: F64, reach: float) -> AtomRoutes:
    """Every atom's route table (float64 graph distances; the reference's, built on the host)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    n = graph.n_atoms
    real = graph.ends[: graph.bond_count]
    rows = np.concatenate([real[:, 0], real[:, 1]])
    cols = np.concatenate([real[:, 1], real[:, 0]])
    w = np.maximum(np.concatenate([weights, weights]), np.finfo(np.float64).tiny)
    adjacency = csr_matrix((w, (rows, cols)), shape=(n, n))
    starts = [0]
    bonds: list[I32] = []
    gis: list[F64] = []
    gjs: list[F64] = []
    chunk = 512
    for first in range(0, n, chunk):
        sources = np.arange(first, min(first + chunk, n))
        dist = dijkstra(adjacency, directed=False, indices=sources, limit=float(reach))
        for row in dist:
            gi = row[graph.ends[:, 0]]
            gj = row[graph.ends[:, 1]]
            keep = np.nonzero((gi < reach) | (gj < reach))[0]
            bonds.append(keep.astype(np.int32))
            gis.append(np.where(gi[keep] < reach, gi[keep], np.inf))
            gjs.append(np.where(gj[keep] < reach, gj[keep], np.inf))
            starts.append(starts[-1] + len(keep))
    return AtomRoutes(
        start=np.asarray(starts, dtype=np.int32),
        bond=np.concatenate(bonds) if bonds else np.zeros(0, np.int32),
        g_i=np.concatenate(gis) if gis else np.zeros(0),
        g_j=np.concatenate(gjs) if gjs else np.zeros(0),
        reach=float(reach),
    )


def ramp(x: F64, w: F64) -> F64:
    """(x + sqrt(x^2 + w^2)) / 2: max(0, x) made smooth (never below it, within w / 2 of it)."""
    out: F64 = 0.5 * (x + np.sqrt(x * x + w * w))
    return out


def smooth_clamp(t: F64, w: F64) -> F64:
    """ramp(t) - ramp(t - 1): in (0, 1), smooth, the clamp of t to [0, 1] as w -> 0."""
    out: F64 = ramp(t, w) - ramp(t - 1.0, w)
    return out


def taper(e: F64, cutoff_sigmas: float | None) -> F64:
    """The renderer's Gaussian, exp(-e) with e = r^2 / 2 sigma^2, tapered to zero at
    `cutoff_sigmas` (density.py); None: untruncated."""
    value: F64 = np.exp(-e)
    if cutoff_sigmas is None:
        return value
    ek = 0.5 * cutoff_sigmas**2
    inside = e < ek
    u = np.where(inside, e / ek, 1.0)
    out: F64 = np.where(inside, value * (1.0 - u**16) ** 2, 0.0)
    return out


@dataclass(frozen=True)
class Geodesic:
    """One system's geodesic density: positions, atom densities, bonds and route tables."""

    positions: F64
    densities: F64
    graph: BondGraph
    routes: AtomRoutes
    gain: float = GAIN

    @classmethod
    def build(
        cls,
        positions: npt.ArrayLike,
        densities: npt.ArrayLike,
        graph: BondGraph,
        reach: float,
        gain: float = GAIN,
    ) -> Geodesic:
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(densities, dtype=np.float64)
        routes = atom_routes(graph, graph.weights(pos, d, gain), reach)
        return cls(pos, d, graph, routes, gain)

    def routes_of(self, points: F64, atoms: npt.NDArray[np.int64], tau: float) -> F64:
        """dist(P_k, a_k) for pairs of a point and an atom: the Boltzmann mean of the smooth
        routes at temperature tau, or (tau = 0) the thesis's minimum of its exact routes."""
        r = self.routes
        counts = (r.start[atoms + 1] - r.start[atoms]).astype(np.int64)
        pair = np.repeat(np.arange(len(atoms)), counts)
        first = np.repeat(r.start[atoms].astype(np.int64) - np.cumsum(counts) + counts, counts)
        idx = first + np.arange(int(counts.sum()))
        ends = self.graph.ends[r.bond[idx]]
        p = points[pair]
        ai = self.positions[ends[:, 0]]
        v = self.positions[ends[:, 1]] - ai
        l2 = (v * v).sum(axis=1)
        length = np.sqrt(l2)
        point = l2 == 0.0
        t = np.where(point, 0.0, ((p - ai) * v).sum(axis=1) / np.where(point, 1.0, l2))
        if tau > 0.0:
            u = np.where(point, 0.0, smooth_clamp(t, tau / np.where(point, 1.0, length)))
        else:
            u = np.clip(t, 0.0, 1.0)
        foot = ai + u[:, None] * v
        across = np.sqrt(((p - foot) ** 2).sum(axis=1) + tau * tau)
        # the two routes of every bond: through its end i, and through its end j
        route = np.concatenate(
            [across + u * length + r.g_i[idx], across + (1 - u) * length + r.g_j[idx]]
        )
        owner = np.concatenate([pair, pair])
        keep = np.isfinite(route)
        route, owner = route[keep], owner[keep]
        low = np.full(len(atoms), np.inf)
        np.minimum.at(low, owner, route)
        if tau <= 0.0:
            return low
        w = np.exp(-(route - low[owner]) / tau)
        num = np.bincount(owner, weights=route * w, minlength=len(atoms))
        den = np.bincount(owner, weights=w, minlength=len(atoms))
        out: F64 = num / den
        return out

    def density(
        self,
        points: npt.ArrayLike,
        sigma: float,
        *,
        strength: float = 1.0,
        smoothing: float = SMOOTHING,
        cutoff_sigmas: float | None = 4.0,
    ) -> F64:
        """S at every point (float64): eq. 5.5 with the smooth distance at tau = smoothing *
        sigma (0: the thesis's own), blended with the straight line by `strength`, each atom's
        Gaussian tapered at `cutoff_sigmas` as the renderer does (None: untruncated, then
        every atom within the route tables' reach is counted)."""
        from scipy.spatial import cKDTree

        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tau = float(smoothing) * float(sigma)
        lam = min(max(float(strength), 0.0), 1.0)
        reach = self.routes.reach if cutoff_sigmas is None else cutoff_sigmas * sigma
        if reach > self.routes.reach * (1.0 + 1e-9):
            raise ValueError(f"route tables reach {self.routes.reach} A, the density {reach} A")
        tree = cKDTree(self.positions)
        out = np.zeros(len(pts))
        for first in range(0, len(pts), 512):
            block = pts[first : first + 512]
            near = tree.query_ball_point(block, reach)
            owner = np.repeat(np.arange(len(block)), [len(x) for x in near])
            if not len(owner):
                continue
            atoms = np.concatenate([np.asarray(x, dtype=np.int64) for x in near])
            r2 = ((self.positions[atoms] - block[owner]) ** 2).sum(axis=1)
            dist2 = r2
            if lam > 0.0:
                m = self.routes_of(block[owner], atoms, tau)
                dist2 = (1.0 - lam) * r2 + lam * m * m
            e = dist2 / (2.0 * sigma * sigma)
            terms = self.densities[atoms] * taper(e, cutoff_sigmas)
            out[first : first + len(block)] = np.bincount(owner, terms, minlength=len(block))
        return out


def classical_density(
    points: npt.ArrayLike,
    positions: npt.ArrayLike,
    densities: npt.ArrayLike,
    sigma: float,
    cutoff_sigmas: float | None = 4.0,
) -> F64:
    """sum_a d_a g_sigma(|P - a|) (float64, every atom), with the renderer's taper."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(densities, dtype=np.float64)
    out = np.empty(len(p))
    for start in range(0, len(p), 256):
        block = p[start : start + 256]
        r2 = ((block[:, None, :] - pos[None]) ** 2).sum(axis=-1)
        out[start : start + 256] = (d[None] * taper(r2 / (2.0 * sigma**2), cutoff_sigmas)).sum(1)
    return out


def best_classical_sigma(
    values: F64,
    points: npt.ArrayLike,
    positions: npt.ArrayLike,
    densities: npt.ArrayLike,
    lo: float,
    hi: float,
) -> tuple[float, float, float]:
    """The classical density closest to `values` at `points` in least squares, over its width
    sigma' in [lo, hi] and an amplitude: (sigma', amplitude, relative residual |r| / |values|).
    A narrower classical Gaussian can look like a geodesic field; its residual says how much of
    the field it cannot explain."""

    def fit(s: float) -> tuple[float, float]:
        c = classical_density(points, positions, densities, s, None)
        cc = float(c @ c)
        amp = float(values @ c) / cc if cc > 0 else 0.0
        r = values - amp * c
        return float(np.sqrt(r @ r)), amp

    grid = np.geomspace(lo, hi, 41)
    errs = [fit(float(s))[0] for s in grid]
    k = int(np.argmin(errs))
    a, b = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, len(grid) - 1)])
    for _ in range(40):  # golden-section refinement between the grid's neighbours
        m1 = b - (b - a) / 1.618033988749895
        m2 = a + (b - a) / 1.618033988749895
        if fit(m1)[0] < fit(m2)[0]:
            b = m2
        else:
            a = m1
    s = 0.5 * (a + b)
    err, amp = fit(s)
    norm = float(np.sqrt(values @ values))
    return s, amp, (err / norm if norm > 0 else 0.0)


def merge_sigma(
    density: object, points: npt.ArrayLike, level: float, lo: float, hi: float
) -> float:
    """The least sigma in [lo, hi] at which `density(points, sigma)` reaches `level` at every one
    of `points` (the gap they sample is bridged), by bisection; hi when it never does."""
    pts = np.asarray(points, dtype=np.float64)

    def bridged(s: float) -> bool:
        return bool((np.asarray(density(pts, s)) >= level).all())  # type: ignore[operator]

    if not bridged(hi):
        return hi
    a, b = lo, hi
    for _ in range(30):
        m = math.sqrt(a * b)
        if bridged(m):
            b = m
        else:
            a = m
    return b


TABLE_STEP = 1.25
"""Route tables are built for a reach rounded up to a power of this: sliding sigma rebuilds
them only when the cutoff crosses a step (longer routes only add terms of negligible weight, and
the limit stays eq. 5.5)."""


@dataclass(frozen=True)
class GeodesicScales:
    """The numbers one (sigma, strength) pair gives the geodesic density on the device."""

    strength: float
    tau: float
    table_reach: float

    @classmethod
    def of(
        cls, sigma: float, strength: float, reach: float, smoothing: float = SMOOTHING
    ) -> GeodesicScales:
        steps = math.ceil(math.log(max(reach, 1e-3)) / math.log(TABLE_STEP) - 1e-9)
        return cls(
            strength=min(max(float(strength), 0.0), 1.0),
            tau=float(smoothing) * float(sigma),
            table_reach=TABLE_STEP**steps,
        )
