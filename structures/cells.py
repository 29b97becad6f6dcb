"""The cells of structure files: a universe's box as its reader gives it (a placeholder is
none), and the deposited entries whose cell is a crystal's unit cell, no periodic box."""

from __future__ import annotations

import gzip
from typing import Any

import numpy as np
import numpy.typing as npt

CRYSTAL_FORMATS = ("pdb", "ent", "cif", "mmcif", "pdbx", "bcif")
"""Formats of deposited models. One such file read alone, with one model, that says how its
model was determined (PDB's EXPDTA, mmCIF's `_exptl.method`: every deposited entry does, a
simulation's snapshot does not) is a crystal's asymmetric unit, and its cell (CRYST1, `_cell`)
is the crystal's unit cell, not a simulation's box. Wrapping each chain into it would take a
deposited complex apart (1BD2, 3KPR), and bonds guessed across it would join atoms of
neighbouring unit cells, so it is no periodic box."""
DEPOSITED_MARKS = ("EXPDTA", "_exptl.method")
HEADER_LINES = 50_000
"""Lines of a PDB or mmCIF file searched for `DEPOSITED_MARKS` before its atoms."""


def deposited(path: str) -> bool:
    """Whether a PDB or mmCIF file (gzipped too) says how its model was determined, before
    its atoms: a deposited entry, not a simulation's snapshot."""
    opener: Any = gzip.open if path.lower().endswith(".gz") else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace") as fh:
            for count, line in enumerate(fh):
                if line.startswith(DEPOSITED_MARKS):
                    return True
                if count > HEADER_LINES or line.startswith(("ATOM", "HETATM", "_atom_site.")):
                    return False
    except OSError:
        return False
    return False


MIN_CELL_SIDE_A = 6.0
"""A box with a side shorter than this is a placeholder (a PDB's CRYST1 of 1 A), no cell."""


def cell_of(u: Any) -> npt.NDArray[np.float32] | None:
    """The universe's current box as MDAnalysis' dimensions (a, b, c, alpha, beta, gamma), or
    None when it has none or a placeholder."""
    try:
        dims = u.dimensions
    except Exception:  # a reader without a box
        return None
    if dims is None:
        return None
    dims = np.asarray(dims, dtype=np.float32)
    if dims.shape != (6,) or not np.isfinite(dims).all() or (dims[:3] < MIN_CELL_SIDE_A).any():
        return None
    if (dims[3:] <= 0).any() or (dims[3:] >= 180).any():
        return None
    return dims
