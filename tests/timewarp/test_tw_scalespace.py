"""Scale spaces: exact values against quadrature, and the scale-space axioms of section 3.2.3."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, optimize

from timewarp import (
    IdentityWarp,
    PiecewiseLinearWarp,
    Warp,
    arclength_warp,
    linear_scale_space,
    warped_scale_space,
)

from .strategies import increasing_knots, sampled_signals


def quad_scale_space(t: np.ndarray, f: np.ndarray, s: float, warp: Warp, x: float) -> float:
    """Definition 1 by adaptive quadrature: (g * G_s)(gamma(x)), g the warped interpolant."""
    u = warp.gamma(t)
    ux = float(warp.gamma(np.array([x]))[0])

    def integrand(v: float) -> float:
        g = np.interp(v, u, f)  # constant beyond the ends
        return float(g * np.exp(-0.5 * ((ux - v) / s) ** 2) / (np.sqrt(2 * np.pi) * s))

    lo, hi = ux - 12 * s, ux + 12 * s
    pts = [p for p in u if lo < p < hi]
    val, _ = integrate.quad(integrand, lo, hi, points=pts or None, limit=400, epsabs=1e-13)
    return float(val)


@pytest.mark.parametrize("s", [0.3, 1.0, 4.0])
def test_warped_scale_space_matches_quadrature(s: float) -> None:
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.3, 2.0, 14))
    f = rng.normal(size=14) * 3
    warp = arclength_warp(t, f)
    x = np.array([t[0] - 2.0, t[3] + 0.1, t[7], 0.5 * (t[10] + t[11]), t[-1] + 1.5])
    got = warped_scale_space(t, f, s, warp, x)
    ref = [quad_scale_space(t, f, s, warp, xi) for xi in x]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)


def test_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(11)
    t = np.arange(12.0)
    f = rng.normal(size=12) * 2
    warp = arclength_warp(t, f)
    x = np.array([-2.0, 2.3, 5.6, 9.1, 14.0])  # inside segments, where gamma' is constant
    h = 1e-5
    d1 = warped_scale_space(t, f, 1.5, warp, x, derivative=1)
    fd1 = (
        warped_scale_space(t, f, 1.5, warp, x + h) - warped_scale_space(t, f, 1.5, warp, x - h)
    ) / (2 * h)
    np.testing.assert_allclose(d1, fd1, rtol=1e-6, atol=1e-8)
    # derivative=2 is L'' of the warped-domain scale space: d/dx F' = L'' gamma'^2 in a segment
    d2 = warped_scale_space(t, f, 1.5, warp, x, derivative=2) * warp.dgamma(x) ** 2
    fd2 = (
        warped_scale_space(t, f, 1.5, warp, x + h, derivative=1)
        - warped_scale_space(t, f, 1.5, warp, x - h, derivative=1)
    ) / (2 * h)
    np.testing.assert_allclose(d2, fd2, rtol=1e-5, atol=1e-7)


@settings(deadline=None, max_examples=40)
@given(sampled_signals(), st.floats(0.05, 6.0))
def test_identity_warp_is_the_linear_scale_space(
    sig: tuple[np.ndarray, np.ndarray], s: float
) -> None:
    t, f = sig
    x = np.linspace(t[0] - 2, t[-1] + 2, 41)
    lin = linear_scale_space(t, f, s, x)
    np.testing.assert_allclose(warped_scale_space(t, f, s, IdentityWarp(), x), lin, atol=1e-12)
    np.testing.assert_allclose(
        warped_scale_space(t, f, s, PiecewiseLinearWarp(t, t), x), lin, rtol=0, atol=1e-12
    )


@settings(deadline=None, max_examples=30)
@given(sampled_signals())
def test_scale_zero_is_the_signal(sig: tuple[np.ndarray, np.ndarray]) -> None:
    t, f = sig
    np.testing.assert_allclose(warped_scale_space(t, f, 0.0), f, rtol=0, atol=1e-12)


def _count_extrema(t: np.ndarray, f: np.ndarray, s: float, warp: Warp) -> int:
    """Local extrema of F(., alpha, s) on the whole line: sign changes of its exact derivative.

    Sampled uniformly on the warped axis, s/10 apart, up to 20 s beyond the data (farther out
    the Gaussian tails drop below 1e-88 and then into subnormal numbers, where float64 cannot
    resolve a sign); a derivative counts as zero when it is rounding noise relative to the
    sum of the magnitudes of its terms (the same scale space of a signal with slopes |f'|).
    """
    u_ends = warp.gamma(np.array([t[0], t[-1]]))
    u = np.arange(u_ends[0] - 20 * s, u_ends[1] + 20 * s, s / 10)
    x = warp.alpha(u)
    d = warped_scale_space(t, f, s, warp, x, derivative=1)
    absf = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(f)))])
    scale = warped_scale_space(t, absf, s, warp, x, derivative=1)
    sgn = np.sign(np.where(np.abs(d) <= 1e-9 * scale, 0.0, d))
    sgn = sgn[sgn != 0]
    return int(np.sum(sgn[1:] != sgn[:-1]))


@st.composite
def signal_and_warp(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, Warp]:
    t, f = draw(sampled_signals(min_n=3, max_n=20, max_abs=10.0))
    if draw(st.booleans()):
        return t, f, arclength_warp(t, f)
    return t, f, PiecewiseLinearWarp(t, draw(increasing_knots(t.size)))


@settings(deadline=None, max_examples=40)
@given(signal_and_warp(), st.lists(st.floats(0.05, 6.0), min_size=2, max_size=4, unique=True))
def test_causality_number_of_extrema_never_increases(
    case: tuple[np.ndarray, np.ndarray, Warp], scales: list[float]
) -> None:
    """Lemma 1 / corollary 1: no new extrema appear as s grows, for any monotone warp."""
    t, f, warp = case
    slopes = np.sign(np.diff(f))
    slopes = slopes[slopes != 0]
    counts = [int(np.sum(slopes[1:] != slopes[:-1]))]  # s = 0: extrema of the interpolant
    counts += [_count_extrema(t, f, s, warp) for s in sorted(scales)]
    assert all(b <= a for a, b in itertools.pairwise(counts)), counts


@settings(deadline=None, max_examples=30)
@given(signal_and_warp(), st.floats(0.2, 4.0))
def test_extrema_are_not_enhanced(case: tuple[np.ndarray, np.ndarray, Warp], s: float) -> None:
    """Corollary 2: dF/ds <= 0 at spatial maxima and >= 0 at spatial minima (finite difference)."""
    t, f, warp = case
    u_ends = warp.gamma(np.array([t[0], t[-1]]))
    u = np.arange(u_ends[0] - 3 * s, u_ends[1] + 3 * s, s / 10)

    def deriv(uu: float) -> float:
        return float(warped_scale_space(t, f, s, warp, warp.alpha(np.array([uu])), derivative=1)[0])

    d = warped_scale_space(t, f, s, warp, warp.alpha(u), derivative=1)
    amp = float(np.ptp(f)) + 1.0
    h = 1e-3 * s
    for i in np.nonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0)[0]:
        ue = optimize.brentq(deriv, u[i], u[i + 1], xtol=1e-13)
        xe = warp.alpha(np.array([ue]))
        ds = (
            warped_scale_space(t, f, s + h, warp, xe) - warped_scale_space(t, f, s - h, warp, xe)
        )[0] / (2 * h)
        if d[i] > 0:  # + to -: a maximum
            assert ds <= 1e-6 * amp
        else:
            assert ds >= -1e-6 * amp


def test_warped_scale_space_keeps_edges() -> None:
    """Fig. 3.3's claim on a clean step: the warped scale space stays much closer to the step."""
    t = np.arange(60.0)
    f = np.where(t < 30, 0.0, 8.0)
    lin = linear_scale_space(t, f, 2.0)
    war = warped_scale_space(t, f, 2.0)
    assert np.abs(war - f).sum() < 0.5 * np.abs(lin - f).sum()
    assert np.max(np.diff(war)) > 2 * np.max(np.diff(lin))
