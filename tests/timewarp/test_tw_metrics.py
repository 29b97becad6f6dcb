"""Metrics against closed forms: Marschner-Lobb metrics, spectra, transfer functions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from timewarp import (
    AffineWarp,
    IdentityWarp,
    energy_bandwidth,
    energy_fraction_below,
    gaussian_frequency_response,
    marschner_lobb,
    postaliasing_metric,
    signal_spectrum,
    signal_weighted_postaliasing,
    signal_weighted_smoothing,
    smoothing_metric,
    step_edge_signal,
    total_absolute_error,
    warp_transfer_function,
)


def _gauss_band_integral(a: float, lo: float, hi: float) -> float:
    """int_lo^hi exp(-a w^2) dw."""
    r = math.sqrt(a)
    return math.sqrt(math.pi / a) / 2 * (math.erf(r * hi) - math.erf(r * lo))


@pytest.mark.parametrize("sigma", [0.2, 0.5, 1.3])
@pytest.mark.parametrize("omega", [0.5, 2.0])
def test_gaussian_smoothing_and_postaliasing_closed_form(sigma: float, omega: float) -> None:
    a = 2 * math.pi**2 * sigma**2

    def resp(w: np.ndarray) -> np.ndarray:
        return gaussian_frequency_response(w, sigma)

    s_ref = 2.0 - 2 * _gauss_band_integral(a, 0.0, omega) / omega
    p_ref = 2 * _gauss_band_integral(a, omega, 10.0) / omega
    assert smoothing_metric(resp, omega) == pytest.approx(s_ref, rel=1e-6)
    assert postaliasing_metric(resp, omega, 10.0) == pytest.approx(p_ref, rel=1e-5, abs=1e-12)


def test_ideal_low_pass_has_no_smoothing_or_postaliasing() -> None:
    def box(w: np.ndarray) -> np.ndarray:
        return (np.abs(w) <= 1.0).astype(np.float64)

    assert smoothing_metric(box, 1.0) == pytest.approx(0.0, abs=1e-12)
    assert postaliasing_metric(box, 1.0, 5.0) == pytest.approx(0.0, abs=1e-3)


def test_gaussian_response_is_the_fourier_transform_of_the_kernel() -> None:
    sigma, w = 0.8, 0.37
    x = np.linspace(-12, 12, 24001)
    g = np.exp(-0.5 * (x / sigma) ** 2) / (math.sqrt(2 * math.pi) * sigma)
    ft = np.sum(g * np.cos(2 * math.pi * w * x)) * (x[1] - x[0])
    assert float(gaussian_frequency_response(np.array(w), sigma)) == pytest.approx(ft, rel=1e-9)


def test_signal_weighted_metrics() -> None:
    f = np.sin(2 * np.pi * 0.1 * np.arange(200))
    freqs, spec = signal_spectrum(f, 1.0)
    band = np.abs(freqs) <= 0.25
    expected = np.sum(np.abs(spec[band])) / 200 / 0.25

    def zero(w: np.ndarray) -> np.ndarray:
        return np.zeros_like(w)

    def one(w: np.ndarray) -> np.ndarray:
        return np.ones_like(w)

    assert signal_weighted_smoothing(f, 1.0, zero, 0.25) == pytest.approx(expected, rel=1e-12)
    assert signal_weighted_smoothing(f, 1.0, one, 0.25) == pytest.approx(0.0, abs=1e-15)
    assert signal_weighted_postaliasing(3.0, 1.25) == pytest.approx(1.75)


def test_spectrum_is_the_riemann_sum_fourier_transform() -> None:
    t = np.arange(64) * 0.5
    f = np.exp(-0.1 * (t - 10.0) ** 2)
    freqs, spec = signal_spectrum(f, 0.5)
    k = 5
    direct = np.sum(f * np.exp(-2j * np.pi * freqs[k] * t)) * 0.5
    assert spec[k] == pytest.approx(direct, rel=1e-12)


def test_energy_of_a_sinusoid_sits_at_its_frequency() -> None:
    dt = 0.01
    t = np.arange(0.0, 10.0, dt)
    f = np.cos(2 * np.pi * 3.0 * t)
    assert energy_fraction_below(f, dt, 3.05) == pytest.approx(1.0, abs=1e-12)
    assert energy_fraction_below(f, dt, 2.95) == pytest.approx(0.0, abs=1e-12)
    assert energy_bandwidth(f, dt, 0.99) == pytest.approx(3.0, abs=1e-9)


def test_marschner_lobb_function() -> None:
    x = np.array([-1.0, 0.0, 1.0, 2.0 / 3.0])
    # cos(pi x / 2) = 0, 1, 0, 1/2 -> 1 + cos(0), 1 + cos(12 pi), ..., 1 + cos(6 pi)
    np.testing.assert_allclose(marschner_lobb(x), [2.0, 2.0, 2.0, 2.0], atol=1e-12)
    assert float(marschner_lobb(np.array(np.arccos(1 / 12) * 2 / np.pi))) == pytest.approx(
        1 + math.cos(math.pi), abs=1e-12
    )


def test_total_absolute_error() -> None:
    assert total_absolute_error([1.0, 2.0, 3.0], [1.5, 2.0, 1.0]) == pytest.approx(2.5)
    with pytest.raises(ValueError):
        total_absolute_error([1.0], [1.0, 2.0])


def test_transfer_function_of_identity_and_affine_warps() -> None:
    """Closed forms: int_0^T exp(i 2 pi (k a - w) t) dt times exp(i 2 pi k b)."""
    w = np.linspace(0.0, 0.5, 7)
    k = np.linspace(0.0, 0.5, 6)
    t1 = 10.0
    for warp, a, b in ((IdentityWarp(), 1.0, 0.0), (AffineWarp(1.7, 0.3), 1.7, 0.3)):
        got = warp_transfer_function(warp, w, k, 0.0, t1)
        nu = k[None, :] * a - w[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            ref = (np.exp(2j * np.pi * nu * t1) - 1) / (2j * np.pi * nu)
        ref = np.where(np.abs(nu) < 1e-14, t1, ref) * np.exp(2j * np.pi * k[None, :] * b)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)


def test_step_signal_is_deterministic_and_scaled() -> None:
    a = step_edge_signal(128, amplitude=2.0)
    b = step_edge_signal(128, amplitude=1.0)
    np.testing.assert_allclose(a, 2.0 * b)
    assert a.shape == (128,)
