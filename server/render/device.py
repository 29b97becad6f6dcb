"""warp-lang initialisation (once, quietly) and device selection."""

from __future__ import annotations

import warp as wp

from server.render.errors import RenderError

_initialised = False


def init() -> None:
    """Initialise warp without its start-up banner and module-load chatter."""
    global _initialised
    if not _initialised:
        wp.config.log_level = wp.LOG_WARNING
        wp.init()  # type: ignore[no-untyped-call]
        _initialised = True


def cuda_count() -> int:
    init()
    return int(wp.get_cuda_device_count())


def resolve(device: str) -> str:
    """'auto' -> the first CUDA device when there is one, else 'cpu'; others are checked."""
    init()
    if device == "auto":
        return "cuda:0" if cuda_count() > 0 else "cpu"
    if device == "cuda" and cuda_count() > 0:
        return "cuda:0"
    if device.startswith("cuda") and cuda_count() == 0:
        raise RenderError(f"device {device!r} requested but no CUDA device is available")
    try:
        return str(wp.get_device(device))
    except (RuntimeError, ValueError) as exc:
        raise RenderError(f"unknown device {device!r}: {exc}") from None


init()
