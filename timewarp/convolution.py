"""Classical and time-warped Gaussian convolution of sampled signals (eqs. 3.1, 3.3, 4.2, 4.8).

The thesis discretises warped convolution "in an almost identical fashion" to the classical one:
the kernel is evaluated at warped distances ``gamma(x) - gamma(t_j)`` instead of ``x - t_j``.
With ``normalise=True`` (the default, the thesis's "normalized Gaussian kernel") the weights at
each output point are divided by their sum, which also handles the signal ends: the kernel is
renormalised over the samples that exist, no padding is invented.
"""

from __future__ import annotations

import numpy as np

from ._types import ArrayLike, FloatArray, as_float_array, as_samples
from .warps import Warp, arclength_warp

__all__ = [
    "convolve",
    "gaussian",
    "gaussian_filter",
    "sample_weights",
    "warped_convolve",
]

_CHUNK = 4096


def gaussian(x: ArrayLike, sigma: float) -> FloatArray:
    """The normalised Gaussian kernel ``exp(-x^2 / 2 sigma^2) / (sqrt(2 pi) sigma)``."""
    _check_sigma(sigma)
    xx = as_float_array(x, "x")
    return np.asarray(np.exp(-0.5 * (xx / sigma) ** 2) / (np.sqrt(2.0 * np.pi) * sigma))


def sample_weights(t: ArrayLike) -> FloatArray:
    """Quadrature weight of each sample: the width of its cell (half-way to each neighbour).

    End cells are mirrored so a uniform lattice gets equal weights; then a normalised sum
    over samples is exactly the plain average the thesis uses.
    """
    tt = as_float_array(t, "t")
    if tt.size < 2:
        return np.ones_like(tt)
    ext = np.concatenate([[2 * tt[0] - tt[1]], tt, [2 * tt[-1] - tt[-2]]])
    return np.asarray(0.5 * (ext[2:] - ext[:-2]), dtype=np.float64)


def _check_sigma(sigma: float) -> None:
    if not (np.isfinite(sigma) and sigma > 0.0):
        raise ValueError("sigma must be positive and finite")


def _kernel_sum(
    ux: FloatArray,
    uj: FloatArray,
    fj: FloatArray,
    wj: FloatArray,
    sigma: float,
    normalise: bool,
    truncate: float | None,
) -> FloatArray:
    """``sum_j w_j f_j G(ux - u_j)``, optionally divided by ``sum_j w_j G``; chunked over ``ux``."""
    flat = fj.reshape(fj.shape[0], -1)
    out = np.empty((ux.size, flat.shape[1]), dtype=np.float64)
    for start in range(0, ux.size, _CHUNK):
        d = (ux[start : start + _CHUNK, None] - uj[None, :]) / sigma
        e = 0.5 * d * d
        if normalise:
            # shift by the row minimum so the nearest sample always has weight 1 (no 0/0)
            e -= e.min(axis=1, keepdims=True)
        k = np.exp(-e) * wj[None, :]
        if truncate is not None:
            k[np.abs(d) > truncate] = 0.0
        if normalise:
            with np.errstate(invalid="ignore", divide="ignore"):
                out[start : start + _CHUNK] = (k @ flat) / k.sum(axis=1, keepdims=True)
        else:
            out[start : start + _CHUNK] = (k @ flat) / (np.sqrt(2.0 * np.pi) * sigma)
    return out.reshape((ux.size, *fj.shape[1:]))


def convolve(
    t: ArrayLike,
    f: ArrayLike,
    sigma: float,
    x: ArrayLike | None = None,
    *,
    normalise: bool = True,
    truncate: float | None = None,
) -> FloatArray:
    """Classical Gaussian convolution of samples ``(t, f)`` evaluated at ``x`` (eq. 4.2).

    ``normalise=False`` gives the Riemann sum ``sum_j f_j G(x - t_j) w_j`` of eq. 3.1 with the
    cell widths ``w_j`` of :func:`sample_weights`. ``truncate`` drops samples farther than
    ``truncate * sigma``.
    """
    tt, ff = as_samples(t, f)
    _check_sigma(sigma)
    xx = tt if x is None else np.atleast_1d(as_float_array(x, "x"))
    w = sample_weights(tt)
    return _kernel_sum(xx.ravel(), tt, ff, w, sigma, normalise, truncate)


def warped_convolve(
    t: ArrayLike,
    f: ArrayLike,
    sigma: float,
    warp: Warp | None = None,
    x: ArrayLike | None = None,
    *,
    normalise: bool = True,
    jacobian: bool = False,
    truncate: float | None = None,
) -> FloatArray:
    """Time-warped Gaussian convolution ``sum_j f_j G(gamma(x) - gamma(t_j))`` (eqs. 3.3, 4.8).

    ``warp`` defaults to the arclength warp of ``(t, f)``. As printed, eq. 3.3 integrates over
    ``dt'`` (no Jacobian), so each sample keeps its original cell width; ``jacobian=True`` uses
    the warped cell widths instead, i.e. the quadrature of ``(f(alpha) * G)(gamma(x))``.
    With ``truncate``, an ``x`` with no sample within ``truncate * sigma`` evaluates to NaN.
    """
    tt, ff = as_samples(t, f)
    _check_sigma(sigma)
    wrp = arclength_warp(tt, ff) if warp is None else warp
    xx = tt if x is None else np.atleast_1d(as_float_array(x, "x"))
    ut = wrp.gamma(tt)
    ux = wrp.gamma(xx.ravel())
    w = sample_weights(ut) if jacobian else sample_weights(tt)
    return _kernel_sum(ux, ut, ff, w, sigma, normalise, truncate)


def gaussian_filter(f: ArrayLike, sigma: float) -> FloatArray:
    """Classical normalised Gaussian filter of a uniformly sampled 1-D signal (unit spacing).

    Implemented as a discrete ``np.convolve`` with the kernel sampled at integer offsets,
    divided by the same convolution of ones so the kernel is renormalised at the ends. It is
    deliberately independent of :func:`convolve`, which it must agree with.
    """
    ff = as_float_array(f, "f")
    if ff.ndim != 1:
        raise ValueError("gaussian_filter expects a 1-D signal")
    _check_sigma(sigma)
    n = ff.size
    offsets = np.arange(-(n - 1), n, dtype=np.float64)
    k = np.exp(-0.5 * (offsets / sigma) ** 2)
    num = np.convolve(ff, k, mode="full")[n - 1 : 2 * n - 1]
    den = np.convolve(np.ones(n), k, mode="full")[n - 1 : 2 * n - 1]
    return np.asarray(num / den, dtype=np.float64)
