"""Warps: monotonicity, exact inversion, the arclength formula and lemma 2's scaling."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from timewarp import (
    AffineWarp,
    CallableWarp,
    IdentityWarp,
    PiecewiseLinearWarp,
    arclength,
    arclength_warp,
    length_normalising_constant,
    normalise_bandwidth,
)

from .strategies import increasing_knots, sampled_signals


def test_arclength_matches_a_loop_over_segments() -> None:
    t = np.array([0.0, 0.5, 2.0, 2.25, 4.0])
    f = np.array([1.0, -2.0, 0.0, 0.0, 3.5])
    expected = [0.0]
    for k in range(1, t.size):
        expected.append(expected[-1] + math.hypot(t[k] - t[k - 1], f[k] - f[k - 1]))
    np.testing.assert_allclose(arclength(t, f), t[0] + np.array(expected), rtol=1e-15)


def test_arclength_of_vector_signal_is_the_curve_length() -> None:
    t = np.arange(4.0)
    xyz = np.array([[0, 0, 0], [1, 2, 2], [1, 2, 2], [4, 6, 2]], dtype=float)
    # segment lengths sqrt(1 + 9) , 1, sqrt(1 + 25)
    expected = np.cumsum([0.0, math.sqrt(10.0), 1.0, math.sqrt(26.0)])
    np.testing.assert_allclose(arclength(t, xyz), expected, rtol=1e-15)


def test_constant_signal_gives_the_identity() -> None:
    t = np.linspace(-1.0, 3.0, 9)
    w = arclength_warp(t, np.full(9, 7.0))
    x = np.linspace(-5.0, 8.0, 50)
    np.testing.assert_allclose(w.gamma(x), x, atol=1e-14)
    np.testing.assert_allclose(w.dgamma(x), 1.0, atol=1e-14)


def test_gain_scales_the_signal_for_the_arclength_only() -> None:
    t = np.arange(5.0)
    f = np.array([0.0, 0.1, 0.3, 0.2, 0.9])
    np.testing.assert_allclose(arclength(t, f, gain=255.0), arclength(t, 255.0 * f), rtol=1e-15)


@settings(deadline=None, max_examples=60)
@given(sampled_signals(max_abs=1e5))
def test_gamma_is_strictly_increasing(sig: tuple[np.ndarray, np.ndarray]) -> None:
    t, f = sig
    w = arclength_warp(t, f)
    assert np.all(np.diff(w.gamma(t)) > 0)
    x = np.linspace(t[0] - 3.0, t[-1] + 3.0, 200)
    assert np.all(np.diff(w.gamma(x)) > 0)
    # gamma' >= 1 everywhere: the arclength never runs slower than time (lemma 3's premise)
    assert np.all(w.dgamma(x) >= 1.0 - 1e-6)


@settings(deadline=None, max_examples=60)
@given(sampled_signals(max_abs=1e3), st.floats(-3.0, 3.0))
def test_round_trip_alpha_of_gamma(sig: tuple[np.ndarray, np.ndarray], shift: float) -> None:
    t, f = sig
    w = arclength_warp(t, f)
    x = np.concatenate([t, np.linspace(t[0] + shift, t[-1] - shift, 37)])
    scale = max(1.0, float(np.max(np.abs(w.gamma(x)))))
    np.testing.assert_allclose(w.alpha(w.gamma(x)), x, rtol=0, atol=1e-12 * scale)
    u = np.linspace(w.gamma(t)[0] - 2, w.gamma(t)[-1] + 2, 41)
    np.testing.assert_allclose(w.gamma(w.alpha(u)), u, rtol=0, atol=1e-12 * scale)


@settings(deadline=None, max_examples=30)
@given(increasing_knots(6), increasing_knots(6))
def test_piecewise_linear_warp_interpolates_its_knots(kt: np.ndarray, ku: np.ndarray) -> None:
    w = PiecewiseLinearWarp(kt, ku)
    np.testing.assert_allclose(w.gamma(kt), ku, rtol=1e-14, atol=1e-12)
    mid = 0.5 * (kt[1:] + kt[:-1])
    np.testing.assert_allclose(w.gamma(mid), 0.5 * (ku[1:] + ku[:-1]), rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(w.dgamma(mid), np.diff(ku) / np.diff(kt), rtol=1e-12)
    # slope 1 beyond the ends
    np.testing.assert_allclose(w.gamma(kt[-1] + 2.5), ku[-1] + 2.5, rtol=1e-14)
    np.testing.assert_allclose(w.gamma(kt[0] - 1.5), ku[0] - 1.5, rtol=1e-14)


def test_callable_warp_inverts_by_bisection() -> None:
    w = CallableWarp(lambda t: t + 0.5 * np.sin(t))  # gamma' = 1 + cos/2 >= 1/2
    u = np.linspace(-40.0, 25.0, 101)
    t = w.alpha(u)
    np.testing.assert_allclose(t + 0.5 * np.sin(t), u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w.dgamma(np.array([0.3])), 1 + 0.5 * np.cos(0.3), rtol=1e-8)


def test_identity_and_affine_warps() -> None:
    x = np.linspace(-3.0, 3.0, 13)
    np.testing.assert_array_equal(IdentityWarp().gamma(x), x)
    a = AffineWarp(2.5, -1.0)
    np.testing.assert_allclose(a.gamma(x), 2.5 * x - 1.0)
    np.testing.assert_allclose(a.alpha(a.gamma(x)), x, rtol=0, atol=1e-15)
    with pytest.raises(ValueError):
        AffineWarp(0.0)


def test_bandwidth_normalisation_scales_the_warped_axis() -> None:
    t = np.arange(6.0)
    f = np.array([0.0, 3.0, 3.0, -1.0, 0.0, 4.0])
    w = arclength_warp(t, f)
    c = length_normalising_constant(w, t[0], t[-1])
    wd = normalise_bandwidth(w, c)
    g = wd.gamma(t)
    assert g[-1] - g[0] == pytest.approx(t[-1] - t[0], rel=1e-14)
    u = np.linspace(0.0, 4.0, 9)
    np.testing.assert_allclose(wd.alpha(u), w.alpha(c * u), rtol=1e-14)
    # for a linear warp the thesis's alpha_d = c * alpha coincides with alpha(c u)
    lin = normalise_bandwidth(AffineWarp(2.0), 3.0)
    np.testing.assert_allclose(lin.alpha(u), 3.0 * AffineWarp(2.0).alpha(u), rtol=1e-15)


def test_invalid_input_is_rejected() -> None:
    with pytest.raises(ValueError):
        arclength(np.array([0.0, 0.0, 1.0]), np.zeros(3))
    with pytest.raises(ValueError):
        arclength(np.arange(3.0), np.zeros(4))
    with pytest.raises(ValueError):
        arclength(np.arange(3.0), np.array([0.0, np.nan, 1.0]))
    with pytest.raises(ValueError):
        PiecewiseLinearWarp(np.arange(3.0), np.array([0.0, 2.0, 1.0]))
