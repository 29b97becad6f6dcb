"""Per-atom colours, radii and weights derived once from a topology (numpy only).

Colours are packed as RGBA8 in one uint32 (r in the low byte) so the device keeps 4 bytes per
atom; the ray caster blends them by each atom's Gaussian contribution at the hit point.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology
from protocol.messages import ColorBy, Legend, LegendEntry

RGB = tuple[float, float, float]
MAX_LEGEND = 24
"""Swatches a categorical legend lists at most (the most common first)."""

R_REF = 1.7
"""Reference radius (carbon, angstrom): in `vdw` mode an atom's width is sigma * r / R_REF."""

DEFAULT_RADIUS = 1.7

#: Jmol/CPK element colours (the common MD elements; others fall back to UNKNOWN_ELEMENT).
ELEMENT_COLORS: dict[str, RGB] = {
    "H": (1.0, 1.0, 1.0),
    "He": (0.85, 1.0, 1.0),
    "Li": (0.8, 0.5, 1.0),
    "B": (1.0, 0.71, 0.71),
    "C": (0.565, 0.565, 0.565),
    "N": (0.188, 0.314, 0.973),
    "O": (1.0, 0.051, 0.051),
    "F": (0.565, 0.878, 0.314),
    "Na": (0.671, 0.361, 0.949),
    "Mg": (0.541, 1.0, 0.0),
    "Al": (0.749, 0.651, 0.651),
    "Si": (0.941, 0.784, 0.627),
    "P": (1.0, 0.502, 0.0),
    "S": (1.0, 1.0, 0.188),
    "Cl": (0.122, 0.941, 0.122),
    "K": (0.561, 0.251, 0.831),
    "Ca": (0.239, 1.0, 0.0),
    "Mn": (0.612, 0.478, 0.78),
    "Fe": (0.878, 0.4, 0.2),
    "Co": (0.941, 0.565, 0.627),
    "Ni": (0.314, 0.816, 0.314),
    "Cu": (0.784, 0.502, 0.2),
    "Zn": (0.49, 0.502, 0.69),
    "Se": (1.0, 0.631, 0.0),
    "Br": (0.651, 0.161, 0.161),
    "I": (0.58, 0.0, 0.58),
}
UNKNOWN_ELEMENT: RGB = (1.0, 0.078, 0.576)

#: Bondi van der Waals radii (angstrom), used when the topology carries no radii.
VDW_RADII: dict[str, float] = {
    "H": 1.1,
    "C": 1.7,
    "N": 1.55,
    "O": 1.52,
    "F": 1.47,
    "Na": 2.27,
    "Mg": 1.73,
    "P": 1.8,
    "S": 1.8,
    "Cl": 1.75,
    "K": 2.75,
    "Ca": 2.31,
    "Fe": 1.94,
    "Zn": 1.39,
    "Cu": 1.4,
    "Se": 1.9,
    "Br": 1.85,
    "I": 1.98,
}

#: Atomic numbers (electron counts of the neutral atoms) for `density_weights="electrons"`.
ATOMIC_NUMBERS: dict[str, int] = {
    "H": 1, "He": 2, "Li": 3, "Be": 4, "B": 5, "C": 6, "N": 7, "O": 8, "F": 9, "Ne": 10,
    "Na": 11, "Mg": 12, "Al": 13, "Si": 14, "P": 15, "S": 16, "Cl": 17, "Ar": 18, "K": 19,
    "Ca": 20, "Mn": 25, "Fe": 26, "Co": 27, "Ni": 28, "Cu": 29, "Zn": 30, "Se": 34, "Br": 35,
    "I": 53,
}  # fmt: skip

_HYDROPHOBIC = {"ALA", "VAL", "LEU", "ILE", "MET", "PHE", "TRP", "PRO", "GLY", "NLE", "MSE"}
_POLAR = {"SER", "THR", "ASN", "GLN", "TYR", "CYS", "CYX", "HSE"}
_ACIDIC = {"ASP", "GLU", "ASH", "GLH"}
_BASIC = {"LYS", "ARG", "HIS", "HID", "HIE", "HIP", "HSD", "HSP", "LYN"}
_NUCLEIC = {"A", "C", "G", "U", "T", "DA", "DC", "DG", "DT", "DU", "RA", "RC", "RG", "RU", "ADE"}
_WATER = {"HOH", "WAT", "SOL", "TIP3", "TIP4", "TIP5", "SPC", "H2O", "T3P", "T4P"}
_IONS = {"NA", "CL", "K", "MG", "CA", "ZN", "SOD", "CLA", "POT", "CAL", "NA+", "CL-"}

#: residue class -> colour, for `color_by="residue"`.
RESIDUE_CLASS_COLORS: dict[str, RGB] = {
    "hydrophobic": (0.93, 0.86, 0.66),
    "polar": (0.42, 0.8, 0.52),
    "acidic": (0.9, 0.25, 0.25),
    "basic": (0.3, 0.45, 0.95),
    "nucleic": (0.98, 0.6, 0.2),
    "water": (0.55, 0.8, 1.0),
    "ion": (0.75, 0.45, 0.95),
    "other": (0.7, 0.7, 0.7),
}

#: categorical palette for chains, in order of first appearance.
CHAIN_PALETTE: tuple[RGB, ...] = (
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.4, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
    (0.68, 0.78, 0.91),
    (1.0, 0.73, 0.47),
)


def residue_class(name: str) -> str:
    """The coarse class of a residue name (protein side-chain chemistry, nucleic, water, ion)."""
    n = name.strip().upper()
    for cls, names in (
        ("hydrophobic", _HYDROPHOBIC),
        ("polar", _POLAR),
        ("acidic", _ACIDIC),
        ("basic", _BASIC),
        ("nucleic", _NUCLEIC),
        ("water", _WATER),
        ("ion", _IONS),
    ):
        if n in names:
            return cls
    return "other"


def _per_value(values: Sequence[str], fn: Callable[[str], Any]) -> npt.NDArray[Any]:
    """fn applied to each distinct value once, broadcast back (fast for millions of atoms)."""
    uniq, inverse = np.unique(np.asarray(values, dtype=str), return_inverse=True)
    table = np.array([fn(str(u)) for u in uniq])
    out: npt.NDArray[Any] = table[inverse.reshape(-1)]
    return out


def _element_key(e: str) -> str:
    e = e.strip()
    return e[:1].upper() + e[1:].lower() if e else ""


def pack_rgba(rgb: npt.ArrayLike) -> npt.NDArray[np.uint32]:
    """(n, 3) floats in [0, 1] -> (n,) uint32 RGBA8 with alpha 255, red in the low byte."""
    c = np.clip(np.asarray(rgb, dtype=np.float64).reshape(-1, 3), 0.0, 1.0)
    b = np.floor(c * 255.0 + 0.5).astype(np.uint32)
    out: npt.NDArray[np.uint32] = (
        b[:, 0] | (b[:, 1] << np.uint32(8)) | (b[:, 2] << np.uint32(16)) | np.uint32(255 << 24)
    )
    return out


def unpack_rgba(packed: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Inverse of `pack_rgba` for the colour channels: (n,) uint32 -> (n, 3) floats."""
    p = np.asarray(packed, dtype=np.uint32)
    return np.stack([(p >> s) & 255 for s in (0, 8, 16)], axis=-1).astype(np.float64) / 255.0


def _ramp(values: npt.NDArray[np.float64], stops: Sequence[RGB]) -> npt.NDArray[np.float64]:
    """Piecewise-linear colour ramp of values in [0, 1] through equally spaced stops."""
    s = np.asarray(stops, dtype=np.float64)
    xs = np.linspace(0.0, 1.0, len(s))
    v = np.clip(values, 0.0, 1.0)
    return np.stack([np.interp(v, xs, s[:, k]) for k in range(3)], axis=-1)


_BLUE_WHITE_RED: tuple[RGB, ...] = ((0.23, 0.3, 0.75), (0.95, 0.95, 0.95), (0.7, 0.02, 0.15))
_RED_WHITE_BLUE: tuple[RGB, ...] = ((0.85, 0.12, 0.12), (0.95, 0.95, 0.95), (0.15, 0.3, 0.9))
MOTION_RAMP = _BLUE_WHITE_RED
MOTION_RANGE = (1.0, 3.0)
"""Warp rates the motion colours span: 1 (at rest, blue) to 3 (fast, red); computed on the
device each frame (`server.render.temporal`)."""


def atom_rgb(
    topology: Topology, color_by: ColorBy, uniform: RGB = (0.85, 0.85, 0.9)
) -> npt.NDArray[np.float64]:
    """(n, 3) colours in [0, 1] for one colouring scheme.

    `bfactor` maps the 2nd..98th percentile range onto blue-white-red; `charge` maps
    [-q, +q] (q = 98th percentile of |charge|) onto red-white-blue. Either falls back to
    `uniform` when the topology has no such values, so a viewer's choice never fails.
    """
    n = topology.n_atoms
    if n == 0:
        return np.zeros((0, 3))
    if color_by == "element":
        return _per_value(
            topology.elements, lambda e: ELEMENT_COLORS.get(_element_key(e), UNKNOWN_ELEMENT)
        ).astype(np.float64)
    if color_by == "residue":
        return _per_value(
            topology.residue_names, lambda r: RESIDUE_CLASS_COLORS[residue_class(r)]
        ).astype(np.float64)
    if color_by == "chain":
        chains = np.asarray(topology.chain_ids, dtype=str)
        uniq, first, inverse = np.unique(chains, return_index=True, return_inverse=True)
        rank = np.empty(len(uniq), dtype=np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(uniq))
        pal = np.asarray(CHAIN_PALETTE, dtype=np.float64)
        chain_rgb: npt.NDArray[np.float64] = pal[rank[inverse.reshape(-1)] % len(pal)]
        return chain_rgb
    if color_by == "bfactor" and topology.bfactors is not None:
        b = topology.bfactors.to_numpy().astype(np.float64)
        lo, hi = _bfactor_range(b)
        return _ramp((b - lo) / (hi - lo), _BLUE_WHITE_RED)
    if color_by == "charge" and topology.charges is not None:
        q = topology.charges.to_numpy().astype(np.float64)
        qmax = _charge_range(q)
        return _ramp(0.5 + 0.5 * q / qmax, _RED_WHITE_BLUE)
    return np.tile(np.asarray(uniform, dtype=np.float64), (n, 1))


def _bfactor_range(b: npt.NDArray[np.float64]) -> tuple[float, float]:
    lo, hi = (float(v) for v in np.percentile(b, [2.0, 98.0]))
    return lo, hi if hi > lo else lo + 1.0


def _charge_range(q: npt.NDArray[np.float64]) -> float:
    qmax = float(np.percentile(np.abs(q), 98.0))
    return qmax if qmax > 0 else 1.0


def legend(topology: Topology, color_by: ColorBy, uniform: RGB = (0.85, 0.85, 0.9)) -> Legend:
    """What the colours of `atom_rgb` mean, for the dashboard's legend: named swatches for the
    categorical schemes (those present in this topology, most atoms first), a ramp with its
    value range for the continuous ones."""
    if color_by == "element":
        names, counts = np.unique(np.asarray(topology.elements, dtype=str), return_counts=True)
        order = np.argsort(-counts, kind="stable")
        entries = [
            LegendEntry(
                label=_element_key(str(names[i])) or "?",
                color=ELEMENT_COLORS.get(_element_key(str(names[i])), UNKNOWN_ELEMENT),
            )
            for i in order[:MAX_LEGEND]
        ]
        return Legend(color_by=color_by, entries=entries)
    if color_by == "residue":
        classes = _per_value(topology.residue_names, residue_class)
        present, counts = np.unique(classes, return_counts=True)
        order = np.argsort(-counts, kind="stable")
        entries = [
            LegendEntry(label=str(present[i]), color=RESIDUE_CLASS_COLORS[str(present[i])])
            for i in order
        ]
        return Legend(color_by=color_by, entries=entries)
    if color_by == "chain":
        chains = np.asarray(topology.chain_ids, dtype=str)
        uniq, first = np.unique(chains, return_index=True)
        in_order = [str(uniq[i]) for i in np.argsort(first, kind="stable")]
        entries = [
            LegendEntry(label=name or "?", color=CHAIN_PALETTE[k % len(CHAIN_PALETTE)])
            for k, name in enumerate(in_order[:MAX_LEGEND])
        ]
        return Legend(color_by=color_by, entries=entries)
    if color_by == "bfactor" and topology.bfactors is not None:
        lo, hi = _bfactor_range(topology.bfactors.to_numpy().astype(np.float64))
        return Legend(color_by=color_by, ramp=list(_BLUE_WHITE_RED), low=lo, high=hi, unit="Å²")
    if color_by == "charge" and topology.charges is not None:
        qmax = _charge_range(topology.charges.to_numpy().astype(np.float64))
        return Legend(color_by=color_by, ramp=list(_RED_WHITE_BLUE), low=-qmax, high=qmax, unit="e")
    if color_by == "motion":
        low, high = MOTION_RANGE
        return Legend(color_by=color_by, ramp=list(MOTION_RAMP), low=low, high=high, unit="γ′")
    label = "uniform" if color_by == "uniform" else f"uniform (no {color_by} in this topology)"
    return Legend(color_by=color_by, entries=[LegendEntry(label=label, color=uniform)])


def atom_colors(
    topology: Topology, color_by: ColorBy, uniform: RGB = (0.85, 0.85, 0.9)
) -> npt.NDArray[np.uint32]:
    """(n,) packed RGBA8 colours for the device."""
    return pack_rgba(atom_rgb(topology, color_by, uniform))


def atom_radii(topology: Topology) -> npt.NDArray[np.float32]:
    """(n,) radii in angstrom: the topology's own, else Bondi radii by element."""
    if topology.radii is not None:
        r = topology.radii.to_numpy().astype(np.float32)
        return np.where(r > 0, r, np.float32(DEFAULT_RADIUS)).astype(np.float32)
    if topology.n_atoms == 0:
        return np.zeros(0, dtype=np.float32)
    return _per_value(
        topology.elements, lambda e: VDW_RADII.get(_element_key(e), DEFAULT_RADIUS)
    ).astype(np.float32)


def atom_weights(topology: Topology, kind: str = "uniform") -> npt.NDArray[np.float32]:
    """(n,) the atom densities d(a_i) of the thesis (eq. 5.5): one per atom (`uniform`: the
    density models where matter is; the width, not the height, carries the atom's size in
    `vdw` mode), or the atom's electron count, its atomic number (`electrons`; unknown
    elements count as carbon)."""
    if kind == "uniform":
        return np.ones(topology.n_atoms, dtype=np.float32)
    if kind != "electrons":
        raise ValueError(f"density weights must be 'uniform' or 'electrons', got {kind!r}")
    return np.array(
        [ATOMIC_NUMBERS.get(_element_key(e), 6) for e in topology.elements], dtype=np.float32
    )
