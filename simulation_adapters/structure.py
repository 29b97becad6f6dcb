"""Reading structures and trajectories (MDAnalysis) into protocol topologies and frames.

Shared by trajectory replay, the REST API and the still renderer, so a file that one of them
accepts, all of them accept. MDAnalysis is imported lazily: `pip install scalesteer[replay]`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology, WireArray

STRUCTURE_FORMATS = (
    "pdb",
    "ent",
    "cif",
    "mmcif",
    "gro",
    "xyz",
    "psf",
    "data",
    "pqr",
    "mol2",
    "crd",
)
TRAJECTORY_FORMATS = ("dcd", "xtc", "trr", "pdb", "nc", "ncdf", "xyz", "lammpsdump")


class StructureError(ValueError):
    """A structure or trajectory that cannot be used, with a message naming the problem."""


@dataclass
class Structure:
    """A loaded universe: the topology message, and access to its frames."""

    topology: Topology
    universe: Any

    @property
    def n_frames(self) -> int:
        return len(self.universe.trajectory)

    def positions(self, index: int = 0) -> npt.NDArray[np.float32]:
        """Positions (angstrom) of frame `index`."""
        ts = self.universe.trajectory[index]
        return np.ascontiguousarray(ts.positions, dtype=np.float32)

    def frames(
        self, start: int = 0, stop: int | None = None, stride: int = 1
    ) -> Iterator[tuple[int, float, npt.NDArray[np.float32]]]:
        """(frame index, time in ps, positions) for a slice of the trajectory."""
        for ts in self.universe.trajectory[start:stop:stride]:
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


def load(
    topology: str,
    trajectories: Sequence[str] = (),
    *,
    guess_bonds: bool = True,
    max_atoms: int | None = None,
) -> Structure:
    """Open a structure (PDB, mmCIF, GRO, XYZ, PSF, ...) with optional trajectory files.

    Raises `StructureError` with a readable reason for missing, unreadable or inconsistent
    files (for instance a trajectory whose atom count differs from the topology's).
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
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            u = mda.Universe(topology, *trajectories) if trajectories else mda.Universe(topology)
    except Exception as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        names = ", ".join(os.path.basename(f) for f in (topology, *trajectories))
        raise StructureError(f"cannot read {names}: {msg[:300]}") from None
    n = int(u.atoms.n_atoms)
    if n == 0:
        raise StructureError(f"{os.path.basename(topology)} contains no atoms")
    if max_atoms is not None and n > max_atoms:
        raise StructureError(
            f"{os.path.basename(topology)} has {n} atoms, the limit is {max_atoms}"
        )
    return Structure(
        topology=topology_of(u, guess_bonds=guess_bonds, title=os.path.basename(topology)),
        universe=u,
    )


def _elements(u: Any) -> list[str]:
    atoms = u.atoms
    if hasattr(atoms, "elements"):
        raw = [str(e).strip().capitalize() for e in atoms.elements]
        if all(raw):
            return raw
    from MDAnalysis.guesser.default_guesser import DefaultGuesser

    guessed = DefaultGuesser(None).guess_types(atoms.names)
    return [str(e).strip().capitalize() or "X" for e in guessed]


def topology_of(u: Any, *, guess_bonds: bool = True, title: str = "") -> Topology:
    """Build the `topology` message of an MDAnalysis universe, guessing elements and bonds."""
    atoms = u.atoms
    n = int(atoms.n_atoms)
    elements = [e[:3] for e in _elements(u)]
    bonds = np.zeros((0, 2), dtype=np.int32)
    if hasattr(u, "bonds") and len(u.bonds):
        bonds = np.asarray(u.bonds.indices, dtype=np.int32).reshape(-1, 2)
    elif guess_bonds and n <= 500_000:
        from MDAnalysis.topology.guessers import guess_bonds as guess

        # the guesser looks radii up by atom type; map each type to its element's radius
        radii = {str(t): _VDW_GUESS.get(e, 1.5) for t, e in zip(atoms.types, elements, strict=True)}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pairs = guess(atoms, atoms.positions, box=None, vdwradii=radii)
        if len(pairs):
            bonds = np.asarray(sorted(pairs), dtype=np.int32).reshape(-1, 2)
    chain = getattr(atoms, "chainIDs", None)
    chains = (
        [str(c)[:4] for c in chain] if chain is not None else [str(s)[:4] for s in atoms.segids]
    )
    charges = WireArray.from_numpy(atoms.charges, "<f4") if hasattr(atoms, "charges") else None
    bfac = getattr(atoms, "tempfactors", None)
    return Topology(
        n_atoms=n,
        elements=elements,
        names=[str(x)[:8] for x in atoms.names],
        residue_ids=WireArray.from_numpy(atoms.resids, "<i4"),
        residue_names=[str(x)[:8] for x in atoms.resnames],
        chain_ids=chains,
        bonds=WireArray.from_numpy(bonds, "<i4"),
        charges=charges,
        bfactors=WireArray.from_numpy(bfac, "<f4") if bfac is not None else None,
        title=title[:256],
    )


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
