"""Reading structures and trajectories (MDAnalysis) into protocol topologies and frames.

Shared by trajectory replay, the REST API and the still renderer, so a file that one of them
accepts, all of them accept. MDAnalysis is imported lazily: `pip install scalesteer[replay]`.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology, WireArray
from structures.binarycif import to_mmcif
from structures.cells import CRYSTAL_FORMATS, cell_of, deposited
from structures.errors import StructureError, reason
from structures.textcheck import CHECKS, refuse_binary
from structures.truncation import cut_short

STRUCTURE_FORMATS = (
    "pdb",
    "ent",
    "cif",
    "mmcif",
    "bcif",
    "gro",
    "xyz",
    "psf",
    "data",
    "pdbx",
    "pqr",
    "mol2",
    "crd",
    "tpr",
    "prmtop",
    "parm7",
)
TRAJECTORY_FORMATS = (
    "dcd",
    "xtc",
    "trr",
    "pdb",
    "nc",
    "ncdf",
    "xyz",
    "lammpsdump",
    "lammpstrj",
    "dump",
    "mdcrd",
    "inpcrd",
    "rst7",
    "gro",
)
MDANALYSIS_FORMATS = {
    "pdbx": "MMCIF",
    "lammpstrj": "LAMMPSDUMP",
    "dump": "LAMMPSDUMP",
    "rst7": "INPCRD",
}
"""Suffixes MDAnalysis does not know by that name, and the format they hold."""


@dataclass
class Structure:
    """A loaded universe: the topology message, and access to its frames."""

    topology: Topology
    universe: Any
    crystal: bool = False
    """A deposited model read alone (`CRYSTAL_FORMATS`): its cell is no periodic box."""
    notes: tuple[str, ...] = ()
    """What the reader took in silence and a user should hear (a trajectory cut short)."""

    @property
    def n_frames(self) -> int:
        """Frames of coordinates; 0 for a topology read without any."""
        return len(self.universe.trajectory) if _has(self.universe, "trajectory") else 0

    def positions(self, index: int = 0) -> npt.NDArray[np.float32]:
        """Positions (angstrom) of frame `index`."""
        with warnings.catch_warnings():  # readers warn about placeholder boxes on every frame
            warnings.simplefilter("ignore")
            ts = self.universe.trajectory[index]
            return np.ascontiguousarray(ts.positions, dtype=np.float32)

    def frame(
        self, index: int = 0
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32] | None]:
        """Positions (angstrom) of frame `index` and its periodic box (rows are the box
        vectors; None without one, or for a placeholder)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ts = self.universe.trajectory[index]
            positions = np.ascontiguousarray(ts.positions, dtype=np.float32)
            box = None
            if not self.crystal and cell_of(self.universe) is not None:
                box = np.asarray(ts.triclinic_dimensions, dtype=np.float32)
        return positions, box

    def frames(
        self, start: int = 0, stop: int | None = None, stride: int = 1
    ) -> Iterator[tuple[int, float, npt.NDArray[np.float32]]]:
        """(frame index, time in ps, positions) for a slice of the trajectory."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            frames = list(range(self.n_frames))[start:stop:stride]
        for index in frames:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ts = self.universe.trajectory[index]
            yield (
                int(ts.frame),
                float(ts.time),
                np.ascontiguousarray(ts.positions, dtype=np.float32),
            )


def _fmt(path: str) -> str:
    name = os.path.basename(path).lower()
    for suffix in (".gz", ".bz2"):
        name = name.removesuffix(suffix)
    return name.rsplit(".", 1)[-1] if "." in name else ""


# LAMMPS data files do not say how their Atoms lines are laid out except in an optional comment
# ("Atoms # full"); MDAnalysis needs the column names.
LAMMPS_ATOM_STYLES = {
    "atomic": "id type x y z",
    "charge": "id type charge x y z",
    "bond": "id resid type x y z",
    "angle": "id resid type x y z",
    "molecular": "id resid type x y z",
    "full": "id resid type charge x y z",
}


def lammps_atom_style(path: str) -> str | None:
    """The MDAnalysis `atom_style` for a LAMMPS data file, from its "Atoms # style" comment."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                head, _, comment = line.partition("#")
                if head.strip() == "Atoms":
                    return LAMMPS_ATOM_STYLES.get(comment.strip().split(" ")[0].lower())
    except OSError:
        return None
    return None


def load(
    topology: str,
    trajectories: Sequence[str] = (),
    *,
    guess_bonds: bool = True,
    max_atoms: int | None = None,
    atom_style: str | None = None,
    require_coordinates: bool = True,
) -> Structure:
    """Open a structure (PDB, mmCIF, GRO, XYZ, PSF, LAMMPS data, ...) with optional
    trajectory files.

    Raises `StructureError` with a readable reason for missing, unreadable or inconsistent
    files (for instance a trajectory whose atom count differs from the topology's).
    `atom_style` overrides the column layout of a LAMMPS data file. With
    `require_coordinates=False` a topology without coordinates (a bare PSF) is accepted: the IMD
    bridge gets its coordinates from the engine.
    """
    try:
        import MDAnalysis as mda
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise StructureError(
            "reading structures needs MDAnalysis: pip install scalesteer[replay]"
        ) from exc
    for path in (topology, *trajectories):
        if not os.path.isfile(path):
            raise StructureError(f"no such file: {path}")
    fmt = _fmt(topology)
    if fmt not in STRUCTURE_FORMATS:
        raise StructureError(
            f"unsupported structure format {fmt!r} ({os.path.basename(topology)}); "
            f"use one of {', '.join(STRUCTURE_FORMATS)}"
        )
    for t in trajectories:
        if _fmt(t) not in TRAJECTORY_FORMATS:
            raise StructureError(
                f"unsupported trajectory format {_fmt(t)!r} ({os.path.basename(t)}); "
                f"use one of {', '.join(TRAJECTORY_FORMATS)}"
            )
    for path in (topology, *trajectories):
        refuse_binary(path, _fmt(path))
        check = CHECKS.get(_fmt(path))
        if check is not None:
            check(path)
    kwargs: dict[str, Any] = {}
    if fmt in MDANALYSIS_FORMATS:
        kwargs["topology_format"] = MDANALYSIS_FORMATS[fmt]
    named = {MDANALYSIS_FORMATS.get(_fmt(t)) for t in trajectories} - {None}
    if len(named) == 1 and all(_fmt(t) in MDANALYSIS_FORMATS for t in trajectories):
        kwargs["format"] = named.pop()
    if fmt == "data":
        style = atom_style or lammps_atom_style(topology)
        if style is not None:
            kwargs["atom_style"] = style
    marked: bool | None = None  # a BinaryCIF's marks, read from its text while it lasts
    try:
        with contextlib.ExitStack() as stack, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            source = topology
            if fmt == "bcif":  # as mmCIF text, read whole while the folder lasts
                folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="bcif-"))
                source = to_mmcif(topology, folder, max_atoms)
                kwargs["topology_format"] = "MMCIF"
            u = mda.Universe(source, *trajectories, **kwargs)
            if fmt == "bcif":
                marked = deposited(source)
    except StructureError:
        raise
    except Exception as exc:
        msg = reason(exc, (topology, *trajectories))
        names = ", ".join(os.path.basename(f) for f in (topology, *trajectories))
        hint = ""
        if fmt == "data" and "atom_style" in str(exc):
            hint = " (add an 'Atoms # full' style comment to the data file)"
        raise StructureError(f"cannot read {names}: {msg[:300]}{hint}") from None
    n = int(u.atoms.n_atoms)
    if n == 0:
        raise StructureError(f"{os.path.basename(topology)} contains no atoms")
    has_coordinates = _has(u, "trajectory")
    if not has_coordinates and require_coordinates:
        raise StructureError(
            f"{os.path.basename(topology)} has no coordinates; add a coordinate or "
            "trajectory file (for example a PDB, DCD or XTC)"
        )
    if max_atoms is not None and n > max_atoms:
        raise StructureError(
            f"{os.path.basename(topology)} has {n} atoms, the limit is {max_atoms}"
        )
    crystal = (
        fmt in CRYSTAL_FORMATS
        and not trajectories
        and len(u.trajectory) == 1
        and (deposited(topology) if marked is None else marked)
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            topo = topology_of(
                u,
                guess_bonds=guess_bonds and has_coordinates,
                title=os.path.basename(topology),
                periodic=not crystal,
            )
    except (ValueError, TypeError) as exc:
        raise StructureError(f"cannot use {os.path.basename(topology)}: {exc}") from None
    return Structure(topology=topo, universe=u, crystal=crystal, notes=tuple(cut_short(u)))


def _strings(atoms: Any, attr: str, default: str, width: int) -> list[str]:
    values = getattr(atoms, attr, None) if _has(atoms, attr) else None
    if values is None:
        return [default] * int(atoms.n_atoms)
    return [str(v).strip()[:width] or default for v in values]


def _has(atoms: Any, attr: str) -> bool:
    try:
        getattr(atoms, attr)
    except Exception:  # MDAnalysis raises NoDataError (an AttributeError/ValueError) per attr
        return False
    return True


def _elements(u: Any) -> list[str]:
    atoms = u.atoms
    raw: list[str] = []
    if _has(atoms, "elements"):
        raw = [str(e).strip().capitalize() for e in atoms.elements]
        if all(raw):
            return raw
    if _has(atoms, "names"):
        from MDAnalysis.guesser.default_guesser import DefaultGuesser

        missing = [i for i, e in enumerate(raw) if not e] if raw else range(int(atoms.n_atoms))
        names = np.asarray(atoms.names)[np.asarray(missing, dtype=np.int64)]
        guessed = DefaultGuesser(None).guess_types(names)  # only those the file left blank
        out = raw or [""] * int(atoms.n_atoms)
        for i, e in zip(missing, guessed, strict=True):
            out[i] = str(e).strip().capitalize() or "X"
        return out
    if _has(atoms, "masses"):
        return [_element_of_mass(float(m)) for m in atoms.masses]
    return ["X"] * int(atoms.n_atoms)


def element_mass(element: str) -> float:
    """The standard atomic mass (g/mol) of an element symbol; 0 for one not in the table."""
    return _MASSES.get(element.strip().capitalize(), 0.0)


def _element_of_mass(mass: float) -> str:
    best = min(_MASSES, key=lambda e: abs(_MASSES[e] - mass))
    return best if abs(_MASSES[best] - mass) < 0.05 * max(mass, 1.0) else "X"


def topology_of(
    u: Any, *, guess_bonds: bool = True, title: str = "", periodic: bool = True
) -> Topology:
    """Build the `topology` message of an MDAnalysis universe, guessing elements and bonds."""
    atoms = u.atoms
    n = int(atoms.n_atoms)
    elements = [e[:3] for e in _elements(u)]
    bonds = np.zeros((0, 2), dtype=np.int32)
    try:
        found = u.bonds  # built once: a bond group of 25,000 bonds takes half a second
    except Exception:  # MDAnalysis raises NoDataError for a topology without bonds
        found = None
    if found is not None and len(found):
        bonds = np.asarray(found.indices, dtype=np.int32).reshape(-1, 2)
    # a PDB's CONECT records cover only hetero groups and disulfides: guess the rest too
    if guess_bonds and len(bonds) < n // 2 and n <= 500_000:
        from MDAnalysis.topology.guessers import guess_bonds as guess

        # the guesser looks radii up by atom type; map each type to its element's radius
        types = atoms.types if _has(atoms, "types") else np.array(elements)
        radii = {str(t): _VDW_GUESS.get(e, 1.5) for t, e in zip(types, elements, strict=True)}
        # across a periodic box too: a molecule the box cuts is still one molecule
        box = cell_of(u) if periodic else None
        try:
            pairs = guess(atoms, atoms.positions, box=box, vdwradii=radii)
        except ValueError as exc:
            span = float(np.ptp(atoms.positions, axis=0).max()) if n else 0.0
            why = (
                f"its {n} atoms span {span:.2f} A, less than a bond (are its coordinates all "
                "alike?); "
                if "too large for box" in str(exc)  # the search grid's cutoff past their span
                else ""
            )
            raise StructureError(
                f"its bonds cannot be guessed: {why}the guesser said: {exc}"
            ) from None
        if len(pairs):
            guessed = np.asarray(sorted(pairs), dtype=np.int32).reshape(-1, 2)
            both = np.sort(np.concatenate([bonds, guessed]), axis=1)
            bonds = np.unique(both, axis=0).astype(np.int32)
    if _has(atoms, "chainIDs"):
        chains = _strings(atoms, "chainIDs", "A", 4)
    else:
        chains = _strings(atoms, "segids", "A", 4)
    names = (
        _strings(atoms, "names", "X", 8)
        if _has(atoms, "names")
        else [f"{e}{i + 1}"[:8] for i, e in enumerate(elements)]
    )
    resids = atoms.resids if _has(atoms, "resids") else np.ones(n, dtype=np.int32)
    charges = atoms.charges if _has(atoms, "charges") else None
    bfac = atoms.tempfactors if _has(atoms, "tempfactors") else None
    return Topology(
        n_atoms=n,
        elements=elements,
        names=names,
        residue_ids=WireArray.from_numpy(resids, "<i4"),
        residue_names=_strings(atoms, "resnames", "UNK", 8),
        chain_ids=chains,
        bonds=WireArray.from_numpy(bonds, "<i4"),
        charges=WireArray.from_numpy(charges, "<f4") if charges is not None else None,
        bfactors=WireArray.from_numpy(bfac, "<f4") if bfac is not None else None,
        title=title[:256],
    )


# standard atomic masses (g/mol), to name elements of files that only give masses
_MASSES = {
    "H": 1.008,
    "He": 4.0026,
    "Li": 6.94,
    "C": 12.011,
    "N": 14.007,
    "O": 15.999,
    "F": 18.998,
    "Ne": 20.180,
    "Na": 22.990,
    "Mg": 24.305,
    "Al": 26.982,
    "Si": 28.085,
    "P": 30.974,
    "S": 32.06,
    "Cl": 35.45,
    "Ar": 39.948,
    "K": 39.098,
    "Ca": 40.078,
    "Fe": 55.845,
    "Cu": 63.546,
    "Zn": 65.38,
    "Br": 79.904,
    "Kr": 83.798,
    "Ag": 107.87,
    "I": 126.90,
    "Xe": 131.29,
    "Au": 196.97,
}

# van der Waals radii (angstrom) used only to guess bonds from distances.
_VDW_GUESS = {
    "H": 1.1,
    "C": 1.7,
    "N": 1.55,
    "O": 1.52,
    "S": 1.8,
    "P": 1.8,
    "F": 1.47,
    "Cl": 1.75,
    "Na": 2.27,
    "Mg": 1.73,
    "K": 2.75,
    "Ca": 2.31,
    "Fe": 1.94,
    "Zn": 1.39,
    "Se": 1.9,
    "Br": 1.85,
    "I": 1.98,
}
