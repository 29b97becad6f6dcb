"""warp-lang kernels behind :mod:`timewarp.batched` (imported only from there, lazily).

Kernel annotations use warp's array types, which are not Python types, hence the mypy pragma.
"""

# mypy: ignore-errors

from __future__ import annotations

import warp as wp


@wp.kernel
def arclength_kernel(
    signals: wp.array3d(dtype=wp.float32),
    dt: wp.float32,
    use_signal: wp.int32,
    gamma: wp.array2d(dtype=wp.float32),
):
    """One thread per signal: ``gamma_i = sum_k sqrt(dt^2 + |f_k - f_{k-1}|^2)`` (eq. 3.4)."""
    b = wp.tid()
    n = signals.shape[1]
    ncomp = signals.shape[2]
    acc = wp.float32(0.0)
    gamma[b, 0] = acc
    for i in range(1, n):
        d2 = dt * dt
        if use_signal != 0:
            for c in range(ncomp):
                df = signals[b, i, c] - signals[b, i - 1, c]
                d2 = d2 + df * df
        acc = acc + wp.sqrt(d2)
        gamma[b, i] = acc


@wp.kernel
def warped_smooth_kernel(
    signals: wp.array3d(dtype=wp.float32),
    gamma: wp.array2d(dtype=wp.float32),
    inv_two_sigma2: wp.float32,
    cutoff: wp.float32,
    out: wp.array3d(dtype=wp.float32),
):
    """One thread per (signal, frame, component): normalised Gaussian in warped distance.

    ``gamma`` is increasing, so walking outwards from the frame itself and stopping at the
    first sample beyond ``cutoff`` visits exactly the samples within the truncation radius.
    """
    b, i, c = wp.tid()
    n = signals.shape[1]
    gi = gamma[b, i]
    wsum = wp.float32(1.0)
    acc = signals[b, i, c]
    j = i - 1
    while j >= 0:
        d = gi - gamma[b, j]
        if d > cutoff:
            break
        w = wp.exp(-d * d * inv_two_sigma2)
        wsum = wsum + w
        acc = acc + w * signals[b, j, c]
        j = j - 1
    j = i + 1
    while j < n:
        d = gamma[b, j] - gi
        if d > cutoff:
            break
        w = wp.exp(-d * d * inv_two_sigma2)
        wsum = wsum + w
        acc = acc + w * signals[b, j, c]
        j = j + 1
    out[b, i, c] = acc / wsum
