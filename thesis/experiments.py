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
import numpy.typing as npt

from timewarp._types import FloatArray, uniform_lattice
from timewarp.denoise import (
    METHODS,
    add_noise,
    gaussian_denoise,
    method_noise_only,
    method_noise_study,
    warped_denoise,
)
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

BoolArray = npt.NDArray[np.bool_]

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


TIE_TOL = 1e-3  # relative gap below which two errors count as a tie, not a win


@dataclass(frozen=True)
class WinRange:
    """A run of tabulated sigmas where the warped error is below the classical one.

    ``lo_cross`` / ``hi_cross`` are the linearly interpolated sign changes of the error difference
    just outside the run; ``None`` where the run reaches the end of the table.
    """

    lo: float
    hi: float
    lo_cross: float | None
    hi_cross: float | None


def _zero_between(s0: float, s1: float, d0: float, d1: float) -> float:
    """Where the line through ``(s0, d0)`` and ``(s1, d1)`` crosses zero."""
    return float(s0 + (s1 - s0) * d0 / (d0 - d1)) if d0 != d1 else float(s0)


def warped_wins(
    sigmas: FloatArray, classical: FloatArray, warped: FloatArray, rel_tol: float = TIE_TOL
) -> list[WinRange]:
    """Every run of sigmas over which warped reconstruction beats classical by more than a tie.

    "Not better at the last sigma" does not mean "never better": the warped error can dip below
    the classical one over an interior range only, so each run is reported on its own.
    """
    c, w = np.asarray(classical), np.asarray(warped)
    d = w - c
    win = d < -rel_tol * np.abs(c)
    out: list[WinRange] = []
    i, n = 0, len(win)
    while i < n:
        if not win[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and win[j + 1]:
            j += 1
        lo = None if i == 0 else _zero_between(sigmas[i - 1], sigmas[i], d[i - 1], d[i])
        hi = None if j == n - 1 else _zero_between(sigmas[j], sigmas[j + 1], d[j], d[j + 1])
        out.append(WinRange(float(sigmas[i]), float(sigmas[j]), lo, hi))
        i = j + 1
    return out


def tied_sigmas(
    sigmas: FloatArray, classical: FloatArray, warped: FloatArray, rel_tol: float = TIE_TOL
) -> FloatArray:
    """Sigmas where the two errors agree to within ``rel_tol``: neither method wins there."""
    c, w = np.asarray(classical), np.asarray(warped)
    return np.asarray(sigmas[np.abs(w - c) <= rel_tol * np.abs(c)], dtype=np.float64)


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
# Local (short-time) spectra (figs. 3.2, 3.4, 3.5b and 4.8)

STFT_WINDOW = 32  # Hann window length in samples; one window centred on every sample
EDGE_SHARE = 0.25  # an edge: gamma' - 1 at least this share of its largest value on the signal
CONCENTRATION = 10.0  # "differ much more at the peaks": edge/flat ratio of the mean difference


def short_time_spectrum(f: FloatArray, window: int = STFT_WINDOW) -> tuple[FloatArray, FloatArray]:
    """Magnitude of the short-time Fourier transform with a Hann window centred on every sample.

    Returns ``(frequencies in cycles per sample, |STFT| of shape (len(f), window // 2 + 1))``.
    The signal is extended by its end values (no spurious edges at the ends) and each frame's
    mean is removed, so the DC term does not leak into the bins the comparison is about.
    """
    half = window // 2
    padded = np.pad(np.asarray(f, dtype=np.float64), half, mode="edge")
    frames = np.lib.stride_tricks.sliding_window_view(padded, window)[: f.size]
    frames = frames - frames.mean(axis=1, keepdims=True)
    taper = np.hanning(window + 1)[:-1]
    mag = np.abs(np.fft.rfft(frames * taper, axis=1))
    freqs = np.asarray(np.fft.rfftfreq(window), dtype=np.float64)
    return freqs, np.asarray(mag, dtype=np.float64)


def half_power_frequency(sigma: float) -> float:
    """Frequency where a Gaussian of std ``sigma`` keeps half the power: the high band's floor."""
    return float(np.sqrt(np.log(2.0)) / (2.0 * np.pi * sigma))


def edge_regions(dgamma: FloatArray, window: int = STFT_WINDOW) -> tuple[BoolArray, BoolArray]:
    """Masks of samples near an edge (within a quarter window) and far from all (over half).

    Edges are the segments where ``gamma'`` peaks, so the regions follow the warp itself.
    """
    excess = dgamma - 1.0
    seg = np.flatnonzero(excess >= EDGE_SHARE * float(excess.max()))
    t = np.arange(dgamma.size + 1, dtype=np.float64)
    dist = np.min(np.abs(seg[None, :] + 0.5 - t[:, None]), axis=1)
    return dist <= window / 4, dist > window / 2


def high_band_share(spec: FloatArray, ref: FloatArray, high: BoolArray, rows: BoolArray) -> float:
    """Energy of ``spec`` above the cut-off in the windows ``rows``, as a share of ``ref``'s."""
    return float((spec[rows][:, high] ** 2).sum() / (ref[rows][:, high] ** 2).sum())


@dataclass
class LocalSpectra:
    """Short-time spectra of the step-edge signal and of both scale spaces at ``SCALE_S``."""

    t: FloatArray
    k: FloatArray
    original: FloatArray
    classical: FloatArray
    warped: FloatArray
    dgamma: FloatArray
    cutoff: float
    near: BoolArray
    flat: BoolArray
    kept: dict[str, dict[str, float]]  # region -> filter -> high-band energy share kept
    diff_near: float  # mean |warped - classical| per window near edges
    diff_flat: float  # the same away from every edge


def run_local_spectra(sc: ScaleSpaceResult) -> LocalSpectra:
    """Figs. 3.2, 3.4 and 3.5b: where the warped filter keeps the edges' high frequencies."""
    k, s_orig = short_time_spectrum(sc.f)
    _, s_lin = short_time_spectrum(sc.linear)
    _, s_war = short_time_spectrum(sc.warped)
    near, flat = edge_regions(sc.dgamma)
    cutoff = half_power_frequency(SCALE_S)
    high = k > cutoff
    kept = {
        region: {
            "classical": high_band_share(s_lin, s_orig, high, rows),
            "warped": high_band_share(s_war, s_orig, high, rows),
        }
        for region, rows in (("near", near), ("flat", flat))
    }
    diff = np.abs(s_war - s_lin).mean(axis=1)
    return LocalSpectra(
        sc.t, k, s_orig, s_lin, s_war, sc.dgamma, cutoff, near, flat, kept,
        float(diff[near].mean()), float(diff[flat].mean()),
    )  # fmt: skip


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


# sigma = 6 * 2^(k/4): a quarter-octave grid through the thesis's sigma = 6, wide enough that
# every method's best sigma lies inside it on both signals
SIGMA_SWEEP = DENOISE_SIGMA * 2.0 ** (np.arange(-14, 15) / 4.0)
SWEEP_LEVEL = 0.3


@dataclass
class SigmaSweep:
    """Mean total error (over the seeds) of each method at every sigma of ``sigmas``."""

    sigmas: FloatArray
    errors: dict[str, FloatArray]

    def best(self, method: str) -> tuple[float, float]:
        """Smallest mean error of ``method`` over the grid and the sigma it occurs at."""
        i = int(np.argmin(self.errors[method]))
        return float(self.sigmas[i]), float(self.errors[method][i])

    def at(self, method: str, sigma: float) -> float:
        """Mean error of ``method`` at the grid point ``sigma``."""
        return float(self.errors[method][int(np.argmin(np.abs(self.sigmas - sigma)))])


def _filter_all(noisy: FloatArray, sigma: float, truth_warp: Warp) -> dict[str, FloatArray]:
    """The three filters of tables 4.3-4.5 at one sigma (noisy warp estimated from ``noisy``)."""
    return {
        "classical": gaussian_denoise(noisy, sigma),
        "noisy_warp": warped_denoise(noisy, sigma),
        "ground_truth_warp": warped_denoise(noisy, sigma, truth_warp),
    }


def sigma_sweep(
    clean: FloatArray, level: float, seeds: Sequence[int], sigmas: FloatArray = SIGMA_SWEEP
) -> SigmaSweep:
    """Each method's error over a range of sigma, on the same noise draws as the study.

    Comparing the methods at one common sigma favours whichever the sigma happens to suit;
    each method at its own best sigma is the fairer comparison of what it can achieve.
    """
    t = uniform_lattice(clean.size)
    truth_warp = arclength_warp(t, clean)
    sums = {m: np.zeros(sigmas.size) for m in METHODS}
    for seed in seeds:
        noisy = add_noise(clean, level, np.random.default_rng(seed))
        for i, s in enumerate(sigmas):
            for m, v in _filter_all(noisy, float(s), truth_warp).items():
                sums[m][i] += total_absolute_error(v, clean)
    return SigmaSweep(sigmas, {m: v / len(seeds) for m, v in sums.items()})


MATCHED = "classical_matched"
"""The classical filter at the noisy warp's mean width, sigma / mean noisy `gamma'`: the control
that tells adaptation to the edges from a filter that is merely narrower everywhere."""

ADAPT_MARGIN = 0.1
"""How much better at the edges (relative) a filter must be to count as keeping the edges' local
bandwidth that another flattens: 10 % more of the clean high-band energy and a 10 % smaller
short-time spectrum error."""


@dataclass
class DenoiseSpectra:
    """Short-time spectra of one denoising trial (seed 0) and edge statistics over all seeds.

    `kept` and `error` hold each of METHODS and MATCHED, near the edges; `kept_far` and
    `error_far` the same far from every edge.
    """

    label: str
    level: float
    k: FloatArray
    spectra: dict[str, FloatArray]  # clean, noisy and each method's output, seed 0
    cutoff: float
    kept: dict[str, float]  # method -> clean high-band energy near edges kept (mean over seeds)
    error: dict[str, float]  # method -> relative short-time spectrum error near edges (mean)
    kept_far: dict[str, float]
    error_far: dict[str, float]
    matched_sigma: float  # the sigma of MATCHED

    def adapts(self, method: str, control: str) -> tuple[bool, bool]:
        """Whether `method` keeps at least ADAPT_MARGIN more of the edges' high band than
        `control`, and whether its spectrum error there is at least ADAPT_MARGIN smaller."""
        return (
            self.kept[method] >= (1.0 + ADAPT_MARGIN) * self.kept[control],
            self.error[method] <= (1.0 - ADAPT_MARGIN) * self.error[control],
        )


def run_denoise_spectra(
    label: str, clean: FloatArray, level: float, seeds: Sequence[int]
) -> DenoiseSpectra:
    """Fig. 4.8: whether warped denoising keeps the edges' local bandwidth that classical loses,
    beside the classical filter at the noisy warp's mean width."""
    t = uniform_lattice(clean.size)
    mid = t[:-1] + 0.5
    truth_warp = arclength_warp(t, clean)
    near, far = edge_regions(truth_warp.dgamma(mid))
    k, s_clean = short_time_spectrum(clean)
    cutoff = half_power_frequency(DENOISE_SIGMA)
    high = k > cutoff
    noisy_all = [add_noise(clean, level, np.random.default_rng(seed)) for seed in seeds]
    mean_gamma = float(np.mean([arclength_warp(t, v).dgamma(mid).mean() for v in noisy_all]))
    matched = DENOISE_SIGMA / mean_gamma
    names = (*METHODS, MATCHED)
    ref = {"near": float(np.linalg.norm(s_clean[near])), "far": float(np.linalg.norm(s_clean[far]))}
    kept = {r: {m: 0.0 for m in names} for r in ref}
    err = {r: {m: 0.0 for m in names} for r in ref}
    first: dict[str, FloatArray] = {}
    for i, noisy in enumerate(noisy_all):
        out = {
            **_filter_all(noisy, DENOISE_SIGMA, truth_warp),
            MATCHED: gaussian_denoise(noisy, matched),
        }
        specs = {m: short_time_spectrum(v)[1] for m, v in out.items()}
        for m, spec in specs.items():
            for region, rows in (("near", near), ("far", far)):
                kept[region][m] += high_band_share(spec, s_clean, high, rows) / len(seeds)
                diff = float(np.linalg.norm((spec - s_clean)[rows]))
                err[region][m] += diff / ref[region] / len(seeds)
        if i == 0:
            first = {"clean": s_clean, "noisy": short_time_spectrum(noisy)[1]}
            first.update({m: specs[m] for m in METHODS})
    return DenoiseSpectra(
        label, level, k, first, cutoff, kept["near"], err["near"], kept["far"], err["far"], matched
    )


@dataclass
class DenoiseStudy:
    synthetic: DenoiseResults
    real: DenoiseResults
    variants: list[DenoiseResults]
    gamma: dict[str, dict[float, GammaStats]]
    sweeps: dict[str, SigmaSweep]
    spectra: dict[str, DenoiseSpectra]


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
    sweeps = {
        "synthetic": sigma_sweep(synth_clean, SWEEP_LEVEL, seeds),
        "real": sigma_sweep(row, SWEEP_LEVEL, seeds),
    }
    spectra = {
        "synthetic": run_denoise_spectra("synthetic", synth_clean, SWEEP_LEVEL, seeds),
        "real": run_denoise_spectra("real", row, SWEEP_LEVEL, seeds),
    }
    return DenoiseStudy(synthetic, real, variants, gamma, sweeps, spectra)


# ---------------------------------------------------------------------------------------------


@dataclass
class AllResults:
    scale: ScaleSpaceResult
    recon: ReconstructionStudy
    spectral: SpectralChecks
    denoise: DenoiseStudy
    local: LocalSpectra
    seeds: int
    quick: bool
    elapsed: float = 0.0
    figures: list[str] = field(default_factory=list)


def run_all(seeds: int, quick: bool) -> AllResults:
    """Run every experiment (no plotting)."""
    row = camera_scanline(CAMERA_ROW)
    scale = run_scale_space()
    return AllResults(
        scale=scale,
        recon=run_reconstruction_study(row),
        spectral=run_spectral(quick),
        denoise=run_denoise_study(row, list(range(seeds))),
        local=run_local_spectra(scale),
        seeds=seeds,
        quick=quick,
    )
