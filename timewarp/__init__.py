"""Time-warped signal processing (thesis chapters 3-4), in plain numpy.

A warp is a strictly increasing pair ``gamma`` (original time -> warped time) and its inverse
``alpha``. Warped operations evaluate classical Gaussian kernels at warped distances
``gamma(x) - gamma(t_j)``; with :class:`IdentityWarp` every one of them reduces to its classical
counterpart. The default warp is the arclength of the signal's linear interpolant (eq. 3.4).

Units: the abscissa ``t`` is whatever the caller passes (the reproduction uses sample units),
``sigma``/``s`` is a Gaussian standard deviation on the warped axis, and frequencies are in
cycles per unit of ``t``. See ``docs/timewarp.md`` for the conventions.

The warp-lang batched smoother lives in :mod:`timewarp.batched` and is not imported here,
so this package needs numpy only.
"""

from __future__ import annotations

from .convolution import convolve, gaussian, gaussian_filter, sample_weights, warped_convolve
from .denoise import (
    METHODS,
    DenoiseTrial,
    add_noise,
    denoise_trial,
    gaussian_denoise,
    method_noise_study,
    warped_denoise,
)
from .metrics import (
    energy_bandwidth,
    energy_fraction_below,
    gaussian_frequency_response,
    postaliasing_metric,
    signal_spectrum,
    signal_weighted_postaliasing,
    signal_weighted_smoothing,
    smoothing_metric,
    total_absolute_error,
    warp_transfer_function,
)
from .reconstruction import classical_reconstruction, warped_reconstruction
from .scalespace import linear_scale_space, warped_scale_space
from .signals import camera_scanline, marschner_lobb, step_edge_signal
from .warps import (
    AffineWarp,
    CallableWarp,
    IdentityWarp,
    PiecewiseLinearWarp,
    ScaledWarp,
    Warp,
    arclength,
    arclength_warp,
    length_normalising_constant,
    normalise_bandwidth,
)

__all__ = [
    "METHODS",
    "AffineWarp",
    "CallableWarp",
    "DenoiseTrial",
    "IdentityWarp",
    "PiecewiseLinearWarp",
    "ScaledWarp",
    "Warp",
    "add_noise",
    "arclength",
    "arclength_warp",
    "camera_scanline",
    "classical_reconstruction",
    "convolve",
    "denoise_trial",
    "energy_bandwidth",
    "energy_fraction_below",
    "gaussian",
    "gaussian_denoise",
    "gaussian_filter",
    "gaussian_frequency_response",
    "length_normalising_constant",
    "linear_scale_space",
    "marschner_lobb",
    "method_noise_study",
    "normalise_bandwidth",
    "postaliasing_metric",
    "sample_weights",
    "signal_spectrum",
    "signal_weighted_postaliasing",
    "signal_weighted_smoothing",
    "smoothing_metric",
    "step_edge_signal",
    "total_absolute_error",
    "warp_transfer_function",
    "warped_convolve",
    "warped_denoise",
    "warped_reconstruction",
    "warped_scale_space",
]
