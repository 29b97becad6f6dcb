"""Warped and classical convolution, reconstruction and filtering against independent oracles."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate, ndimage

from timewarp import (
    AffineWarp,
    IdentityWarp,
    PiecewiseLinearWarp,
    arclength_warp,
    classical_reconstruction,
    convolve,
    gaussian,
    gaussian_denoise,
    gaussian_filter,
    sample_weights,
    warped_convolve,
    warped_denoise,
    warped_reconstruction,
)

from .strategies import sampled_signals

sigmas = st.floats(0.05, 8.0)


@pytest.mark.parametrize("sigma", [0.01, 0.3, 1.0, 7.5])
def test_gaussian_kernel_integrates_to_one(sigma: float) -> None:
    lim = 40.0 * sigma
    val, _ = integrate.quad(
        lambda x: float(gaussian(np.array(x), sigma)), -lim, lim, points=[0.0], epsabs=1e-13
    )
    assert val == pytest.approx(1.0, abs=1e-10)


@settings(deadline=None, max_examples=40)
@given(sampled_signals(), sigmas, st.floats(-1e3, 1e3))
def test_normalised_weights_sum_to_one(
    sig: tuple[np.ndarray, np.ndarray], sigma: float, c: float
) -> None:
    """A normalised kernel reproduces a constant exactly, warped or not, anywhere."""
    t, _ = sig
    x = np.linspace(t[0] - 2 * sigma, t[-1] + 2 * sigma, 31)
    const = np.full(t.size, c)
    warp = arclength_warp(t, sig[1])
    for out in (convolve(t, const, sigma, x), warped_convolve(t, const, sigma, warp, x)):
        np.testing.assert_allclose(out, c, rtol=1e-13, atol=1e-13)


@settings(deadline=None, max_examples=50)
@given(sampled_signals(), sigmas)
def test_identity_warp_reproduces_classical_convolution(
    sig: tuple[np.ndarray, np.ndarray], sigma: float
) -> None:
    t, f = sig
    x = np.linspace(t[0] - 1.0, t[-1] + 1.0, 57)
    for warp in (IdentityWarp(), PiecewiseLinearWarp(t, t)):
        np.testing.assert_allclose(
            warped_convolve(t, f, sigma, warp, x), convolve(t, f, sigma, x), rtol=0, atol=1e-12
        )
        np.testing.assert_allclose(
            warped_reconstruction(t, f, x, sigma, warp),
            classical_reconstruction(t, f, x, sigma),
            rtol=0,
            atol=1e-12,
        )


@settings(deadline=None, max_examples=50)
@given(sampled_signals(min_n=2, max_n=40, uniform=True), sigmas)
def test_identity_warp_denoising_equals_the_classical_filter(
    sig: tuple[np.ndarray, np.ndarray], sigma: float
) -> None:
    """The warped filter (dense sums) against the np.convolve-based classical filter."""
    _, f = sig
    np.testing.assert_allclose(
        warped_denoise(f, sigma, IdentityWarp()), gaussian_denoise(f, sigma), rtol=0, atol=1e-12
    )


def test_warped_convolution_matches_a_brute_force_loop() -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.2, 1.5, 15))
    f = rng.normal(size=15) * 4
    x = np.linspace(t[0] - 1, t[-1] + 1, 23)
    warp = arclength_warp(t, f)
    sigma = 1.7
    for jac in (False, True):
        got = warped_convolve(t, f, sigma, warp, x, jacobian=jac)
        raw = warped_convolve(t, f, sigma, warp, x, jacobian=jac, normalise=False)
        g = warp.gamma(t)
        nodes = g if jac else t
        w = np.empty(t.size)
        for j in range(t.size):
            left = nodes[j] - nodes[j - 1] if j > 0 else nodes[1] - nodes[0]
            right = nodes[j + 1] - nodes[j] if j < t.size - 1 else nodes[-1] - nodes[-2]
            w[j] = 0.5 * (left + right)
        for i, xi in enumerate(x):
            num = den = 0.0
            gx = float(warp.gamma(np.array([xi]))[0])
            for j in range(t.size):
                k = np.exp(-0.5 * ((gx - g[j]) / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma)
                num += w[j] * f[j] * k
                den += w[j] * k
            assert got[i] == pytest.approx(num / den, rel=1e-12, abs=1e-12)
            assert raw[i] == pytest.approx(num, rel=1e-12, abs=1e-12)


@settings(deadline=None, max_examples=40)
@given(sampled_signals(), sigmas, st.floats(0.2, 5.0))
def test_affine_warp_is_a_rescaled_kernel(
    sig: tuple[np.ndarray, np.ndarray], sigma: float, a: float
) -> None:
    """gamma = a t turns the kernel G(a (x - t), sigma) into G(x - t, sigma / a)."""
    t, f = sig
    x = np.linspace(t[0], t[-1], 19)
    np.testing.assert_allclose(
        warped_convolve(t, f, sigma, AffineWarp(a, 3.0), x),
        convolve(t, f, sigma / a, x),
        rtol=1e-9,
        atol=1e-9,
    )


def test_unnormalised_convolution_is_the_continuous_integral() -> None:
    """A Riemann sum of a smooth signal: the Gaussian blur of sin(w t) is exp(-w^2 s^2/2) sin."""
    t = np.linspace(-60.0, 60.0, 4801)
    w0, sigma = 0.7, 1.3
    x = np.linspace(-5.0, 5.0, 11)
    got = convolve(t, np.sin(w0 * t), sigma, x, normalise=False)
    np.testing.assert_allclose(got, np.exp(-0.5 * (w0 * sigma) ** 2) * np.sin(w0 * x), atol=1e-9)


def test_classical_filter_agrees_with_scipy_away_from_the_ends() -> None:
    rng = np.random.default_rng(0)
    f = rng.normal(size=300)
    sigma = 4.0
    ours = gaussian_filter(f, sigma)
    ref = ndimage.gaussian_filter1d(f, sigma, truncate=12.0, mode="constant")
    margin = int(12 * sigma) + 1
    np.testing.assert_allclose(ours[margin:-margin], ref[margin:-margin], rtol=0, atol=1e-12)


def test_sample_weights_are_cell_widths() -> None:
    np.testing.assert_allclose(sample_weights(np.arange(5.0)), 1.0)
    np.testing.assert_allclose(sample_weights(np.array([0.0, 1.0, 3.0])), [1.0, 1.5, 2.0])


def test_truncation_drops_distant_samples() -> None:
    t = np.arange(10.0)
    f = np.zeros(10)
    f[9] = 100.0
    out = convolve(t, f, 1.0, np.array([0.0]), truncate=3.0)
    assert out[0] == 0.0
    assert convolve(t, f, 1.0, np.array([0.0]))[0] > 0.0


def test_warped_reconstruction_interpolates_gamma_linearly() -> None:
    """Section 4.2.1: gamma on the finer lattice is the linear interpolant of its samples."""
    t = np.arange(8.0)
    f = np.array([0.0, 2.0, -1.0, 0.5, 3.0, 3.0, 0.0, 1.0])
    x = np.linspace(0.0, 7.0, 36)
    warp = arclength_warp(t, f)
    np.testing.assert_allclose(warp.gamma(x), np.interp(x, t, warp.gamma(t)), rtol=1e-15)
    rec = warped_reconstruction(t, f, x, 0.6)
    np.testing.assert_allclose(rec, warped_reconstruction(t, f, x, 0.6, warp), rtol=1e-15)


def test_warped_filter_preserves_a_step_better() -> None:
    """The edge-preservation claim on a clean step: warped method noise is far smaller."""
    f = np.where(np.arange(80) < 40, 0.0, 10.0)
    t = np.arange(80.0)
    classical = np.abs(gaussian_denoise(f, 4.0) - f).sum()
    warped = np.abs(warped_denoise(f, 4.0, arclength_warp(t, f)) - f).sum()
    assert warped < 0.2 * classical


def test_bad_sigma_is_rejected() -> None:
    with pytest.raises(ValueError):
        convolve(np.arange(3.0), np.zeros(3), 0.0)
    with pytest.raises(ValueError):
        gaussian_filter(np.zeros(3), -1.0)
