"""Small molecules with bonds for the warped-density tests: the thesis's three-atom molecule,
benzene, a hairpin, a straight chain, and villin (with its Phe rings) from the demo's PDB."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol import Topology, WireArray

DATA = Path(__file__).parent / "data"


@dataclass(frozen=True)
class Mol:
    topology: Topology
    positions: np.ndarray  # (n, 3) float32


def topology(
    elements: list[str],
    bonds: list[tuple[int, int]] | np.ndarray,
    residues: list[str] | None = None,
) -> Topology:
    n = len(elements)
    b = np.asarray(bonds, dtype=np.int32).reshape(-1, 2)
    return Topology(
        n_atoms=n,
        elements=elements,
        names=[f"{e}{i}" for i, e in enumerate(elements)],
        residue_ids=WireArray.from_numpy(np.ones(n, np.int32), "<i4"),
        residue_names=residues or ["MOL"] * n,
        chain_ids=["A"] * n,
        bonds=WireArray.from_numpy(b, "<i4"),
    )


def three_atoms() -> Mol:
    pos = np.array([[-1.3, -0.75, 0.0], [0.0, 0.0, 0.0], [1.3, -0.75, 0.0]], np.float32)
    return Mol(topology(["C", "C", "C"], [(0, 1), (1, 2)]), pos)


def benzene(hydrogens: bool = True) -> Mol:
    ang = np.arange(6) * math.pi / 3
    ring = np.stack([1.39 * np.cos(ang), 1.39 * np.sin(ang), 0 * ang], axis=1)
    bonds = [(i, (i + 1) % 6) for i in range(6)]
    elements = ["C"] * 6
    if hydrogens:
        h = np.stack([2.48 * np.cos(ang), 2.48 * np.sin(ang), 0 * ang], axis=1)
        ring = np.vstack([ring, h])
        bonds += [(i, i + 6) for i in range(6)]
        elements += ["H"] * 6
    return Mol(topology(elements, bonds), ring.astype(np.float32))


def hairpin(n: int = 8) -> Mol:
    """Two parallel strands 4 A apart, bonded at one end only."""
    x = np.arange(n) * 1.5
    top = np.stack([x, np.full(n, 2.0), np.zeros(n)], axis=1)
    bot = np.stack([x, np.full(n, -2.0), np.zeros(n)], axis=1)
    bonds = [(i, i + 1) for i in range(n - 1)] + [(n + i, n + i + 1) for i in range(n - 1)]
    bonds.append((0, n))
    return Mol(topology(["C"] * (2 * n), bonds), np.vstack([top, bot]).astype(np.float32))


def chain(elements: list[str], spacing: float = 1.4) -> Mol:
    """A straight chain along x."""
    n = len(elements)
    x = np.arange(n) * spacing
    pos = np.stack([x, np.zeros(n), np.zeros(n)], axis=1).astype(np.float32)
    return Mol(topology(elements, [(i, i + 1) for i in range(n - 1)]), pos)


def villin() -> Mol:
    d = np.load(DATA / "villin.npz")
    elements = [str(e) for e in d["elements"]]
    residues = [str(r) for r in d["residues"]]
    return Mol(topology(elements, d["bonds"], residues), d["positions"].astype(np.float32))


def villin_phe() -> Mol:
    """The first phenylalanine side-chain ring of villin with its hydrogens (CG..CZ, HD..HZ)."""
    d = np.load(DATA / "villin.npz")
    names = [str(x) for x in d["names"]]
    res = [str(r) for r in d["residues"]]
    ids = d["residue_ids"]
    first = int(ids[next(i for i, r in enumerate(res) if r == "PHE")])
    ring_names = {"CG", "CD1", "CD2", "CE1", "CE2", "CZ", "HD1", "HD2", "HE1", "HE2", "HZ"}
    keep = [i for i in range(len(names)) if ids[i] == first and names[i] in ring_names]
    where = {a: k for k, a in enumerate(keep)}
    bonds = [(where[a], where[b]) for a, b in d["bonds"] if a in where and b in where]
    elements = [str(d["elements"][i]) for i in keep]
    return Mol(topology(elements, bonds), d["positions"][keep].astype(np.float32))
