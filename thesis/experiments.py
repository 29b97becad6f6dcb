"""The experiments of thesis chapters 3-4 as plain functions returning their numbers.

Everything here is numpy (plus scikit-image to load the real scanline); plotting lives in
:mod:`thesis.figures` and the markdown report in :mod:`thesis.report`.
The thesis's own numbers are kept here for the side-by-side comparison only.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from timewarp._types import FloatArray, uniform_lattice
from timewarp.denoise import method_noise_only, method_noise_study
from timewarp.metrics import (
    energy_fraction_below,
    gaussian_frequency_response,
    postaliasing_metric,
    signal_weighted_smoothing,
    smoothing_metric,
    total_absolute_error,
    warp_transfer_function,
)
from timewarp.reconstruction import classical_reconstruction, warped_reconstruction
from timewarp.scalespace import linear_scale_space, warped_scale_space
from timewarp.signals import camera_scanline, marschner_lobb, step_edge_signal
from timewarp.warps import (
    IdentityWarp,
    Warp,
    arclength_warp,
    length_normalising_constant,
    normalise_bandwidth,
)

# ---------------------------------------------------------------------------------------------
# The thesis's numbers (tables 4.1-4.5), quoted for comparison only.

SIGMAS = np.arange(1, 21, dtype=np.float64) / 15.0
THESIS_4_1 = {
    "classical": [25.129, 20.405, 21.519, 25.553, 29.856, 33.697, 37.070, 40.044, 42.679, 45.022,
                  47.114, 48.990, 50.685, 52.232, 53.645, 54.934, 56.114, 57.197, 58.196, 59.119],
    "warped": [30.419, 27.512, 24.879, 23.287, 22.534, 22.201, 22.178, 22.761, 23.832, 25.195,
               26.615, 28.172, 29.747, 31.396, 33.042, 34.637, 36.196, 37.716, 39.174, 40.570],
}  # fmt: skip
THESIS_4_2 = {
    "classical": [42.712, 41.616, 41.600, 42.364, 43.630, 44.977, 46.273, 47.435, 48.486, 49.495,
                  50.371, 51.154, 51.840, 52.452, 53.019, 53.552, 54.033, 54.464, 54.856, 55.215],
    "warped": [43.251, 42.346, 41.609, 41.400, 41.416, 41.629, 41.992, 42.398, 42.912, 43.493,
               44.080, 44.649, 45.200, 45.735, 46.249, 46.743, 47.221, 47.680, 48.116, 48.541],
}  # fmt: skip
THESIS_4_3 = {"classical": 51.597, "noisy_warp": 43.334, "ground_truth_warp": 34.58}
THESIS_4_4 = {"classical": 104.29, "noisy_warp": 91.241, "ground_truth_warp": 83.04}
THESIS_4_5 = {
    0.3: {"noisy_warp": 83.514, "ground_truth_warp": 83.275, "classical": 96.960},
    0.5: {"noisy_warp": 114.62, "ground_truth_warp": 107.56, "classical": 120.68},
    0.7: {"noisy_warp": 192.91, "ground_truth_warp": 163.99, "classical": 172.13},
}

ML_STEP = 0.05  # sampling interval of the Marschner-Lobb samples on [-1, 1]
ML_LATTICE = 0.01  # reconstruction lattice spacing
SUBSAMPLE = 5  # real data: every 5th pixel is a sample
CAMERA_ROW = 256
GRAY_LEVELS = 255.0  # the warp gain that reads intensities as 8-bit grey levels
DENOISE_SIGMA = 6.0
NOISE_LEVELS = (0.3, 0.5, 0.7, 0.9)
SCALE_S = 2.0
SYNTH_N = 256

# ---------------------------------------------------------------------------------------------
# Reconstruction (section 4.2)


@dataclass
class Reconstruction:
    """Errors of both reconstructions over ``sigmas`` and the data they came from."""

    sigmas: FloatArray
    classical: FloatArray
    warped: FloatArray
    t_samples: FloatArray
    f_samples: FloatArray
    t_lattice: FloatArray
    truth: FloatArray
    warp: Warp


def run_reconstruction(
    t_samples: FloatArray,
    f_samples: FloatArray,
    t_lattice: FloatArray,
    truth: FloatArray,
    sigmas: FloatArray,
    warp: Warp | None = None,
) -> Reconstruction:
    """Classical (eq. 4.2) vs warped (eq. 4.8) reconstruction error for every sigma."""
    wrp = arclength_warp(t_samples, f_samples) if warp is None else warp
    c = [
        total_absolute_error(classical_reconstruction(t_samples, f_samples, t_lattice, s), truth)
        for s in sigmas
    ]
    w = [
        total_absolute_error(warped_reconstruction(t_samples, f_samples, t_lattice, s, wrp), truth)
        for s in sigmas
    ]
    return Reconstruction(
        sigmas, np.asarray(c), np.asarray(w), t_samples, f_samples, t_lattice, truth, wrp
    )


def crossover(
    sigmas: FloatArray, classical: FloatArray, warped: FloatArray
) -> tuple[float | None, float | None]:
    """First tabulated sigma from which the warped error stays below the classical one, and the
    linearly interpolated sigma where their difference changes sign just before it."""
    better = np.asarray(warped) < np.asarray(classical)
    if not better[-1]:
        return None, None
    idx = len(better) - 1
    while idx > 0 and better[idx - 1]:
        idx -= 1
    if idx == 0:
        return float(sigmas[0]), None
    d0 = warped[idx - 1] - classical[idx - 1]
    d1 = warped[idx] - classical[idx]
    s0, s1 = sigmas[idx - 1], sigmas[idx]
    return float(sigmas[idx]), float(s0 + (s1 - s0) * d0 / (d0 - d1))


def natural_cubic_spline(t: FloatArray, f: FloatArray, x: FloatArray) -> FloatArray:
    """Natural cubic spline through ``(t, f)`` at ``x``: a reference reconstruction."""
    n = t.size
    h = np.diff(t)
    a = np.zeros((n, n))
    rhs = np.zeros(n)
    a[0, 0] = a[-1, -1] = 1.0
    for i in range(1, n - 1):
        a[i, i - 1] = h[i - 1]
        a[i, i] = 2 * (h[i - 1] + h[i])
        a[i, i + 1] = h[i]
        rhs[i] = 6 * ((f[i + 1] - f[i]) / h[i] - (f[i] - f[i - 1]) / h[i - 1])
    m = np.linalg.solve(a, rhs)
    k = np.clip(np.searchsorted(t, x, side="right") - 1, 0, n - 2)
    hk = h[k]
    u0 = t[k + 1] - x
    u1 = x - t[k]
    out = (
        m[k] * u0**3 / (6 * hk)
        + m[k + 1] * u1**3 / (6 * hk)
        + (f[k] / hk - m[k] * hk / 6) * u0
        + (f[k + 1] / hk - m[k + 1] * hk / 6) * u1
    )
    return np.asarray(out, dtype=np.float64)


def ml_data(units: str) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """ML samples at 0.05 on [-1, 1] and the 0.01 lattice, in "samples" or "signal" units."""
    x_s = np.linspace(-1.0, 1.0, round(2 / ML_STEP) + 1)
    x_l = np.linspace(-1.0, 1.0, round(2 / ML_LATTICE) + 1)
    f_s, truth = marschner_lobb(x_s), marschner_lobb(x_l)
    if units == "samples":
        x_s, x_l = (x_s + 1) / ML_STEP, (x_l + 1) / ML_STEP
    return np.asarray(x_s, dtype=np.float64), f_s, np.asarray(x_l, dtype=np.float64), truth


def real_data(row: FloatArray, units: str) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Every 5th pixel as samples and the pixels they span as the lattice."""
    last = SUBSAMPLE * ((row.size - 1) // SUBSAMPLE)
    px = np.arange(last + 1, dtype=np.float64)
    idx = np.arange(0, last + 1, SUBSAMPLE)
    scale = 1.0 / SUBSAMPLE if units == "samples" else 1.0
    t = np.asarray(idx * scale, dtype=np.float64)
    return t, row[idx], np.asarray(px * scale, dtype=np.float64), row[: last + 1]


@dataclass
class ReconstructionStudy:
    ml: Reconstruction
    real: Reconstruction
    ml_variants: dict[str, Reconstruction]
    real_variants: dict[str, Reconstruction]
    references: dict[str, float]
    best_classical: dict[str, tuple[float, float]]


def best_classical(
    t: FloatArray, f: FloatArray, x: FloatArray, truth: FloatArray
) -> tuple[float, float]:
    """Smallest classical reconstruction error over a dense sigma range, and its sigma.

    The minimum does not depend on the unit sigma is expressed in, so it tells whether any
    reading of the thesis's sigma column could reproduce its error levels.
    """
    grid = np.geomspace(0.02, 5.0, 400) * float(np.median(np.diff(t)))
    errs = [total_absolute_error(classical_reconstruction(t, f, x, s), truth) for s in grid]
    i = int(np.argmin(errs))
    return float(errs[i]), float(grid[i] / np.median(np.diff(t)))


def run_reconstruction_study(row: FloatArray) -> ReconstructionStudy:
    """Tables 4.1 and 4.2 in the primary convention plus the convention variants."""
    ts, fs, tl, truth = ml_data("samples")
    ml = run_reconstruction(ts, fs, tl, truth, SIGMAS)
    xs, fxs, xl, truth_x = ml_data("signal")
    c_ml = length_normalising_constant(ml.warp, ts[0], ts[-1])
    ml_variants = {
        "signal units": run_reconstruction(xs, fxs, xl, truth_x, SIGMAS),
        "bandwidth-normalised warp": run_reconstruction(
            ts, fs, tl, truth, SIGMAS, normalise_bandwidth(ml.warp, c_ml)
        ),
    }
    rt, rf, rl, rtruth = real_data(row, "samples")
    real = run_reconstruction(rt, rf, rl, rtruth, SIGMAS)
    pt, pf, pl, ptruth = real_data(row, "signal")
    c_real = length_normalising_constant(real.warp, rt[0], rt[-1])
    real_variants = {
        "signal units (pixels)": run_reconstruction(pt, pf, pl, ptruth, SIGMAS),
        "bandwidth-normalised warp": run_reconstruction(
            rt, rf, rl, rtruth, SIGMAS, normalise_bandwidth(real.warp, c_real)
        ),
        "warp from grey levels 0-255": run_reconstruction(
            rt, rf, rl, rtruth, SIGMAS, arclength_warp(rt, rf, GRAY_LEVELS)
        ),
    }
    references = {
        "ml_linear": total_absolute_error(np.interp(tl, ts, fs), truth),
        "ml_spline": total_absolute_error(natural_cubic_spline(ts, fs, tl), truth),
        "real_linear": total_absolute_error(np.interp(rl, rt, rf), rtruth),
        "real_spline": total_absolute_error(natural_cubic_spline(rt, rf, rl), rtruth),
    }
    best = {"ml": best_classical(ts, fs, tl, truth), "real": best_classical(rt, rf, rl, rtruth)}
    return ReconstructionStudy(ml, real, ml_variants, real_variants, references, best)


# ---------------------------------------------------------------------------------------------
# Scale space (chapter 3)


def count_extrema(derivative: FloatArray) -> int:
    """Sign changes of a sampled derivative, ignoring values that are zero to rounding."""
    if derivative.size == 0:
        return 0
    thr = 1e-9 * float(np.max(np.abs(derivative)))
    sgn = np.sign(np.where(np.abs(derivative) <= thr, 0.0, derivative))
    sgn = sgn[sgn != 0]
    return int(np.sum(sgn[1:] != sgn[:-1]))


@dataclass
class ScaleSpaceResult:
    t: FloatArray
    f: FloatArray
    linear: FloatArray
    warped: FloatArray
    dgamma: FloatArray
    scales: list[float]
    extrema: dict[str, list[int]]


def run_scale_space(n: int = SYNTH_N) -> ScaleSpaceResult:
    """Figs. 3.3 and 3.5 and a numerical check of corollary 1 on the step-edge signal."""
    f = step_edge_signal(n)
    t = uniform_lattice(n)
    warp = arclength_warp(t, f)
    scales = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]
    extrema: dict[str, list[int]] = {"linear": [], "warped": []}
    for s in scales:
        for key, wrp in (("linear", IdentityWarp()), ("warped", warp)):
            if s == 0:
                extrema[key].append(count_extrema(np.diff(f)))
                continue
            # sample uniformly on the warped axis, s / 10 apart, well past both ends
            ends = wrp.gamma(np.array([t[0], t[-1]]))
            u = np.arange(ends[0] - 6 * s - 1, ends[1] + 6 * s + 1, s / 10)
            x = wrp.alpha(u)
            extrema[key].append(count_extrema(warped_scale_space(t, f, s, wrp, x, derivative=1)))
    return ScaleSpaceResult(
        t=t,
        f=f,
        linear=linear_scale_space(t, f, SCALE_S),
        warped=warped_scale_space(t, f, SCALE_S, warp),
        dgamma=warp.dgamma(t[:-1] + 0.5),
        scales=scales,
        extrema=extrema,
    )


def non_increasing(values: Sequence[float]) -> bool:
    return all(b <= a for a, b in itertools.pairwise(values))


# ---------------------------------------------------------------------------------------------
# Spectral checks (section 4.1)


@dataclass
class SpectralChecks:
    energy_below_10: float
    energy_below_10_no_mean: float
    theorem3: list[tuple[float, float, float, float, float, float]]
    transfer_w: FloatArray
    transfer_k: FloatArray
    transfer_arc: FloatArray
    transfer_id: FloatArray
    mass_above: dict[str, float]
    c_norm: float


def run_spectral(quick: bool) -> SpectralChecks:
    """The 99.8 % energy claim, theorem 3 on the ML function, and lemma 3's transfer function.

    Frequencies are in cycles per sample spacing; the bandlimit is the samples' Nyquist, 0.5.
    """
    xd = np.linspace(-1.0, 1.0, 20001)
    fd = marschner_lobb(xd)
    dx = float(xd[1] - xd[0])
    e10 = energy_fraction_below(fd, dx, 10.0)
    e10c = energy_fraction_below(fd, dx, 10.0, remove_mean=True)
    ts, fs, _, _ = ml_data("samples")
    warp = arclength_warp(ts, fs)
    t_end = float(ts[-1])
    c_norm = length_normalising_constant(warp, 0.0, t_end)
    step = 0.02 if quick else 0.01
    f_dense = marschner_lobb(-1.0 + ML_STEP * np.arange(0.0, t_end + step / 2, step))
    warped_signals: list[FloatArray] = []
    for c in (1.0, c_norm):
        wc = normalise_bandwidth(warp, c)
        ends = wc.gamma(np.array([0.0, t_end]))
        u = np.arange(ends[0], ends[1] + step / 2, step)
        warped_signals.append(marschner_lobb(-1.0 + ML_STEP * wc.alpha(u)))
    rows = []
    for s in (0.2, 7.0 / 15.0, 0.8, 20.0 / 15.0):

        def resp(q: FloatArray, s: float = s) -> FloatArray:
            return gaussian_frequency_response(q, s)

        rows.append(
            (
                s,
                smoothing_metric(resp, 0.5),
                postaliasing_metric(resp, 0.5, 10.0),
                signal_weighted_smoothing(f_dense, step, resp, 0.5),
                signal_weighted_smoothing(warped_signals[0], step, resp, 0.5),
                signal_weighted_smoothing(warped_signals[1], step, resp, 0.5),
            )
        )
    nk = 41 if quick else 101
    wv = np.linspace(0.0, 0.5, nk)
    kv = np.linspace(0.0, 0.5, nk)
    p_arc = np.abs(warp_transfer_function(warp, wv, kv, 0.0, t_end))
    p_id = np.abs(warp_transfer_function(IdentityWarp(), wv, kv, 0.0, t_end))
    above = kv[None, :] > wv[:, None]
    mass = {
        "arclength": float((p_arc[above] ** 2).sum() / (p_arc**2).sum()),
        "identity": float((p_id[above] ** 2).sum() / (p_id**2).sum()),
    }
    return SpectralChecks(e10, e10c, rows, wv, kv, p_arc, p_id, mass, c_norm)


# ---------------------------------------------------------------------------------------------
# Noise removal (section 4.3)


@dataclass
class DenoiseResults:
    label: str
    clean: FloatArray
    study: dict[float, dict[str, FloatArray]]
    as_variance: bool
    warp_gain: float
    method_noise: dict[str, float]


def run_denoise(
    label: str,
    clean: FloatArray,
    seeds: Sequence[int],
    *,
    as_variance: bool = False,
    warp_gain: float = 1.0,
) -> DenoiseResults:
    study = method_noise_study(
        clean, NOISE_LEVELS, DENOISE_SIGMA, seeds, as_variance=as_variance, warp_gain=warp_gain
    )
    mn = method_noise_only(clean, DENOISE_SIGMA, warp_gain=warp_gain)
    return DenoiseResults(label, clean, study, as_variance, warp_gain, mn)


def gamma_prime_pair(clean: FloatArray, level: float, seed: int) -> tuple[FloatArray, FloatArray]:
    """Per-segment ``gamma'`` of the arclength warp of a noisy realisation and of the clean signal.

    Uses the same noise draw as seed ``seed`` of the denoising study.
    """
    noisy = clean + np.random.default_rng(seed).normal(0.0, level, clean.size)
    t = uniform_lattice(clean.size)
    mid = t[:-1] + 0.5
    return arclength_warp(t, noisy).dgamma(mid), arclength_warp(t, clean).dgamma(mid)


@dataclass(frozen=True)
class GammaStats:
    """How the arclength ``gamma'`` of noisy realisations compares with the clean signal's."""

    share_over: float  # share of segments where the noisy gamma' exceeds the ground truth
    mean_excess: float
    mean_noisy: float
    mean_truth: float


def gamma_stats(clean: FloatArray, level: float, seeds: Sequence[int]) -> GammaStats:
    pairs = [gamma_prime_pair(clean, level, s) for s in seeds]
    noisy = np.concatenate([n for n, _ in pairs])
    truth = np.concatenate([g for _, g in pairs])
    diff = noisy - truth
    return GammaStats(
        float(np.mean(diff > 0)), float(np.mean(diff)), float(noisy.mean()), float(truth.mean())
    )


@dataclass
class DenoiseStudy:
    synthetic: DenoiseResults
    real: DenoiseResults
    variants: list[DenoiseResults]
    gamma: dict[str, dict[float, GammaStats]]


def run_denoise_study(row: FloatArray, seeds: Sequence[int]) -> DenoiseStudy:
    """Tables 4.3-4.5 (primary convention) and the variants, with the same seeds throughout."""
    synth_clean = step_edge_signal(SYNTH_N)
    synthetic = run_denoise("synthetic", synth_clean, seeds)
    real = run_denoise("real", row, seeds)
    variants = [
        run_denoise("synthetic", synth_clean, seeds, as_variance=True),
        run_denoise("real", row, seeds, as_variance=True),
        run_denoise("synthetic, amplitude 1", step_edge_signal(SYNTH_N, 1.0), seeds),
        run_denoise("real, warp from grey levels 0-255", row, seeds, warp_gain=GRAY_LEVELS),
    ]
    gamma = {
        "synthetic": {lv: gamma_stats(synth_clean, lv, seeds) for lv in NOISE_LEVELS},
        "real": {lv: gamma_stats(row, lv, seeds) for lv in NOISE_LEVELS},
    }
    return DenoiseStudy(synthetic, real, variants, gamma)


# ---------------------------------------------------------------------------------------------


@dataclass
class AllResults:
    scale: ScaleSpaceResult
    recon: ReconstructionStudy
    spectral: SpectralChecks
    denoise: DenoiseStudy
    seeds: int
    quick: bool
    elapsed: float = 0.0
    figures: list[str] = field(default_factory=list)


def run_all(seeds: int, quick: bool) -> AllResults:
    """Run every experiment (no plotting)."""
    row = camera_scanline(CAMERA_ROW)
    return AllResults(
        scale=run_scale_space(),
        recon=run_reconstruction_study(row),
        spectral=run_spectral(quick),
        denoise=run_denoise_study(row, list(range(seeds))),
        seeds=seeds,
        quick=quick,
    )
