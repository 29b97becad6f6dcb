"""warp-lang initialisation (once, quietly) and device selection."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

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


def host_threads() -> int:
    """The cores this process may run on: the host threads the CPU device's heaviest launches
    are split across (warp's CPU device runs a launch on the thread that makes it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


RUNS_PER_HOST_THREAD = 4
"""Runs a split launch is cut into per host thread: the work is uneven (rays through the
molecule against rays past it, bricks at its core against its edge), and a thread that is done
takes the next run."""

_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def on_host_threads(threads: int, runs: Iterable[Callable[[], None]]) -> None:
    """Each of `runs` (launches on the CPU device that write apart) on a pool of `threads` host
    threads, made once per process; returns when all are done, raising the first error."""
    with _POOLS_LOCK:
        pool = _POOLS.get(threads)
        if pool is None:
            pool = ThreadPoolExecutor(threads, thread_name_prefix="cpu-launch")
            _POOLS[threads] = pool
    for future in [pool.submit(run) for run in runs]:
        future.result()


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


def resolve_many(spec: str) -> tuple[str, ...]:
    """`--gpus`: 'all' (every CUDA device), CUDA indices '0,1', or device names ('cpu,cpu'
    stands two CPU devices in for two GPUs, for tests and for the CPU's cores)."""
    init()
    if spec.strip() == "all":
        n = cuda_count()
        if n == 0:
            raise RenderError("--gpus all: no CUDA device is available")
        return tuple(f"cuda:{i}" for i in range(n))
    names = [part.strip() for part in spec.split(",") if part.strip()]
    if not names:
        raise RenderError(f"--gpus {spec!r}: name at least one device")
    out = []
    for name in names:
        device = f"cuda:{name}" if name.isdigit() else name
        if device.startswith("cuda:") and int(device[5:]) >= cuda_count():
            raise RenderError(f"--gpus: {device} does not exist ({cuda_count()} CUDA devices)")
        out.append(resolve(device))
    return tuple(out)


_KERNELS: dict[tuple[Callable[..., None], bool, int], Any] = {}
_KERNELS_LOCK = threading.Lock()  # each device's thread may make its first renderer at once


def compiled(fn: Callable[..., None], fast_math: bool, registers: int = 0) -> Any:
    """`fn` as a kernel compiled with CUDA's approximate transcendentals or not and a register
    cap (0: the compiler's), made once per process for each choice. For the kernels whose cost
    is square roots, divisions and exponentials: each precise form is a sequence of
    instructions where the approximate one is a single instruction. (warp's CPU build takes
    neither option: on the CPU device both choices compile the same code.)"""
    key = (fn, bool(fast_math), max(int(registers), 0))
    with _KERNELS_LOCK:
        kernel = _KERNELS.get(key)
        if kernel is None:
            make: Any = wp.kernel  # warp's decorator is unannotated
            kernel = make(
                fn,
                enable_backward=False,
                module="unique",
                module_options={"fast_math": key[1]},
                cuda_max_registers=key[2] or None,
            )
            _KERNELS[key] = kernel
    return kernel


init()
