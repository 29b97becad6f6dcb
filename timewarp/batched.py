"""Batched time-warped Gaussian smoothing in warp-lang, for streaming trajectories.

Smooths many signals at once over a window of frames, e.g. every atom's coordinates: each
signal of shape ``(frames, components)`` gets its own arclength warp (the arclength of the curve
``(t, x(t), y(t), z(t))`` for a 3-vector), and is filtered with a normalised Gaussian of
standard deviation ``sigma`` in warped distance, evaluated at its own frames. It computes the
same as :func:`timewarp.convolution.warped_convolve` (float32 on the device instead of
float64). warp-lang is imported on first use only, so ``import timewarp`` never needs it.
"""

from __future__ import annotations

import importlib
from typing import Any, Literal

import numpy as np

from ._types import FloatArray

__all__ = ["BatchedWarpedSmoother", "default_device", "warped_smooth_batched"]

Mode = Literal["arclength", "identity"]


def _warp() -> Any:
    """Import and initialise warp-lang once, without its start-up banner."""
    wp: Any = importlib.import_module("warp")
    if not getattr(_warp, "_done", False):
        setattr(wp.config, "quiet", True)  # noqa: B010 - older releases
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = max(int(wp.config.log_level), int(wp.LOG_WARNING))
        wp.init()
        _warp._done = True  # type: ignore[attr-defined]
    return wp


def default_device() -> str:
    """``"cuda"`` when a CUDA device is present, else ``"cpu"``."""
    wp = _warp()
    return "cuda" if wp.is_cuda_available() else "cpu"


class BatchedWarpedSmoother:
    """Owns the device buffers for ``n_signals`` signals of ``n_frames`` frames and reuses them.

    Call it once per window; nothing is allocated per call, as the renderer's buffers are.
    """

    def __init__(
        self,
        n_signals: int,
        n_frames: int,
        n_components: int = 1,
        device: str | None = None,
    ) -> None:
        if min(n_signals, n_frames, n_components) < 1:
            raise ValueError("n_signals, n_frames and n_components must be positive")
        wp = _warp()
        from . import _wp_kernels

        self._kernels = _wp_kernels
        self.device = device or default_device()
        self.shape = (n_signals, n_frames, n_components)
        self._signals = wp.zeros(self.shape, dtype=wp.float32, device=self.device)
        self._out = wp.zeros(self.shape, dtype=wp.float32, device=self.device)
        self._gamma = wp.zeros((n_signals, n_frames), dtype=wp.float32, device=self.device)

    def __call__(
        self,
        signals: np.ndarray,
        sigma: float,
        *,
        dt: float = 1.0,
        truncate: float = 8.0,
        mode: Mode = "arclength",
    ) -> FloatArray:
        """Smooth ``signals`` (``(n_signals, n_frames)`` or ``(n_signals, n_frames, comps)``).

        ``mode="identity"`` gives classical Gaussian smoothing over frames. Samples farther than
        ``truncate * sigma`` (in warped distance) are ignored; with the default 8 every
        ignored weight is below ``exp(-32)`` of the frame's own weight.
        """
        wp = _warp()
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError("sigma must be positive and finite")
        if not truncate > 0:
            raise ValueError("truncate must be positive")
        if mode not in ("arclength", "identity"):
            raise ValueError(f"unknown mode {mode!r}")
        arr = np.asarray(signals, dtype=np.float32)
        squeeze = arr.ndim == 2
        if squeeze:
            arr = arr[:, :, None]
        if arr.shape != self.shape:
            raise ValueError(f"expected shape {self.shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError("signals must be finite")
        self._signals.assign(arr)
        k = self._kernels
        wp.launch(
            k.arclength_kernel,
            dim=self.shape[0],
            inputs=[self._signals, float(dt), 1 if mode == "arclength" else 0],
            outputs=[self._gamma],
            device=self.device,
        )
        wp.launch(
            k.warped_smooth_kernel,
            dim=self.shape,
            inputs=[
                self._signals,
                self._gamma,
                float(0.5 / (sigma * sigma)),
                float(truncate * sigma),
            ],
            outputs=[self._out],
            device=self.device,
        )
        out = np.asarray(self._out.numpy(), dtype=np.float64)
        return out[:, :, 0] if squeeze else out


def warped_smooth_batched(
    signals: np.ndarray,
    sigma: float,
    *,
    dt: float = 1.0,
    truncate: float = 8.0,
    mode: Mode = "arclength",
    device: str | None = None,
) -> FloatArray:
    """One-shot :class:`BatchedWarpedSmoother` call (allocates buffers for this shape)."""
    arr = np.asarray(signals)
    if arr.ndim not in (2, 3):
        raise ValueError("signals must have shape (n_signals, n_frames[, n_components])")
    comps = 1 if arr.ndim == 2 else arr.shape[2]
    smoother = BatchedWarpedSmoother(arr.shape[0], arr.shape[1], comps, device)
    return smoother(arr, sigma, dt=dt, truncate=truncate, mode=mode)
