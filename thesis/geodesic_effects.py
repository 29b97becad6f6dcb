"""What the geodesic density does where the bond graph matters, each measure against the
classical density at the same sigma *and* at the sigma' of the classical density that fits the
geodesic field best (a narrower Gaussian can look like a warp; its fit says how much of the
effect is that).

``python -m thesis.geodesic_effects [--out docs/thesis/geodesic_effects.json]`` measures

- ring centre ratios, S(ring centre) / S(midpoint of a ring bond), at the sigma where the
  classical density has nearly filled the ring (its ratio 0.9; inside a protein the ring's
  neighbours keep its bonds denser than its centre up to large sigma, so full filling is no
  common yardstick): benzene, villin's phenylalanine and tryptophan rings in the whole protein,
  a heme pyrrole of cytochrome c3 (19HC);
- the merge sigma of a real beta-hairpin (cobrotoxin) and of the contact between the two
  unbonded chains of HIV protease (1HVR): the least sigma at which the density reaches the
  default level (a quarter of the mean density at the atoms) at every point of the gap;
- the best-fit classical sigma' and its residual in each region.

Densities come from the renderer's kernels on the CPU device (they match the float64 reference,
server/render/geodesic.py, within 2e-6: tests/render/test_geodesic.py), in the units relative
levels use (the mean density at the atoms is 1). Structures: MDAnalysisTests' files, bonds
guessed by `structures.reader` as the server does.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from protocol import RenderParams, Topology, WireArray
from server.render import Renderer
from server.render.camera import fit_camera
from server.render.geodesic import classical_density

LEVEL = 0.25
"""The default relative iso level."""
FILLED = 0.9
"""A ring counts as (nearly) filled where S(centre) / S(bond midpoint) reaches this."""


def relative_density(topology: Topology, positions: np.ndarray, params: RenderParams) -> Any:
    """points -> the density of `params` at them, in units of its mean at the atoms."""
    r = Renderer("cpu", max_atoms=max(topology.n_atoms, 1))
    r.set_topology(topology)
    r.set_positions(positions)
    r.render(params, fit_camera(positions, 8, 8), 8, 8)

    def at(points: np.ndarray) -> np.ndarray:
        values = r.evaluate(np.asarray(points, np.float32))[0]
        return np.asarray(values, dtype=np.float64)

    return at


def space(sigma: float, name: str) -> RenderParams:
    return RenderParams(sigma_A=sigma, scale_space=name)


def best_fit(
    topology: Topology, positions: np.ndarray, sigma: float, points: np.ndarray
) -> tuple[float, float]:
    """sigma' (in [0.3 sigma, 1.5 sigma]) and the relative residual of the classical density
    (times the best amplitude) that fits the geodesic one at `points` in least squares; both in
    absolute units (the fit's amplitude takes the levels' scale out)."""
    geo = relative_density(topology, positions, space(sigma, "geodesic"))(points)
    ones = np.ones(len(positions))

    def residual(s: float) -> float:
        c = classical_density(points, positions, ones, s)
        amp = float(geo @ c) / float(c @ c)
        r = geo - amp * c
        return float(np.sqrt(r @ r) / np.sqrt(geo @ geo))

    grid = np.geomspace(0.3 * sigma, 1.5 * sigma, 49)
    errors = [residual(float(s)) for s in grid]
    k = int(np.argmin(errors))
    return float(grid[k]), float(errors[k])


def ring_measure(
    name: str, topology: Topology, positions: np.ndarray, ring: list[int]
) -> dict[str, Any]:
    pos = positions.astype(np.float64)
    centre = pos[ring].mean(axis=0)
    mid = 0.5 * (pos[ring[0]] + pos[ring[1]])
    pts = np.stack([centre, mid])

    def ratio(name: str, sigma: float) -> float:
        s = relative_density(topology, positions, space(sigma, name))(pts)
        return float(s[0] / s[1])

    lo, hi = 0.3, 3.0  # the classical ring nearly fills (ratio 0.9) somewhere in between
    for _ in range(24):
        m = math.sqrt(lo * hi)
        if ratio("classical", m) >= FILLED:
            hi = m
        else:
            lo = m
    sigma = hi
    normal = np.linalg.svd(pos[ring] - centre)[2][2]
    rng = np.random.default_rng(0)
    radius = float(np.linalg.norm(pos[ring] - centre, axis=1).max()) + 1.0
    disc = rng.normal(size=(300, 3))
    disc -= np.outer(disc @ normal, normal)
    disc *= (radius * rng.uniform(0, 1, 300) ** 0.5 / np.linalg.norm(disc, axis=1))[:, None]
    disc += centre + np.outer(rng.normal(scale=0.3, size=300), normal)
    fit_sigma, residual = best_fit(topology, positions, sigma, disc)
    return {
        "ring": name,
        "sigma_fill_A": sigma,
        "classical": ratio("classical", sigma),
        "geodesic": ratio("geodesic", sigma),
        "best_fit_sigma_A": fit_sigma,
        "classical_at_best_fit": ratio("classical", fit_sigma),
        "fit_residual": residual,
    }


def merge_sigma(density_of: Any, points: np.ndarray) -> float:
    """The least sigma in [0.3, 4] with the density at every point at least the level (inf: not
    even at 4 A)."""

    def bridged(s: float) -> bool:
        return bool((density_of(s)(points) >= LEVEL).all())

    if not bridged(4.0):
        return math.inf
    lo, hi = 0.3, 4.0
    for _ in range(12):
        m = math.sqrt(lo * hi)
        if bridged(m):
            hi = m
        else:
            lo = m
    return hi


def gap_measure(
    name: str, topology: Topology, positions: np.ndarray, gap: np.ndarray
) -> dict[str, Any]:
    def of(kind: str) -> Any:
        return lambda s: relative_density(topology, positions, space(s, kind))

    classical = merge_sigma(of("classical"), gap)
    geodesic = merge_sigma(of("geodesic"), gap)
    rng = np.random.default_rng(1)
    region = np.concatenate([gap + rng.normal(scale=1.0, size=gap.shape) for _ in range(6)])
    fits = {s: best_fit(topology, positions, s, region) for s in (1.0, 2.0, 3.0)}
    # the classical density matched to the geodesic one at each sigma is the classical one at
    # sigma'(sigma): it merges where sigma'(sigma) reaches the classical merge sigma
    sig = np.array(sorted(fits))
    fitted = np.array([fits[s][0] for s in sig])
    matched = float(np.interp(classical, fitted, sig, right=math.inf))
    return {
        "gap": name,
        "points": len(gap),
        "merge_sigma_classical_A": classical,
        "merge_sigma_geodesic_A": geodesic,
        "merge_sigma_matched_classical_A": matched,
        "best_fit": {f"{s:g}": {"sigma_A": v[0], "residual": v[1]} for s, v in fits.items()},
    }


# ---------------------------------------------------------------- the structures


def load(path: str) -> tuple[Topology, np.ndarray, Any]:
    from structures.reader import load as read

    s = read(path)
    return s.topology, s.positions(0), s.universe


def atoms_named(universe: Any, resname: str, names: list[str], which: int = 0) -> list[int]:
    res = [r for r in universe.residues if r.resname == resname][which]
    index = {a.name: int(a.index) for a in res.atoms}
    return [index[n] for n in names]


def benzene() -> tuple[Topology, np.ndarray, list[int]]:
    ang = 2 * np.pi * np.arange(6) / 6
    pos = np.stack([1.39 * np.cos(ang), 1.39 * np.sin(ang), 0 * ang], 1).astype(np.float32)
    bonds = np.array([[i, (i + 1) % 6] for i in range(6)], np.int32)
    topo = Topology(
        n_atoms=6,
        elements=["C"] * 6,
        names=[f"C{i}" for i in range(6)],
        residue_ids=WireArray.from_numpy(np.ones(6, np.int32), "<i4"),
        residue_names=["BNZ"] * 6,
        chain_ids=["A"] * 6,
        bonds=WireArray.from_numpy(bonds, "<i4"),
    )
    return topo, pos, list(range(6))


def hairpin_gap(universe: Any) -> np.ndarray:
    """Midpoints across the longest antiparallel ladder of CA atoms closed by a short turn."""
    ca = universe.select_atoms("protein and name CA")
    pos = ca.positions.astype(np.float64)
    n = len(pos)
    best: list[tuple[int, int]] = []
    for i in range(n):
        for j in range(i + 4, min(i + 14, n)):
            if np.linalg.norm(pos[i] - pos[j]) < 6.0:
                ladder = [(i - k, j + k) for k in range(1, 8) if i - k >= 0 and j + k < n]
                rungs = [(a, b) for a, b in ladder if np.linalg.norm(pos[a] - pos[b]) < 6.0]
                if len(rungs) > len(best):
                    best = rungs
    return np.array([0.5 * (pos[a] + pos[b]) for a, b in best])


def contact_gap(universe: Any, count: int = 10) -> np.ndarray:
    """Midpoints of the closest heavy-atom pairs between chains A and B."""
    a = universe.select_atoms("protein and chainID A and not name H*")
    b = universe.select_atoms("protein and chainID B and not name H*")
    d = np.linalg.norm(a.positions[:, None] - b.positions[None], axis=-1)
    order = np.dstack(np.unravel_index(np.argsort(d, axis=None)[: count * 20], d.shape))[0]
    out: list[np.ndarray] = []
    used: set[int] = set()
    for i, j in order:
        if int(i) in used or d[i, j] < 3.4:  # a hydrogen bond or closer is one surface already
            continue
        used.add(int(i))
        out.append(0.5 * (a.positions[i] + b.positions[j]))
        if len(out) == count:
            break
    return np.asarray(out, dtype=np.float64)


def synthetic_hairpin() -> tuple[Topology, np.ndarray, np.ndarray]:
    """Two parallel strands of 8 atoms 1.5 A apart, 4 A between the strands, bonded at one end
    (the render tests' hairpin), and points along the middle of the gap."""
    x = np.arange(8) * 1.5
    pos = np.concatenate(
        [
            np.stack([x, np.full(8, 2.0), np.zeros(8)], 1),
            np.stack([x, np.full(8, -2.0), np.zeros(8)], 1),
        ]
    ).astype(np.float32)
    bonds = [(i, i + 1) for i in range(7)] + [(8 + i, 9 + i) for i in range(7)] + [(0, 8)]
    topo = Topology(
        n_atoms=16,
        elements=["C"] * 16,
        names=[f"C{i}" for i in range(16)],
        residue_ids=WireArray.from_numpy(np.ones(16, np.int32), "<i4"),
        residue_names=["HRP"] * 16,
        chain_ids=["A"] * 16,
        bonds=WireArray.from_numpy(np.asarray(bonds, np.int32), "<i4"),
    )
    gap = np.stack([x[2:], np.zeros(6), np.zeros(6)], 1).astype(np.float64)
    return topo, pos, gap


def carved_measures() -> dict[str, Any]:
    """The carved density against the classical one at the same sigma and at 0.6 sigma (the
    width of its Gaussians): benzene's ring centre ratio where the classical density fills the
    ring, and the hairpin's merge sigma."""
    topo, pos, ring = benzene()
    filled = ring_measure("benzene (no hydrogens)", topo, pos, ring)["sigma_fill_A"]
    # the carved density's measure of record: where the classical density fills the ring
    lo, hi = 0.3, 3.0
    centre0, mid0 = pos[ring].mean(axis=0), 0.5 * (pos[0] + pos[1])
    for _ in range(24):
        m = math.sqrt(lo * hi)
        c = classical_density(np.stack([centre0, mid0]), pos, np.ones(len(pos)), m)
        if c[0] >= c[1]:
            hi = m
        else:
            lo = m
    filled = hi
    centre = pos[ring].mean(axis=0)
    mid = 0.5 * (pos[0] + pos[1])
    pts = np.stack([centre, mid]).astype(np.float64)

    def ratio(kind: str, sigma: float) -> float:
        s = relative_density(topo, pos, space(sigma, kind))(pts)
        return float(s[0] / s[1])

    htopo, hpos, gap = synthetic_hairpin()

    def of(kind: str) -> Any:
        return lambda s: relative_density(htopo, hpos, space(s, kind))

    classical = merge_sigma(of("classical"), gap)
    return {
        "ring_sigma_A": filled,
        "ring_ratio": {
            "carved": ratio("carved", filled),
            "geodesic": ratio("geodesic", filled),
            "classical_at_0.6_sigma": ratio("classical", 0.6 * filled),
            "classical": ratio("classical", filled),
        },
        "hairpin_merge_sigma_A": {
            "carved": merge_sigma(of("carved"), gap),
            "geodesic": merge_sigma(of("geodesic"), gap),
            "classical_at_0.6_sigma": classical / 0.6,
            "classical": classical,
        },
    }


def measure() -> dict[str, Any]:
    import MDAnalysisTests

    from thesis.chapter5 import villin

    out: dict[str, Any] = {"rings": [], "gaps": []}
    topo, pos, ring = benzene()
    out["rings"].append(ring_measure("benzene (no hydrogens)", topo, pos, ring))
    vt, vp = villin()
    names = list(vt.names)
    residues = list(vt.residue_names)
    ids = vt.residue_ids.to_numpy()

    def ring_in(resname: str, atoms: list[str]) -> list[int]:
        first = next(int(ids[i]) for i, r in enumerate(residues) if r == resname)
        return [
            next(i for i in range(len(names)) if ids[i] == first and names[i] == a) for a in atoms
        ]

    phe = ring_in("PHE", ["CG", "CD1", "CE1", "CZ", "CE2", "CD2"])
    out["rings"].append(ring_measure("villin Phe (in the protein)", vt, vp, phe))
    trp6 = ring_in("TRP", ["CD2", "CE3", "CZ3", "CH2", "CZ2", "CE2"])
    out["rings"].append(ring_measure("villin Trp six-ring (in the protein)", vt, vp, trp6))
    trp5 = ring_in("TRP", ["CG", "CD1", "NE1", "CE2", "CD2"])
    out["rings"].append(ring_measure("villin Trp five-ring (in the protein)", vt, vp, trp5))
    folder = Path(MDAnalysisTests.__file__).parent / "data"
    ht, hp, hu = load(str(folder / "19hc.pdb.gz"))
    pyrrole = atoms_named(hu, "HEM", ["NA", "C1A", "C2A", "C3A", "C4A"])
    out["rings"].append(ring_measure("19HC heme pyrrole A (in the protein)", ht, hp, pyrrole))
    ct, cp, cu = load(str(folder / "cobrotoxin.pdb"))
    keep = cu.select_atoms("protein")
    protein = _subset(ct, cp, keep.indices)
    out["gaps"].append(gap_measure("cobrotoxin beta-hairpin", *protein, hairpin_gap(keep.universe)))
    it, ip, iu = load(str(folder / "1hvr.pdb"))
    chains = iu.select_atoms("protein")
    dimer = _subset(it, ip, chains.indices)
    out["gaps"].append(gap_measure("HIV protease chains A/B contact", *dimer, contact_gap(iu)))
    out["carved"] = carved_measures()
    return out


def _subset(
    topology: Topology, positions: np.ndarray, keep: np.ndarray
) -> tuple[Topology, np.ndarray]:
    """The atoms `keep` with the bonds among them."""
    keep = np.sort(np.asarray(keep, dtype=np.int64))
    where = np.full(topology.n_atoms, -1)
    where[keep] = np.arange(len(keep))
    bonds = topology.bonds.to_numpy().reshape(-1, 2)
    inside = (where[bonds[:, 0]] >= 0) & (where[bonds[:, 1]] >= 0)
    n = len(keep)
    sub = Topology(
        n_atoms=n,
        elements=[topology.elements[i] for i in keep],
        names=[topology.names[i] for i in keep],
        residue_ids=WireArray.from_numpy(
            topology.residue_ids.to_numpy()[keep].astype(np.int32), "<i4"
        ),
        residue_names=[topology.residue_names[i] for i in keep],
        chain_ids=[topology.chain_ids[i] for i in keep],
        bonds=WireArray.from_numpy(where[bonds[inside]].astype(np.int32), "<i4"),
    )
    return sub, positions[keep]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m thesis.geodesic_effects", description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("docs/thesis/geodesic_effects.json"))
    args = ap.parse_args(argv)
    result = measure()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    for r in result["rings"]:
        print(
            f"{r['ring']}: sigma {r['sigma_fill_A']:.2f} A, centre/midpoint classical "
            f"{r['classical']:.3f}, geodesic {r['geodesic']:.3f}, classical at sigma' "
            f"{r['best_fit_sigma_A']:.2f} A {r['classical_at_best_fit']:.3f} (fit residual "
            f"{r['fit_residual']:.3f})"
        )
    print("carved:", json.dumps(result["carved"]))
    for g in result["gaps"]:
        print(
            f"{g['gap']}: merge sigma classical {g['merge_sigma_classical_A']:.2f} A, geodesic "
            f"{g['merge_sigma_geodesic_A']:.2f} A, matched classical "
            f"{g['merge_sigma_matched_classical_A']:.2f} A"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
