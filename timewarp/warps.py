"""Warping functions: the pair gamma (original time -> warped time) and alpha = gamma^-1.

The thesis writes a warped signal as ``g(t) = f(alpha(t))`` and recovers ``f(t) = g(gamma(t))``.
Every operation in this package only needs ``gamma`` (and ``gamma'`` for the exact scale space),
so any strictly increasing map can be plugged in by subclassing :class:`Warp`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np

from ._types import ArrayLike, FloatArray, as_float_array, as_samples

__all__ = [
    "AffineWarp",
    "CallableWarp",
    "IdentityWarp",
    "PiecewiseLinearWarp",
    "ScaledWarp",
    "Warp",
    "arclength",
    "arclength_warp",
    "length_normalising_constant",
    "normalise_bandwidth",
]


class Warp(ABC):
    """A strictly increasing, continuous warp; subclasses give ``gamma`` and ``alpha``."""

    @abstractmethod
    def gamma(self, t: ArrayLike) -> FloatArray:
        """Inverse warp: original time ``t`` -> warped time ``u`` (eq. 3.4 for arclength)."""

    @abstractmethod
    def alpha(self, u: ArrayLike) -> FloatArray:
        """Forward warp: warped time ``u`` -> original time, the inverse of :meth:`gamma`."""

    def dgamma(self, t: ArrayLike) -> FloatArray:
        """``gamma'(t)``, the local stretch; a central difference unless a subclass knows better."""
        tt = as_float_array(t, "t")
        h = 1e-6 * np.maximum(1.0, np.abs(tt))
        return (self.gamma(tt + h) - self.gamma(tt - h)) / (2.0 * h)


class IdentityWarp(Warp):
    """``gamma(t) = t``: every warped operation reduces to its classical counterpart."""

    def gamma(self, t: ArrayLike) -> FloatArray:
        return np.array(as_float_array(t, "t"), copy=True)

    def alpha(self, u: ArrayLike) -> FloatArray:
        return np.array(as_float_array(u, "u"), copy=True)

    def dgamma(self, t: ArrayLike) -> FloatArray:
        return np.ones_like(as_float_array(t, "t"))


class AffineWarp(Warp):
    """``gamma(t) = scale * t + offset``: a uniform stretch (the trivial warp of section 4.1.2)."""

    def __init__(self, scale: float, offset: float = 0.0) -> None:
        if not scale > 0.0 or not np.isfinite(scale):
            raise ValueError("scale must be positive and finite")
        self.scale = float(scale)
        self.offset = float(offset)

    def gamma(self, t: ArrayLike) -> FloatArray:
        return self.scale * as_float_array(t, "t") + self.offset

    def alpha(self, u: ArrayLike) -> FloatArray:
        return (as_float_array(u, "u") - self.offset) / self.scale

    def dgamma(self, t: ArrayLike) -> FloatArray:
        return np.full_like(as_float_array(t, "t"), self.scale)


class PiecewiseLinearWarp(Warp):
    """A warp given by knots ``gamma(knots_t[k]) = knots_u[k]``, linear in between (section 4.2.1).

    Outside the knots it continues with slope ``end_slope`` (1 by default: the arclength of a
    constant extension of the signal), so ``gamma`` stays invertible on the whole line and
    ``alpha`` is the exact piecewise-linear inverse through the swapped knots.
    """

    def __init__(self, knots_t: ArrayLike, knots_u: ArrayLike, end_slope: float = 1.0) -> None:
        kt, ku = as_samples(knots_t, knots_u)
        if ku.ndim != 1 or not np.all(np.diff(ku) > 0):
            raise ValueError("knots_u must be 1-D and strictly increasing")
        if not end_slope > 0.0:
            raise ValueError("end_slope must be positive")
        self.knots_t = kt
        self.knots_u = ku
        self.end_slope = float(end_slope)
        self._slopes = np.diff(ku) / np.diff(kt)

    @staticmethod
    def _interp(x: FloatArray, xp: FloatArray, fp: FloatArray, slope: float) -> FloatArray:
        y = np.interp(x, xp, fp)
        lo = x < xp[0]
        hi = x > xp[-1]
        y[lo] = fp[0] + slope * (x[lo] - xp[0])
        y[hi] = fp[-1] + slope * (x[hi] - xp[-1])
        return y

    def gamma(self, t: ArrayLike) -> FloatArray:
        tt = np.atleast_1d(as_float_array(t, "t"))
        out = self._interp(tt.ravel(), self.knots_t, self.knots_u, self.end_slope)
        return out.reshape(np.shape(t))

    def alpha(self, u: ArrayLike) -> FloatArray:
        uu = np.atleast_1d(as_float_array(u, "u"))
        out = self._interp(uu.ravel(), self.knots_u, self.knots_t, 1.0 / self.end_slope)
        return out.reshape(np.shape(u))

    def dgamma(self, t: ArrayLike) -> FloatArray:
        """Slope of the segment holding ``t`` (right-continuous at knots)."""
        tt = as_float_array(t, "t")
        idx = np.searchsorted(self.knots_t, tt, side="right") - 1
        inside = (idx >= 0) & (idx < self._slopes.size)
        out = np.full(tt.shape, self.end_slope)
        out[inside] = self._slopes[idx[inside]]
        return out


class CallableWarp(Warp):
    """Wrap any strictly increasing function ``gamma``; ``alpha`` is found by bisection.

    Bisection on a bracket that is widened until it holds every target value gives the inverse
    to a few ulps without needing ``gamma'``; pass ``alpha`` when a closed form is known.
    """

    def __init__(
        self,
        gamma: Callable[[FloatArray], FloatArray],
        dgamma: Callable[[FloatArray], FloatArray] | None = None,
        alpha: Callable[[FloatArray], FloatArray] | None = None,
    ) -> None:
        self._gamma = gamma
        self._dgamma = dgamma
        self._alpha = alpha

    def gamma(self, t: ArrayLike) -> FloatArray:
        return np.asarray(self._gamma(as_float_array(t, "t")), dtype=np.float64)

    def dgamma(self, t: ArrayLike) -> FloatArray:
        if self._dgamma is not None:
            return np.asarray(self._dgamma(as_float_array(t, "t")), dtype=np.float64)
        return super().dgamma(t)

    def alpha(self, u: ArrayLike) -> FloatArray:
        uu = as_float_array(u, "u")
        if self._alpha is not None:
            return np.asarray(self._alpha(uu), dtype=np.float64)
        flat = uu.ravel()
        lo = np.full(flat.shape, -1.0)
        hi = np.full(flat.shape, 1.0)
        for _ in range(1100):
            below = self.gamma(lo) > flat
            above = self.gamma(hi) < flat
            if not (below.any() or above.any()):
                break
            lo[below] *= 2.0
            hi[above] *= 2.0
        else:
            raise ValueError("could not bracket the inverse warp; is gamma unbounded?")
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if np.all((mid == lo) | (mid == hi)):
                break
            right = self.gamma(mid) < flat
            lo = np.where(right, mid, lo)
            hi = np.where(right, hi, mid)
        return np.asarray((0.5 * (lo + hi)).reshape(uu.shape), dtype=np.float64)


class ScaledWarp(Warp):
    """``gamma_d = gamma / c``, i.e. ``alpha_d(u) = alpha(c * u)``: lemma 2's bandwidth scaling.

    The thesis writes ``alpha_d = c * alpha``; the Fourier scaling theorem its proof appeals to
    scales the *warped* time axis, which is what this class does. For a linear ``alpha`` the
    two readings are identical.
    """

    def __init__(self, base: Warp, c: float) -> None:
        if not c > 0.0 or not np.isfinite(c):
            raise ValueError("c must be positive and finite")
        self.base = base
        self.c = float(c)

    def gamma(self, t: ArrayLike) -> FloatArray:
        return self.base.gamma(t) / self.c

    def alpha(self, u: ArrayLike) -> FloatArray:
        return self.base.alpha(self.c * as_float_array(u, "u"))

    def dgamma(self, t: ArrayLike) -> FloatArray:
        return self.base.dgamma(t) / self.c


def arclength(t: ArrayLike, f: ArrayLike, gain: float = 1.0) -> FloatArray:
    """Arclength of the linear interpolant at the samples, ``gamma(t_0) = t_0`` (eq. 3.4).

    Each segment contributes ``sqrt(dt^2 + gain^2 |df|^2)``; ``gain`` states the units of
    ``f`` relative to ``t`` (arclength is not invariant to them). ``f`` may be vector valued
    (shape ``(n, c)``), giving the arclength of the curve ``(t, f(t))``. The result is
    strictly increasing because every increment is at least ``dt > 0``.
    """
    tt, ff = as_samples(t, f)
    if not (np.isfinite(gain) and gain >= 0.0):
        raise ValueError("gain must be finite and non-negative")
    df = gain * np.diff(ff, axis=0).reshape(tt.size - 1, -1)
    inc = np.sqrt(np.diff(tt) ** 2 + np.sum(df * df, axis=1))
    out = np.empty_like(tt)
    out[0] = tt[0]
    out[1:] = tt[0] + np.cumsum(inc)
    return out


def arclength_warp(t: ArrayLike, f: ArrayLike, gain: float = 1.0) -> PiecewiseLinearWarp:
    """The arclength warp of the linear interpolant of ``(t, f)`` as a :class:`PiecewiseLinearWarp`.

    The arclength of a piecewise-linear signal is itself piecewise linear in ``t``, so linear
    interpolation of ``gamma`` onto a finer lattice (section 4.2.1) is exact here.
    """
    tt, _ = as_samples(t, f)
    return PiecewiseLinearWarp(tt, arclength(t, f, gain))


def length_normalising_constant(warp: Warp, t0: float, t1: float) -> float:
    """``c`` such that ``gamma / c`` maps ``[t0, t1]`` onto an interval of the same length.

    Used as the lemma 2 normalisation: the warped signal then has as many samples per unit
    length as the original, so its bandwidth is comparable with the original bandlimit.
    """
    g = warp.gamma(np.array([t0, t1], dtype=np.float64))
    return float((g[1] - g[0]) / (t1 - t0))


def normalise_bandwidth(warp: Warp, c: float) -> ScaledWarp:
    """Lemma 2: the bandwidth-normalised warp ``gamma_d = gamma / c`` (see :class:`ScaledWarp`)."""
    return ScaledWarp(warp, c)
