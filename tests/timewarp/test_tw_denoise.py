"""Noise, denoising trials and the method-noise study."""

from __future__ import annotations

import numpy as np
import pytest

from timewarp import (
    METHODS,
    add_noise,
    arclength_warp,
    denoise_trial,
    gaussian_denoise,
    method_noise_study,
    total_absolute_error,
    warped_denoise,
)
from timewarp.denoise import method_noise_only


@pytest.mark.parametrize(("level", "as_variance", "std"), [(0.5, False, 0.5), (0.25, True, 0.5)])
def test_noise_level_is_std_or_variance(level: float, as_variance: bool, std: float) -> None:
    f = np.zeros(200_000)
    n = add_noise(f, level, np.random.default_rng(1), as_variance=as_variance)
    assert n.mean() == pytest.approx(0.0, abs=0.01)
    assert n.std() == pytest.approx(std, rel=0.01)


def test_trial_errors_are_the_total_absolute_errors() -> None:
    clean = np.where(np.arange(100) < 50, 0.0, 5.0)
    trial = denoise_trial(clean, 0.3, 3.0, np.random.default_rng(5))
    assert set(trial.errors) == set(METHODS)
    t = np.arange(100.0)
    expected = {
        "classical": gaussian_denoise(trial.noisy, 3.0),
        "noisy_warp": warped_denoise(trial.noisy, 3.0, arclength_warp(t, trial.noisy)),
        "ground_truth_warp": warped_denoise(trial.noisy, 3.0, arclength_warp(t, clean)),
    }
    for m in METHODS:
        np.testing.assert_allclose(trial.filtered[m], expected[m], rtol=1e-14)
        assert trial.errors[m] == pytest.approx(total_absolute_error(expected[m], clean))


def test_study_reuses_the_same_noise_for_every_method() -> None:
    clean = np.sin(np.arange(64) / 5.0)
    study = method_noise_study(clean, [0.1, 0.4], 2.0, [0, 1, 2])
    assert sorted(study) == [0.1, 0.4]
    for per in study.values():
        assert set(per) == set(METHODS)
        assert all(v.shape == (3,) for v in per.values())
    again = denoise_trial(clean, 0.4, 2.0, np.random.default_rng(1))
    assert study[0.4]["classical"][1] == pytest.approx(again.errors["classical"])
    # more noise, more error
    assert study[0.4]["classical"].mean() > study[0.1]["classical"].mean()


def test_ground_truth_warp_removes_noise_but_keeps_a_steep_step() -> None:
    """Theorem 5 in a case where its premise is clearly met: a tall step, mild noise."""
    clean = np.where(np.arange(120) < 60, 0.0, 20.0)
    errs = method_noise_study(clean, [0.3], 5.0, range(5))[0.3]
    assert errs["ground_truth_warp"].mean() < 0.5 * errs["classical"].mean()
    assert np.all(errs["ground_truth_warp"] < errs["classical"])


def test_method_noise_only_filters_the_clean_signal() -> None:
    clean = np.where(np.arange(60) < 30, 0.0, 10.0)
    mn = method_noise_only(clean, 3.0)
    assert mn["classical"] == pytest.approx(
        total_absolute_error(gaussian_denoise(clean, 3.0), clean)
    )
    assert mn["ground_truth_warp"] < mn["classical"]


def test_filters_keep_constants() -> None:
    f = np.full(40, 2.5)
    np.testing.assert_allclose(gaussian_denoise(f, 3.0), 2.5, rtol=1e-14)
    np.testing.assert_allclose(warped_denoise(f, 3.0), 2.5, rtol=1e-14)
