"""The warp-lang batched smoother against the numpy implementation, on every available device."""

from __future__ import annotations

import numpy as np
import pytest

from tests.fresh import python_c
from timewarp import arclength_warp, gaussian_filter, warped_convolve

wp = pytest.importorskip("warp")

from timewarp.batched import (  # noqa: E402 - only once warp is known to be importable
    BatchedWarpedSmoother,
    default_device,
    warped_smooth_batched,
)


def _devices() -> list[object]:
    params: list[object] = ["cpu"]
    params.append(
        pytest.param(
            "cuda",
            marks=[
                pytest.mark.gpu,
                pytest.mark.skipif(default_device() != "cuda", reason="no CUDA device"),
            ],
        )
    )
    return params


DEVICES = _devices()


def _numpy_reference(signals: np.ndarray, sigma: float, dt: float = 1.0) -> np.ndarray:
    n = signals.shape[1]
    t = dt * np.arange(n, dtype=np.float64)
    return np.stack(
        [warped_convolve(t, s, sigma, arclength_warp(t, s)) for s in signals.astype(np.float64)]
    )


@pytest.mark.parametrize("device", DEVICES)
def test_scalar_signals_match_numpy(device: str) -> None:
    rng = np.random.default_rng(0)
    signals = np.cumsum(rng.normal(size=(7, 50)), axis=1) * 0.5
    signals[2, 25:] += 4.0  # an edge
    got = warped_smooth_batched(signals, 2.5, device=device)
    ref = _numpy_reference(signals.astype(np.float32), 2.5)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_vector_signals_share_one_warp_per_signal(device: str) -> None:
    """Atom trajectories: the warp is the arclength of the 3-D curve, shared by x, y, z."""
    rng = np.random.default_rng(1)
    coords = np.cumsum(rng.normal(scale=0.3, size=(5, 40, 3)), axis=1)
    got = warped_smooth_batched(coords, 1.8, dt=0.5, device=device)
    ref = _numpy_reference(coords.astype(np.float32), 1.8, dt=0.5)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_identity_mode_is_classical_smoothing(device: str) -> None:
    rng = np.random.default_rng(2)
    signals = rng.normal(size=(4, 33))
    got = warped_smooth_batched(signals, 3.0, mode="identity", device=device)
    ref = np.stack([gaussian_filter(s, 3.0) for s in signals.astype(np.float32)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_smoother_reuses_its_buffers_across_windows(device: str) -> None:
    rng = np.random.default_rng(3)
    smoother = BatchedWarpedSmoother(3, 20, 1, device=device)
    for _ in range(3):
        signals = rng.normal(size=(3, 20))
        np.testing.assert_allclose(
            smoother(signals, 1.2), _numpy_reference(signals.astype(np.float32), 1.2), atol=1e-5
        )
    with pytest.raises(ValueError):
        smoother(rng.normal(size=(3, 21)), 1.2)
    with pytest.raises(ValueError):
        smoother(rng.normal(size=(3, 20)), 0.0)


def test_truncation_matches_the_truncated_numpy_sum() -> None:
    rng = np.random.default_rng(4)
    signals = rng.normal(size=(2, 30)) * 3
    got = warped_smooth_batched(signals, 2.0, truncate=1.5, device="cpu")
    t = np.arange(30.0)
    ref = np.stack(
        [
            warped_convolve(t, s, 2.0, arclength_warp(t, s), truncate=1.5)
            for s in signals.astype(np.float32).astype(np.float64)
        ]
    )
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5)


def test_package_import_needs_no_optional_dependency() -> None:
    code = (
        "import sys, timewarp as tw; "
        "bad = [m for m in ('warp', 'matplotlib', 'skimage', 'scipy') if m in sys.modules]; "
        "sys.exit(1 if bad else 0)"
    )
    proc = python_c(code, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
