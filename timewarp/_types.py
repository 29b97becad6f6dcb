"""Shared array aliases and small validation helpers for the timewarp package."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
ArrayLike = npt.ArrayLike


def as_float_array(x: ArrayLike, name: str = "array") -> FloatArray:
    """Return ``x`` as a float64 array, rejecting NaN and infinity early."""
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values")
    return arr


def as_samples(t: ArrayLike, f: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Validate a sampled signal: strictly increasing 1-D ``t`` and ``f`` with ``len(f) == len(t)``.

    ``f`` may carry trailing component axes (shape ``(n, c)``) for vector-valued signals.
    """
    tt = as_float_array(t, "t")
    ff = as_float_array(f, "f")
    if tt.ndim != 1 or tt.size < 2:
        raise ValueError("t must be a 1-D array with at least two samples")
    if ff.shape[0] != tt.size:
        raise ValueError(f"f has {ff.shape[0]} samples but t has {tt.size}")
    if not np.all(np.diff(tt) > 0):
        raise ValueError("t must be strictly increasing")
    return tt, ff


def uniform_lattice(n: int, dt: float = 1.0, start: float = 0.0) -> FloatArray:
    """Sample positions ``start + k*dt`` for ``k = 0..n-1`` (the default abscissa: sample units)."""
    return start + dt * np.arange(n, dtype=np.float64)
