"""Thesis section 5.3, as printed: the geodesically warped atomic density (eqs. 5.2-5.6).

A float64 numpy reference, every atom and bond against every point:

- the bond graph M = (A, B) with edge weights built from the first differences of the atom
  densities, arclength-like: w_ij = sqrt(|a_i - a_j|^2 + (gain (d_i - d_j))^2) (the text sets
  "the first order differences of the density values" as edge weights "to match the
  one-dimensional, arclength-based warping functions"; `gain = inf` would keep only the
  differences, and then atoms of equal density are at distance 0);
- dist_M(a_i, a) by shortest paths;
- a point I on a bond b = (a_i, a_j): eq. 5.2,
  dist_M(I, a) = min(|I - a_i| + dist_M(a_i, a), |I - a_j| + dist_M(a_j, a));
- the projection of P onto a bond and whether P is in its span (definition 5, eq. 5.3), D(P, b)
  the distance from P to that projection;
- dist(P, a) = min_b { D(P, b) + dist_M(I_b, a) } (eq. 5.4), or with D squared (eq. 5.6);
- S(P) = sum_i d(a_i) g_sigma(dist(P, a_i)) with g_sigma(x) = exp(-x^2 / 2 sigma^2) (eq. 5.5).

`scalesteer`'s own warped density (`server/render/skeleton.py`) keeps what these gain and
drops the minimum over bonds that makes them creased and breaks them on rings; the figures of
`thesis/chapter5.py` show the two side by side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class BondGraph:
    positions: F64  # (n, 3)
    densities: F64  # (n,)
    bonds: npt.NDArray[np.int64]  # (m, 2)
    gain: float = 1.0

    def edge_weights(self) -> F64:
        a, b = self.bonds[:, 0], self.bonds[:, 1]
        length = np.linalg.norm(self.positions[a] - self.positions[b], axis=1)
        jump = self.densities[a] - self.densities[b]
        if math.isinf(self.gain):
            return np.abs(jump)
        out: F64 = np.sqrt(length**2 + (self.gain * jump) ** 2)
        return out

    def geodesics(self) -> F64:
        """dist_M between every pair of atoms (Floyd-Warshall; inf between components)."""
        n = len(self.positions)
        dist = np.full((n, n), np.inf)
        np.fill_diagonal(dist, 0.0)
        for (i, j), w in zip(self.bonds, self.edge_weights(), strict=True):
            dist[i, j] = dist[j, i] = min(dist[i, j], w)
        for k in range(n):
            dist = np.minimum(dist, dist[:, k : k + 1] + dist[k : k + 1, :])
        return dist


def projections(graph: BondGraph, points: npt.ArrayLike) -> tuple[F64, F64, F64]:
    """For every point and bond (definition 5, eq. 5.3): the parameter u of the projection on the
    bond's line clamped to the bond (u in [0, 1] is P in the span), the projected point I, and
    D(P, b) = |P - I|. Shapes (m, nb), (m, nb, 3), (m, nb)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a = graph.positions[graph.bonds[:, 0]]
    v = graph.positions[graph.bonds[:, 1]] - a
    len2 = (v * v).sum(axis=1)
    u = ((p[:, None, :] - a[None]) * v[None]).sum(axis=-1) / len2[None]
    u = np.clip(u, 0.0, 1.0)
    proj = a[None] + u[..., None] * v[None]
    d = np.linalg.norm(p[:, None, :] - proj, axis=-1)
    return u, proj, d


def thesis_distances(graph: BondGraph, points: npt.ArrayLike, squared: bool = False) -> F64:
    """dist(P, a) for every point and atom: eq. 5.4, or eq. 5.6 with `squared`."""
    geo = graph.geodesics()
    _u, proj, d = projections(graph, points)
    a, b = graph.bonds[:, 0], graph.bonds[:, 1]
    pa = np.linalg.norm(proj - graph.positions[a][None], axis=-1)  # |I - a_i|
    pb = np.linalg.norm(proj - graph.positions[b][None], axis=-1)  # |I - a_j|
    # eq. 5.2 for every point, bond and atom: (m, nb, n)
    along = np.minimum(pa[..., None] + geo[a][None], pb[..., None] + geo[b][None])
    across = d * d if squared else d
    total: F64 = np.min(across[..., None] + along, axis=1)
    return total


def thesis_density(
    graph: BondGraph, points: npt.ArrayLike, sigma: float, squared: bool = False
) -> F64:
    """S(P) of eq. 5.5 with the distance of eq. 5.4 (or 5.6)."""
    dist = thesis_distances(graph, points, squared)
    out: F64 = (graph.densities[None] * np.exp(-(dist**2) / (2.0 * sigma**2))).sum(axis=1)
    return out


def classical_density(graph: BondGraph, points: npt.ArrayLike, sigma: float) -> F64:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d2 = ((p[:, None, :] - graph.positions[None]) ** 2).sum(axis=-1)
    out: F64 = (graph.densities[None] * np.exp(-d2 / (2.0 * sigma**2))).sum(axis=1)
    return out


def crease_ratio(
    density: object, origin: npt.ArrayLike, direction: npt.ArrayLike, half: float, h: float
) -> float:
    """How the largest second difference of `density` along a line shrinks when the step
    halves: 4 for a field with a bounded second derivative, about 2 across a crease."""
    o = np.asarray(origin, dtype=np.float64)
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    worst = []
    for step in (h, h / 2):
        t = np.arange(-half, half + step / 2, step)
        s = np.asarray(density(o + t[:, None] * v))  # type: ignore[operator]
        worst.append(float(np.abs(s[2:] - 2.0 * s[1:-1] + s[:-2]).max()))
    return worst[0] / worst[1]


# ---------------------------------------------------------------- the molecules of figs. 5.5-5.8


def three_atoms(center_density: float = 1.0) -> BondGraph:
    """Fig. 5.5: two bonds, three atoms (the middle one `center_density` times the others)."""
    pos = np.array([[-1.3, -0.75, 0.0], [0.0, 0.0, 0.0], [1.3, -0.75, 0.0]])
    dens = np.array([1.0, center_density, 1.0])
    return BondGraph(pos, dens, np.array([[0, 1], [1, 2]]))


def ring(n: int = 6, bond: float = 1.39) -> BondGraph:
    """Fig. 5.8: a ring of `n` atoms (a benzene-sized hexagon by default)."""
    radius = bond / (2.0 * math.sin(math.pi / n))
    ang = 2.0 * math.pi * np.arange(n) / n
    pos = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(n)], axis=1)
    bonds = np.array([[i, (i + 1) % n] for i in range(n)])
    return BondGraph(pos, np.ones(n), bonds)
