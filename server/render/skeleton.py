"""The carved density: its topology tables and its float64 reference.

The carved density (docs/rendering.md, "The carved density") is a Gaussian density of the atoms
multiplied by a factor that falls away from the bond skeleton. Strength lambda in [0, 1] narrows
the atoms' Gaussians and deepens the factor:

    S(P) = sum_i dt_i exp(-|P - a_i|^2 / (2 s3^2)) * exp(-lambda^2 kappa^2 phi(P)^2 / (2 sigma^2))

- s3 = sigma sqrt(1 - (c lambda)^2): at full strength the Gaussians are 0.6 sigma wide
  (c = GRAPH_SHARE);
- dt = the atom weights d averaged along the bond graph at scale sg = c lambda sigma, over the
  graph distance where a bond's length is the arclength of the weights across it,
  sqrt(l^2 + (gain (d_i - d_j))^2). With uniform weights (the default) this average returns
  every weight unchanged; with electron weights it blurs them along the bonds, less across a
  large weight difference;
- phi(P) = a smooth distance from P to the bond skeleton (the bonds as segments; an atom with no
  bond is a point): a harmonic soft minimum of the segment distances with compact support R,
  zero on every bond and saturating at R far away (kappa = KAPPA).

No distance in it is measured through the bond graph: it is not the thesis's warped density
(that is `geodesic.py`). What it does is measured against the classical density at the same
sigma *and* at 0.6 sigma (docs/rendering.md): most of its narrower look is the narrower Gaussian.

At lambda = 0 every piece is the identity: S is the classical density. On the axis of a straight
chain (between its end atoms) phi = 0 and S is the classical scale space (s3) of the
along-graph average (eq. 3.3's warped convolution on the graph, scale sg) of the atom weights:
both computed by `timewarp` (tests/render/test_carved.py). The density never exceeds the
classical density of the same weights and spatial scale, so the classical cell bounds stay valid.

This module is plain numpy: the Renderer prepares the tables here, the kernels live in
`carved.py`, and `carved_density` is the float64 reference the kernels are tested against.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from protocol import Topology

KAPPA = 1.5
"""How much farther a point is from the atoms, in the carved space, per unit of its distance
from the skeleton (at full strength)."""
GRAPH_SHARE = 0.8
"""At full strength, the share c of sigma that smooths along the bond graph (sg = c sigma);
space keeps s3 = sigma sqrt(1 - c^2) = 0.6 sigma."""
GAIN = 0.25
"""Angstrom of warped bond length per unit of density difference across a bond (with electron
weights a C-H bond of 1.09 A is 1.66 A long in the warped graph)."""
SKELETON_POWER = 4
"""p of the harmonic soft minimum (sum_s c_s dist_s^-2p)^(-1/p) that makes phi smooth."""
SKELETON_MIN_RANGE = 2.0
SKELETON_RANGE_SIGMAS = 1.5
"""phi looks at segments within R = max(2 A, 1.5 sigma) and saturates at R beyond them."""
GRAPH_CUTOFF_SIGMAS = 4.0
"""The along-graph smoothing reaches sg * this (warped angstrom)."""
GRAPH_TABLE = 128
"""At most this many graph-nearest atoms enter one atom's smoothing (exact below that)."""

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class WarpScales:
    """The numbers one (sigma, strength) pair gives the carved density."""

    sigma: float
    strength: float
    space: float  # s3
    graph: float  # sg
    atten: float  # lambda^2 kappa^2 / (2 sigma^2)
    reach: float  # R

    @classmethod
    def of(cls, sigma: float, strength: float) -> WarpScales:
        lam = min(max(float(strength), 0.0), 1.0)
        share = GRAPH_SHARE * lam
        return cls(
            sigma=float(sigma),
            strength=lam,
            space=float(sigma) * math.sqrt(1.0 - share * share),
            graph=float(sigma) * share,
            atten=(lam * KAPPA) ** 2 / (2.0 * float(sigma) ** 2),
            reach=max(SKELETON_MIN_RANGE, SKELETON_RANGE_SIGMAS * float(sigma)),
        )


@dataclass(frozen=True)
class Skeleton:
    """The bond graph of a topology as the carved density uses it.

    `segments` (m, 2): every bond as (i, j), then every atom without bonds as (i, i);
    `adj_start`, `adj_atom`, `adj_bond`: CSR neighbours of each atom and the bond joining them.
    """

    n_atoms: int
    bonds: npt.NDArray[np.int32]
    segments: npt.NDArray[np.int32]
    adj_start: npt.NDArray[np.int32]
    adj_atom: npt.NDArray[np.int32]
    adj_bond: npt.NDArray[np.int32]

    @classmethod
    def of(cls, topology: Topology) -> Skeleton:
        n = int(topology.n_atoms)
        raw = topology.bonds.to_numpy().reshape(-1, 2).astype(np.int64)
        raw = raw[raw[:, 0] != raw[:, 1]]
        bonds = np.unique(np.sort(raw, axis=1), axis=0).astype(np.int32)
        degree = np.bincount(bonds.ravel(), minlength=n) if len(bonds) else np.zeros(n, int)
        lonely = np.nonzero(degree == 0)[0].astype(np.int32)
        segments = np.concatenate([bonds, np.stack([lonely, lonely], axis=1)]).astype(np.int32)
        ends = np.concatenate([bonds[:, 0], bonds[:, 1]])
        others = np.concatenate([bonds[:, 1], bonds[:, 0]])
        ids = np.concatenate([np.arange(len(bonds)), np.arange(len(bonds))])
        order = np.lexsort((others, ends))
        start = np.zeros(n + 1, dtype=np.int32)
        np.add.at(start, ends + 1, 1)
        return cls(
            n_atoms=n,
            bonds=bonds,
            segments=segments,
            adj_start=np.cumsum(start).astype(np.int32),
            adj_atom=others[order].astype(np.int32),
            adj_bond=ids[order].astype(np.int32),
        )

    def bond_lengths(self, positions: npt.ArrayLike) -> F64:
        pos = np.asarray(positions, dtype=np.float64)
        if not len(self.bonds):
            return np.zeros(0)
        diff = pos[self.bonds[:, 0]] - pos[self.bonds[:, 1]]
        out: F64 = np.sqrt((diff * diff).sum(axis=1))
        return out

    def warped_lengths(self, positions: npt.ArrayLike, densities: npt.ArrayLike) -> F64:
        """Each bond's arclength of the density along it: sqrt(l^2 + (gain (d_i - d_j))^2)."""
        d = np.asarray(densities, dtype=np.float64)
        length = self.bond_lengths(positions)
        if not len(self.bonds):
            return length
        jump = GAIN * (d[self.bonds[:, 0]] - d[self.bonds[:, 1]])
        out: F64 = np.sqrt(length * length + jump * jump)
        return out

    def cell_weights(self, positions: npt.ArrayLike) -> F64:
        """Each atom's share of the skeleton (the quadrature weight of the smoothing): half of
        each bond it has, and an end atom counts its bond twice (the 1-D library's mirrored end
        cell); an atom without bonds weighs 1."""
        length = self.bond_lengths(positions)
        w = np.zeros(self.n_atoms)
        if len(self.bonds):
            np.add.at(w, self.bonds[:, 0], 0.5 * length)
            np.add.at(w, self.bonds[:, 1], 0.5 * length)
            degree = np.bincount(self.bonds.ravel(), minlength=self.n_atoms)
            end = degree == 1
            w[end] *= 2.0
        w[w <= 0.0] = 1.0
        return w

    def max_segment(self, positions: npt.ArrayLike) -> float:
        length = self.bond_lengths(positions)
        return float(length.max()) if len(length) else 0.0


# ---------------------------------------------------------------- float64 reference


def graph_distances(
    skeleton: Skeleton, lengths: F64, source: int, limit: float
) -> dict[int, float]:
    """Shortest warped path lengths from `source` to every atom within `limit` (Dijkstra)."""
    best = {source: 0.0}
    heap = [(0.0, source)]
    done: set[int] = set()
    while heap:
        du, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        for e in range(int(skeleton.adj_start[u]), int(skeleton.adj_start[u + 1])):
            v = int(skeleton.adj_atom[e])
            dv = du + float(lengths[skeleton.adj_bond[e]])
            if dv <= limit and dv < best.get(v, math.inf):
                best[v] = dv
                heapq.heappush(heap, (dv, v))
    return best


def smoothed_densities(
    skeleton: Skeleton, positions: npt.ArrayLike, densities: npt.ArrayLike, scale: float
) -> F64:
    """dt: the densities smoothed along the bond graph by a normalised Gaussian (std `scale`)
    of the warped geodesic distance, each atom weighted by its share of the skeleton."""
    d = np.asarray(densities, dtype=np.float64)
    if scale <= 0.0 or not len(skeleton.bonds):
        return d.copy()
    lengths = skeleton.warped_lengths(positions, d)
    cells = skeleton.cell_weights(positions)
    limit = GRAPH_CUTOFF_SIGMAS * scale
    out = np.empty_like(d)
    for i in range(skeleton.n_atoms):
        near = graph_distances(skeleton, lengths, i, limit)
        idx = np.fromiter(near.keys(), dtype=np.int64)
        dist = np.fromiter(near.values(), dtype=np.float64)
        if len(idx) > GRAPH_TABLE:  # the kernel keeps the graph-nearest GRAPH_TABLE atoms
            keep = np.argsort(dist, kind="stable")[:GRAPH_TABLE]
            idx, dist = idx[keep], dist[keep]
        k = cells[idx] * np.exp(-(dist * dist) / (2.0 * scale * scale))
        out[i] = float((k * d[idx]).sum() / k.sum())
    return out


def segment_distances(points: npt.ArrayLike, a: npt.ArrayLike, b: npt.ArrayLike) -> tuple[F64, F64]:
    """(m, s) squared distances from points to segments [a, b] and (m, s, 3) vectors from the
    nearest point of each segment to each point."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a64 = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    ab = np.asarray(b, dtype=np.float64).reshape(-1, 3) - a64
    len2 = (ab * ab).sum(axis=1)
    ap = p[:, None, :] - a64[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(len2[None] > 0, (ap * ab[None]).sum(axis=-1) / len2[None], 0.0)
    u = np.clip(u, 0.0, 1.0)
    off = ap - u[..., None] * ab[None]
    return (off * off).sum(axis=-1), off


def skeleton_distance2(
    points: npt.ArrayLike, a: npt.ArrayLike, b: npt.ArrayLike, reach: float
) -> tuple[F64, F64]:
    """phi^2 and its gradient: (sum_s c_s (R^2/dist_s^2)^p + 1)^(-1/p) R^2 with
    c_s = (1 - dist_s^2 / R^2)^3 on segments within R (zero on a segment, R^2 far away)."""
    d2, off = segment_distances(points, a, b)
    r2 = reach * reach
    p = SKELETON_POWER
    inside = d2 < r2
    c = np.where(inside, (1.0 - d2 / r2) ** 3, 0.0)
    dc = np.where(inside, -3.0 * (1.0 - d2 / r2) ** 2 / r2, 0.0)  # d c / d(d2)
    # a point on a segment has phi = 0 and a minimum there (zero gradient); elsewhere the
    # ratios stay finite because every distance is positive
    on: npt.NDArray[np.bool_] = np.asarray((d2 <= 0.0).any(axis=1))
    safe = np.where(on[:, None] | ~inside, r2, d2)
    ratio = np.where(inside, r2 / safe, 0.0) ** p
    term = c * ratio
    dterm = dc * ratio - c * p * ratio / safe
    h = term.sum(axis=1)
    phi2 = np.where(on, 0.0, r2 * (h + 1.0) ** (-1.0 / p))
    # d phi2 / dP = r2 (-1/p) (h+1)^(-1/p-1) sum_s dterm_s * 2 off_s
    dh = 2.0 * (dterm[..., None] * off).sum(axis=1)
    scale = np.where(on, 0.0, -r2 / p * (h + 1.0) ** (-1.0 / p - 1.0))
    return phi2, scale[:, None] * dh


def carved_density(
    points: npt.ArrayLike,
    positions: npt.ArrayLike,
    densities: npt.ArrayLike,
    skeleton: Skeleton,
    sigma: float,
    strength: float,
    cutoff_sigmas: float | None = None,
) -> tuple[F64, F64]:
    """S and its gradient at points (float64, every atom, no grid); `cutoff_sigmas` tapers
    each atom's Gaussian to zero at that many spatial scales as the renderer does (None: the
    untruncated density)."""
    sc = WarpScales.of(sigma, strength)
    pos = np.asarray(positions, dtype=np.float64)
    dt = smoothed_densities(skeleton, pos, densities, sc.graph)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    off = pos[None] - p[:, None, :]
    d2 = (off * off).sum(axis=-1)
    e = d2 / (2.0 * sc.space**2)
    value, slope = np.exp(-e), np.exp(-e)
    if cutoff_sigmas is not None:  # the renderer's taper (density.py)
        ek = 0.5 * cutoff_sigmas**2
        inside = e < ek
        u = np.where(inside, e / ek, 1.0)
        w = (1.0 - u**16) ** 2
        dw = -32.0 * (1.0 - u**16) * u**15 / ek
        value = np.where(inside, value * w, 0.0)
        slope = np.where(inside, slope * (w - dw), 0.0)
    s = (dt[None] * value).sum(axis=1)
    grad = ((dt[None] * slope)[..., None] * off).sum(axis=1) / sc.space**2
    if sc.atten == 0.0:
        return s, grad
    seg = skeleton.segments
    phi2, dphi2 = skeleton_distance2(p, pos[seg[:, 0]], pos[seg[:, 1]], sc.reach)
    att = np.exp(-sc.atten * phi2)
    return s * att, att[:, None] * grad - (sc.atten * s * att)[:, None] * dphi2
