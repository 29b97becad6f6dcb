"""What a `forces` message means once it reaches an engine: per-atom vectors, each capped.

Every party that handles external forces (the session merging pulls with script forces, the
OpenMM plug-in, the IMD bridge) caps them here, so "at most `max_force` kJ/mol/A on any atom"
means the same everywhere and a huge vector is scaled down, never to zero or NaN.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def vector_norms(vectors: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Euclidean norm of each row of an (n, 3) array, without overflow for huge components
    (each row is scaled by its largest magnitude before squaring)."""
    v = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
    big = np.max(np.abs(v), axis=1)
    safe = np.where(big > 0, big, 1.0)
    norms: npt.NDArray[np.float64] = big * np.sqrt(np.sum((v / safe[:, None]) ** 2, axis=1))
    return norms


def cap_forces(vectors: npt.ArrayLike, max_force: float) -> tuple[npt.NDArray[np.float64], int]:
    """A float64 copy of `vectors` (n, 3) with every row longer than `max_force` scaled to that
    length, and how many rows were capped. Raises ValueError for NaN or infinite components."""
    if not max_force > 0:
        raise ValueError(f"max_force must be positive, got {max_force}")
    v = np.array(vectors, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(v).all():
        raise ValueError("forces must be finite")
    norms = vector_norms(v)
    over = norms > max_force
    if over.any():
        v[over] *= (max_force / norms[over])[:, None]
    return v, int(over.sum())
