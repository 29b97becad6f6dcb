"""Reconstruction of a signal from samples onto a finer lattice (section 4.2).

Both reconstructions use the normalised Gaussian kernel: the weights at each lattice point are
divided by their sum, so a constant signal is reconstructed exactly and the kernel is
renormalised near the ends of the sampled interval.
"""

from __future__ import annotations

from ._types import ArrayLike, FloatArray
from .convolution import convolve, warped_convolve
from .warps import Warp

__all__ = ["classical_reconstruction", "warped_reconstruction"]


def classical_reconstruction(t: ArrayLike, f: ArrayLike, x: ArrayLike, sigma: float) -> FloatArray:
    """``f_rec(x) = sum_k f(t_k) h(x - t_k)`` with a normalised Gaussian ``h`` (eq. 4.2)."""
    return convolve(t, f, sigma, x)


def warped_reconstruction(
    t: ArrayLike, f: ArrayLike, x: ArrayLike, sigma: float, warp: Warp | None = None
) -> FloatArray:
    """``f_rec(x) = sum_n f(t_n) h(gamma(x) - gamma(t_n))`` with a normalised Gaussian (eq. 4.8).

    ``warp`` defaults to the arclength warp of the samples; its ``gamma`` is linearly
    interpolated onto ``x`` (section 4.2.1), which is exact for the arclength of the linear
    interpolant.
    """
    return warped_convolve(t, f, sigma, warp, x)
