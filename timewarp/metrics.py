"""Error metrics of chapter 4: total absolute error, Marschner-Lobb smoothing and postaliasing
(eqs. 4.3-4.4), their signal-weighted versions (4.5-4.6), energy bandwidths, and the warp
transfer functions ``P_gamma(w, k)`` (eq. 4.12) computed by quadrature.

Frequencies are in cycles per unit of the signal's abscissa (the thesis's ``e^{i 2 pi w t}``
convention), so a Gaussian of standard deviation ``sigma`` has the response
``exp(-2 pi^2 sigma^2 w^2)``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ._types import ArrayLike, FloatArray, as_float_array
from .warps import Warp

__all__ = [
    "energy_bandwidth",
    "energy_fraction_below",
    "gaussian_frequency_response",
    "postaliasing_metric",
    "signal_spectrum",
    "signal_weighted_postaliasing",
    "signal_weighted_smoothing",
    "smoothing_metric",
    "total_absolute_error",
    "warp_transfer_function",
]

Response = Callable[[FloatArray], FloatArray]
ComplexArray = npt.NDArray[np.complex128]


def total_absolute_error(estimate: ArrayLike, truth: ArrayLike) -> float:
    """``sum_i |estimate_i - truth_i|`` over the lattice: the thesis's tables 4.1-4.5 measure.

    It is a plain sum over lattice points (not multiplied by the spacing), as the thesis
    describes it ("the sum of absolute value of the differences").
    """
    a = as_float_array(estimate, "estimate")
    b = as_float_array(truth, "truth")
    if a.shape != b.shape:
        raise ValueError(f"shape mismatch {a.shape} vs {b.shape}")
    return float(np.sum(np.abs(a - b)))


def gaussian_frequency_response(w: ArrayLike, sigma: float) -> FloatArray:
    """Fourier transform of the normalised Gaussian: ``exp(-2 pi^2 sigma^2 w^2)``."""
    ww = as_float_array(w, "w")
    return np.exp(-2.0 * np.pi**2 * sigma**2 * ww**2)


def _simpson(y: FloatArray, x: FloatArray) -> float:
    """Composite Simpson rule on an odd number of equally spaced points."""
    if y.size % 2 == 0 or y.size < 3:
        raise ValueError("Simpson's rule needs an odd number (>= 3) of points")
    h = (x[-1] - x[0]) / (y.size - 1)
    return float(h / 3 * (y[0] + y[-1] + 4 * y[1:-1:2].sum() + 2 * y[2:-1:2].sum()))


def smoothing_metric(response: Response, bandlimit: float, n: int = 4001) -> float:
    """Marschner-Lobb smoothing ``s(h) = (1/Omega) int_{-Omega}^{Omega} (1 - |H(w)|) dw`` (4.3).

    Integrated with Simpson's rule on ``n`` (odd) points.
    """
    if not bandlimit > 0:
        raise ValueError("bandlimit must be positive")
    w = np.linspace(-bandlimit, bandlimit, n)
    return _simpson(1.0 - np.abs(response(w)), w) / bandlimit


def postaliasing_metric(response: Response, bandlimit: float, w_max: float, n: int = 8001) -> float:
    """Postaliasing: ``(1/Omega) int_{Omega < |w| < w_max} |H(w)| dw``, the area outside the band.

    Eq. 4.4 as printed integrates over ``[-Omega, Omega]``; its text (and Marschner & Lobb)
    define postaliasing as the area of ``|H|`` outside the band, which is what is computed.
    """
    if not w_max > bandlimit > 0:
        raise ValueError("need 0 < bandlimit < w_max")
    w = np.linspace(bandlimit, w_max, n)
    return 2.0 * _simpson(np.abs(response(w)), w) / bandlimit


def signal_spectrum(f: ArrayLike, dt: float = 1.0) -> tuple[FloatArray, ComplexArray]:
    """Frequencies and ``F(w) ~ dt * DFT(f)``, the Riemann-sum Fourier transform of the samples."""
    ff = as_float_array(f, "f")
    freqs = np.fft.fftfreq(ff.size, d=dt)
    return np.asarray(freqs, dtype=np.float64), dt * np.fft.fft(ff)


def signal_weighted_smoothing(
    f: ArrayLike, dt: float, response: Response, bandlimit: float
) -> float:
    """``s(h, f) = (1/Omega) int_{-Omega}^{Omega} |F(w)| (1 - |H(w)|) dw`` (eq. 4.5).

    The integral is the sum over DFT bins inside the band times the bin width ``1/(n dt)``.
    """
    freqs, spec = signal_spectrum(f, dt)
    band = np.abs(freqs) <= bandlimit
    dw = 1.0 / (freqs.size * dt)
    weight = np.abs(spec[band]) * (1.0 - np.abs(response(freqs[band])))
    return float(np.sum(weight) * dw / bandlimit)


def signal_weighted_postaliasing(total_error: float, smoothing: float) -> float:
    """``p(h, f) = B - s(h, f)`` with ``B = int |f - f_rec|`` (eqs. 4.6-4.7)."""
    return float(total_error - smoothing)


def energy_fraction_below(
    f: ArrayLike, dt: float, frequency: float, *, remove_mean: bool = False
) -> float:
    """Fraction of the signal energy ``sum |F|^2`` at ``|w| <= frequency``."""
    ff = as_float_array(f, "f")
    if remove_mean:
        ff = ff - ff.mean()
    freqs, spec = signal_spectrum(ff, dt)
    power = np.abs(spec) ** 2
    total = float(power.sum())
    if total == 0.0:
        return 1.0
    return float(power[np.abs(freqs) <= frequency].sum() / total)


def energy_bandwidth(
    f: ArrayLike, dt: float, fraction: float = 0.998, *, remove_mean: bool = False
) -> float:
    """Smallest frequency below which ``fraction`` of the energy lies (a practical bandlimit)."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError("fraction must lie in (0, 1]")
    ff = as_float_array(f, "f")
    if remove_mean:
        ff = ff - ff.mean()
    freqs, spec = signal_spectrum(ff, dt)
    power = np.abs(spec) ** 2
    order = np.argsort(np.abs(freqs), kind="stable")
    cum = np.cumsum(power[order])
    if cum[-1] == 0.0:
        return 0.0
    idx = int(np.searchsorted(cum, fraction * cum[-1] * (1 - 1e-12)))
    return float(np.abs(freqs[order][min(idx, freqs.size - 1)]))


def warp_transfer_function(
    warp: Warp,
    w: ArrayLike,
    k: ArrayLike,
    t0: float,
    t1: float,
    n: int | None = None,
) -> ComplexArray:
    """``P_gamma(w, k) = int_{t0}^{t1} exp(i 2 pi k gamma(t)) exp(-i 2 pi w t) dt`` (eq. 4.12).

    The thesis's integral runs over the whole line, where ``P`` is a distribution; over a
    finite window it is an ordinary integral, computed with Simpson's rule on ``n`` points
    (by default enough for at most 0.05 rad of phase change per step). Returns an
    array of shape ``(len(w), len(k))``.
    """
    ww = np.atleast_1d(as_float_array(w, "w"))
    kk = np.atleast_1d(as_float_array(k, "k"))
    if not t1 > t0:
        raise ValueError("need t1 > t0")
    if n is None:
        probe = np.linspace(t0, t1, 2049)
        rate = 2 * np.pi * (np.max(np.abs(kk)) * np.max(np.abs(warp.dgamma(probe))))
        rate += 2 * np.pi * np.max(np.abs(ww))
        n = int(min(max(np.ceil((t1 - t0) * rate / 0.05) + 1, 257), 4_000_001))
    n += 1 - n % 2  # Simpson's rule needs an odd number of points
    t = np.linspace(t0, t1, n)
    q = np.full(n, 2.0)
    q[1::2] = 4.0
    q[0] = q[-1] = 1.0
    q *= (t1 - t0) / (n - 1) / 3.0
    g = warp.gamma(t)
    basis = np.exp(-2j * np.pi * np.outer(ww, t)) * q[None, :]
    out = np.empty((ww.size, kk.size), dtype=np.complex128)
    for j, kj in enumerate(kk):
        out[:, j] = basis @ np.exp(2j * np.pi * kj * g)
    return out
