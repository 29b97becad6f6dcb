"""Figures of the reproduction (matplotlib, imported on first use with the Agg backend)."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import numpy as np

from thesis.experiments import (
    CAMERA_ROW,
    DENOISE_SIGMA,
    SCALE_S,
    AllResults,
    DenoiseResults,
    DenoiseSpectra,
    LocalSpectra,
    Reconstruction,
    ScaleSpaceResult,
    SpectralChecks,
    gamma_prime_pair,
)
from timewarp._types import FloatArray, uniform_lattice
from timewarp.denoise import denoise_trial
from timewarp.reconstruction import classical_reconstruction, warped_reconstruction

__all__ = ["make_figures"]

COLORS = {"truth": "#d4a017", "classical": "tab:red", "warped": "tab:green", "signal": "tab:blue"}


def _plt() -> Any:
    mpl: Any = importlib.import_module("matplotlib")
    mpl.use("Agg")
    return importlib.import_module("matplotlib.pyplot")


def _save(fig: Any, out: Path, name: str, dpi: int) -> str:
    fig.tight_layout()
    fig.savefig(out / name, dpi=dpi)
    _plt().close(fig)
    return name


def _save_as_is(fig: Any, out: Path, name: str, dpi: int) -> str:
    """Save a figure that arranges itself (colour bars beside several panels)."""
    fig.savefig(out / name, dpi=dpi)
    _plt().close(fig)
    return name


def fig_scale_space(res: ScaleSpaceResult, out: Path, dpi: int) -> list[str]:
    """Fig. 3.3 (signal, linear and warped scale space at s = 2) and fig. 3.5 (gamma')."""
    plt = _plt()
    fig, ax = plt.subplots(3, 1, figsize=(7, 6.5), sharex=True)
    ax[0].plot(res.t, res.f, color=COLORS["signal"])
    ax[0].set_title("(a) original signal")
    ax[1].plot(res.t, res.f, color=COLORS["signal"], alpha=0.35)
    ax[1].plot(res.t, res.linear, color=COLORS["classical"])
    ax[1].set_title(f"(b) linear scale space, s = {SCALE_S}")
    ax[2].plot(res.t, res.f, color=COLORS["signal"], alpha=0.35)
    ax[2].plot(res.t, res.warped, color=COLORS["warped"])
    ax[2].set_title(f"(c) arclength-warped scale space, s = {SCALE_S}")
    ax[2].set_xlabel("t (samples)")
    names = [_save(fig, out, "fig3_3_scale_space.png", dpi)]
    fig, ax = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
    ax[0].plot(res.t, res.f, color=COLORS["signal"])
    ax[0].set_title("signal")
    ax[1].step(res.t[:-1] + 0.5, res.dgamma, where="mid", color="k")
    ax[1].set_title("gamma'(t) of the arclength warp")
    ax[1].set_xlabel("t (samples)")
    names.append(_save(fig, out, "fig3_5_gamma_prime.png", dpi))
    return names


def fig_reconstruction(
    rec: Reconstruction,
    out: Path,
    dpi: int,
    tag: str,
    names: tuple[str, str],
    at: list[float],
) -> list[str]:
    """Figs. 4.2/4.3 (error against sigma) and 4.4/4.5 (reconstructions at two sigmas)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(rec.sigmas, rec.classical, "o-", color="tab:blue", label="classical")
    ax.plot(rec.sigmas, rec.warped, "s-", color="tab:green", label="warped")
    ax.set_xlabel("sigma (sample spacings)")
    ax.set_ylabel("total absolute error")
    ax.set_title(f"{tag}: reconstruction error")
    ax.legend()
    out_names = [_save(fig, out, names[0], dpi)]
    fig, axs = plt.subplots(len(at), 1, figsize=(7, 2.8 * len(at)), sharex=True)
    axs = np.atleast_1d(axs)
    for a, s in zip(axs, at, strict=True):
        c = classical_reconstruction(rec.t_samples, rec.f_samples, rec.t_lattice, s)
        w = warped_reconstruction(rec.t_samples, rec.f_samples, rec.t_lattice, s, rec.warp)
        a.plot(rec.t_lattice, rec.truth, color=COLORS["truth"], lw=2.5, label="ground truth")
        a.plot(rec.t_lattice, c, color=COLORS["classical"], label="classical")
        a.plot(rec.t_lattice, w, color=COLORS["warped"], label="warped")
        a.plot(rec.t_samples, rec.f_samples, "k.", ms=3, label="samples")
        a.set_title(f"{tag}: reconstruction at sigma = {s:.5f}")
        a.legend(fontsize=7, loc="upper right")
    axs[-1].set_xlabel("t (sample spacings)")
    out_names.append(_save(fig, out, names[1], dpi))
    return out_names


def fig_real_data(out: Path, dpi: int) -> str:
    """Fig. 4.1: the photograph with the scanline marked, and the scanline."""
    plt = _plt()
    data: Any = importlib.import_module("skimage.data")
    img = np.asarray(data.camera(), dtype=np.float64) / 255.0
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6), gridspec_kw={"width_ratios": [1, 1.6]})
    ax[0].imshow(img, cmap="gray")
    ax[0].axhline(CAMERA_ROW, color="tab:red", lw=1)
    ax[0].set_title("(a) scikit-image 'camera'")
    ax[0].axis("off")
    ax[1].plot(img[CAMERA_ROW], color="k", lw=0.8)
    ax[1].set_title(f"(b) row {CAMERA_ROW}, ground truth")
    ax[1].set_xlabel("pixel")
    return _save(fig, out, "fig4_1_real_data.png", dpi)


def fig_denoise(res: DenoiseResults, level: float, out: Path, dpi: int, name: str) -> str:
    """Figs. 4.6/4.7: noisy signal, classical and warped (noisy warp) filtering, overlay."""
    plt = _plt()
    trial = denoise_trial(res.clean, level, DENOISE_SIGMA, np.random.default_rng(0))
    x = uniform_lattice(res.clean.size)
    fig, ax = plt.subplots(4, 1, figsize=(7, 8), sharex=True)
    ax[0].plot(x, trial.noisy, color="0.4", lw=0.6)
    ax[0].set_title(f"(a) noisy signal, noise std {level}")
    panels = (
        (ax[1], "classical", COLORS["classical"], "(b) classical Gaussian filter"),
        (ax[2], "noisy_warp", COLORS["warped"], "(c) time-warped filter (noisy warp)"),
    )
    for a, key, color, title in panels:
        a.plot(x, res.clean, color=COLORS["truth"], lw=2)
        a.plot(x, trial.filtered[key], color=color)
        a.set_title(f"{title}, sigma = {DENOISE_SIGMA}")
    ax[3].plot(x, res.clean, color=COLORS["truth"], lw=2, label="ground truth")
    ax[3].plot(x, trial.filtered["classical"], color=COLORS["classical"], label="classical")
    ax[3].plot(x, trial.filtered["noisy_warp"], color=COLORS["warped"], label="warped")
    ax[3].set_title("(d) overlay")
    ax[3].legend(fontsize=7)
    ax[3].set_xlabel("t (samples)")
    return _save(fig, out, name, dpi)


def fig_gamma_prime(clean: FloatArray, level: float, out: Path, dpi: int) -> list[str]:
    """Figs. 4.9 and 4.10: gamma' from the noisy signal vs the ground truth, and their gap."""
    plt = _plt()
    noisy, gt = gamma_prime_pair(clean, level, 0)
    mid = uniform_lattice(clean.size - 1) + 0.5
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(mid, noisy, color="tab:blue", lw=0.8, label="gamma' from the noisy signal")
    ax.plot(mid, gt, color="tab:green", lw=0.8, label="ground truth gamma'")
    ax.set_title(f"real data, noise std {level}")
    ax.set_xlabel("pixel")
    ax.legend(fontsize=7)
    names = [_save(fig, out, "fig4_9_gamma_prime_noisy.png", dpi)]
    fig, ax = plt.subplots(figsize=(7, 3.0))
    ax.plot(mid, noisy - gt, color="k", lw=0.8)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_title("p = gamma'(t) - gamma'_gt(t)")
    ax.set_xlabel("pixel")
    names.append(_save(fig, out, "fig4_10_gamma_prime_difference.png", dpi))
    return names


def fig_high_noise(clean: FloatArray, level: float, out: Path, dpi: int) -> str:
    """Fig. 4.11: real data at a high noise level, classical vs warped filtering."""
    plt = _plt()
    trial = denoise_trial(clean, level, DENOISE_SIGMA, np.random.default_rng(0))
    x = uniform_lattice(clean.size)
    fig, ax = plt.subplots(figsize=(7, 3.4))
    ax.plot(x, clean, color=COLORS["truth"], lw=2, label="ground truth")
    ax.plot(x, trial.filtered["classical"], color="tab:blue", lw=1, label="classical")
    ax.plot(x, trial.filtered["noisy_warp"], color="tab:green", lw=1, label="warped (noisy warp)")
    ax.set_title(f"real data, noise std {level}, sigma = {DENOISE_SIGMA}")
    ax.set_xlabel("pixel")
    ax.legend(fontsize=7)
    return _save(fig, out, "fig4_11_high_noise.png", dpi)


def fig_transfer(sp: SpectralChecks, out: Path, dpi: int) -> str:
    """|P_gamma(w, k)| for the identity and the ML arclength warp (lemma 3)."""
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(9, 4))
    ext = (sp.transfer_k[0], sp.transfer_k[-1], sp.transfer_w[0], sp.transfer_w[-1])
    for a, p, title in (
        (ax[0], sp.transfer_id, "identity warp"),
        (ax[1], sp.transfer_arc, "arclength warp of the ML samples"),
    ):
        a.imshow(p, origin="lower", extent=ext, aspect="auto", cmap="magma")
        a.plot([0, 0.5], [0, 0.5], color="w", lw=0.7, ls="--")
        a.set_xlabel("k (cycles per warped unit)")
        a.set_ylabel("w (cycles per sample)")
        a.set_title(f"|P_gamma(w, k)|, {title}", fontsize=9)
    return _save(fig, out, "fig_transfer_function.png", dpi)


DB_RANGE = 60.0  # dynamic range shown in the short-time spectra


def _db(mag: FloatArray) -> FloatArray:
    return np.asarray(20.0 * np.log10(mag + 1e-12), dtype=np.float64)


def _spectrogram(ax: Any, mag: FloatArray, k: FloatArray, top: float, cutoff: float) -> Any:
    """One short-time spectrum, time across and frequency up, on a shared dB scale."""
    n = mag.shape[0]
    ext = (-0.5, n - 0.5, float(k[0]), float(k[-1]))
    im = ax.imshow(
        _db(mag).T, origin="lower", extent=ext, aspect="auto", cmap="magma",
        vmin=top - DB_RANGE, vmax=top,
    )  # fmt: skip
    ax.axhline(cutoff, color="w", lw=0.7, ls="--")
    ax.set_ylabel("cycles / sample")
    return im


def fig_local_spectra(loc: LocalSpectra, out: Path, dpi: int) -> list[str]:
    """Figs. 3.2/3.4 (short-time spectra of the signal and both filters) and 3.5b (difference)."""
    plt = _plt()
    top = float(_db(loc.original).max())
    fig, ax = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    panels = (
        (loc.original, "(a) original signal"),
        (loc.classical, f"(b) linear (classical) filter, s = {SCALE_S}"),
        (loc.warped, f"(c) arclength-warped filter, s = {SCALE_S}"),
    )
    for a, (mag, title) in zip(ax, panels, strict=True):
        im = _spectrogram(a, mag, loc.k, top, loc.cutoff)
        a.set_title(f"{title}: |STFT|, Hann window of {2 * (loc.k.size - 1)} samples", fontsize=9)
    ax[-1].set_xlabel("t (samples)")
    fig.colorbar(im, ax=list(ax), shrink=0.6, label="dB")
    fig.set_layout_engine("constrained")
    names = [_save_as_is(fig, out, "fig3_2_local_spectra.png", dpi)]
    fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    ax[0].step(loc.t[:-1] + 0.5, loc.dgamma, where="mid", color="k")
    ax[0].set_title("(a) gamma'(t) of the arclength warp")
    diff = loc.warped - loc.classical
    lim = float(np.abs(diff).max())
    ext = (-0.5, diff.shape[0] - 0.5, float(loc.k[0]), float(loc.k[-1]))
    im = ax[1].imshow(
        diff.T, origin="lower", extent=ext, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim
    )
    ax[1].axhline(loc.cutoff, color="k", lw=0.7, ls="--")
    ax[1].set_title(
        "(b) |STFT| of the warped minus |STFT| of the linear filtered signal", fontsize=9
    )
    ax[1].set_ylabel("cycles / sample")
    ax[1].set_xlabel("t (samples)")
    fig.colorbar(im, ax=list(ax), shrink=0.6, label="magnitude difference")
    fig.set_layout_engine("constrained")
    names.append(_save_as_is(fig, out, "fig3_5b_spectra_difference.png", dpi))
    return names


def fig_denoise_spectra(sp: DenoiseSpectra, out: Path, dpi: int) -> str:
    """Fig. 4.8: short-time spectra of the clean, noisy, classical and warped denoised signal."""
    plt = _plt()
    top = float(_db(sp.spectra["clean"]).max())
    fig, ax = plt.subplots(4, 1, figsize=(7, 8.5), sharex=True)
    panels = (
        ("clean", "(a) original signal"),
        ("noisy", f"(b) noisy signal, noise std {sp.level}"),
        ("classical", f"(c) classical filter, sigma = {DENOISE_SIGMA}"),
        ("noisy_warp", f"(d) time-warped filter (noisy warp), sigma = {DENOISE_SIGMA}"),
    )
    for a, (key, title) in zip(ax, panels, strict=True):
        im = _spectrogram(a, sp.spectra[key], sp.k, top, sp.cutoff)
        a.set_title(title, fontsize=9)
    ax[-1].set_xlabel("pixel")
    fig.colorbar(im, ax=list(ax), shrink=0.5, label="|STFT| (dB)")
    fig.set_layout_engine("constrained")
    return _save_as_is(fig, out, "fig4_8_denoising_spectrograms.png", dpi)


def make_figures(r: AllResults, out: Path, dpi: int) -> list[str]:
    """Write every figure into ``out``; returns their file names."""
    names = fig_scale_space(r.scale, out, dpi)
    names += fig_reconstruction(
        r.recon.ml,
        out,
        dpi,
        "ML",
        ("fig4_2_ml_error.png", "fig4_4_ml_reconstruction.png"),
        [0.2, 7.0 / 15.0],
    )
    names.append(fig_real_data(out, dpi))
    names += fig_reconstruction(
        r.recon.real,
        out,
        dpi,
        "real",
        ("fig4_3_real_error.png", "fig4_5_real_reconstruction.png"),
        [2.0 / 15.0, 0.4],
    )
    names.append(fig_denoise(r.denoise.synthetic, 0.3, out, dpi, "fig4_6_synthetic_denoising.png"))
    names.append(fig_denoise(r.denoise.real, 0.3, out, dpi, "fig4_7_real_denoising.png"))
    names += fig_gamma_prime(r.denoise.real.clean, 0.3, out, dpi)
    names.append(fig_high_noise(r.denoise.real.clean, 0.9, out, dpi))
    names.append(fig_transfer(r.spectral, out, dpi))
    names += fig_local_spectra(r.local, out, dpi)
    names.append(fig_denoise_spectra(r.denoise.spectra["real"], out, dpi))
    return names
