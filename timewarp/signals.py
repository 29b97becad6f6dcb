"""Test signals: the 1-D Marschner-Lobb function (eq. 4.27), a synthetic step-edge signal and a
scanline of a real photograph shipped inside scikit-image (no download needed).
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from ._types import ArrayLike, FloatArray, as_float_array

__all__ = ["camera_scanline", "marschner_lobb", "step_edge_signal"]


def marschner_lobb(x: ArrayLike) -> FloatArray:
    """``f(x) = 1 + cos(12 pi cos(pi x / 2))`` on ``[-1, 1]`` (eq. 4.27)."""
    xx = as_float_array(x, "x")
    return 1.0 + np.cos(12.0 * np.pi * np.cos(np.pi * xx / 2.0))


def step_edge_signal(n: int = 256, amplitude: float = 8.0) -> FloatArray:
    """A deterministic signal with sharp edges, a narrow pulse and smooth parts (figs. 3.1, 3.3).

    Values are in units of the sample spacing, which matters: the arclength warp is not
    invariant to the scale of ``f`` (``gamma' = sqrt(1 + f'^2)``), and with ``amplitude = 8``
    the edges are steep enough (jumps of 3.6-6 per sample) to be stretched several-fold.
    """
    if n < 32:
        raise ValueError("n must be at least 32")
    u = np.arange(n, dtype=np.float64) / n
    levels = np.array([0.0, 0.75, 0.3, 1.0, 0.45])
    edges = np.array([0.18, 0.38, 0.56, 0.78])
    f = levels[np.searchsorted(edges, u, side="right")]
    f = f + 0.12 * np.sin(2 * np.pi * 3.0 * u)  # gentle oscillation on the plateaus
    pulse = (u >= 0.66) & (u < 0.66 + 4.0 / n)
    f = f - 0.5 * pulse  # a narrow dip, four samples wide
    return np.asarray(amplitude * f, dtype=np.float64)


def camera_scanline(row: int = 256) -> FloatArray:
    """Row ``row`` of scikit-image's ``camera`` photograph as floats in ``[0, 1]`` (fig. 4.1).

    The image ships inside the scikit-image wheel, so nothing is downloaded.
    """
    # optional dependency, only needed for the real-data experiments
    data: Any = importlib.import_module("skimage.data")
    img = np.asarray(data.camera(), dtype=np.float64) / 255.0
    if not 0 <= row < img.shape[0]:
        raise ValueError(f"row must lie in [0, {img.shape[0]})")
    return np.array(img[row], dtype=np.float64)
