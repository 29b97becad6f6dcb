"""Periodic boxes in plain numpy: which box is a simulation cell, what to do with a frame
(`Options`, the render parameters' periodic fields with their selections evaluated), and a
frame as displayed (`Shown`). The device kernels are `server.render.periodic`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

Mode = Literal["off", "whole", "wrap", "molecules", "unwrap"]
FitMode = Literal["off", "translation", "rotation"]
MIN_CELL_A = 6.0
"""A box narrower than this (between opposite faces) is no simulation cell (a PDB's
placeholder CRYST1 of 1 A): its frames are shown as sent."""


def usable_box(box: npt.ArrayLike | None) -> npt.NDArray[np.float64] | None:
    """The box (rows are its vectors, angstrom) if it is a simulation cell: finite, of positive
    volume and at least MIN_CELL_A between opposite faces; else None."""
    if box is None:
        return None
    b = np.asarray(box, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(b).all():
        return None
    volume = abs(float(np.linalg.det(b)))
    if volume <= 0.0:
        return None
    for k in range(3):
        face = np.cross(b[(k + 1) % 3], b[(k + 2) % 3])
        if volume / float(np.linalg.norm(face)) < MIN_CELL_A:
            return None
    return b


@dataclass(frozen=True)
class Options:
    """What to do with a frame (the render parameters' periodic fields, selections evaluated:
    sorted atom indices, None for none)."""

    mode: Mode = "off"
    centre: npt.NDArray[np.int32] | None = None
    fit: FitMode = "off"
    fit_atoms: npt.NDArray[np.int32] | None = None

    def key(self) -> tuple[Any, ...]:
        """Changes when the fit's reference must be taken again."""
        fit = None if self.fit_atoms is None else self.fit_atoms.tobytes()
        centre = None if self.centre is None else self.centre.tobytes()
        return (self.mode, centre, self.fit, fit)


@dataclass(frozen=True)
class Shown:
    """A frame as displayed: positions (host, float32), and the rigid motion applied after the
    box vectors (display = R (y - c) + c_ref, y the whole, centred, wrapped positions), and the
    box as displayed (its origin and vectors; None without a box)."""

    positions: npt.NDArray[np.float32]
    rotation: npt.NDArray[np.float64]
    centre: npt.NDArray[np.float64]
    reference_centre: npt.NDArray[np.float64]
    cell: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None

    def to_display(self, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Points of the centred, wrapped frame (box vectors applied) in display space."""
        return (np.asarray(points) - self.centre) @ self.rotation.T + self.reference_centre
