"""The trajectory frames a temporal filter sees when a render reads them from a file: one
window per output frame, the same for a job rendered here and for its chunks on Ray."""

from __future__ import annotations

from collections.abc import Callable

import protocol as p


def time_window(params: p.RenderParams, n_frames: int) -> Callable[[int], tuple[int, int]] | None:
    """For temporal smoothing: the trajectory frames around output frame `i` its filter
    sees (the causal kernel: the window before it; otherwise centred on it, as the file holds
    the future too), or None without smoothing."""
    if not params.needs_history():
        return None
    w = params.time_window
    if params.time_kernel == "causal":
        return lambda i: (max(0, i - w + 1), i)
    half = (w - 1) // 2
    return lambda i: (max(0, i - half), min(n_frames - 1, i + half))
