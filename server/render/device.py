"""warp-lang initialisation (once, quietly) and device selection."""

from __future__ import annotations

import itertools
import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from pathlib import Path
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
    are split across (warp's CPU device runs a launch on the thread that makes it). A cgroup's
    CPU quota (a container's `--cpus`) bounds the cores the affinity mask lists."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):
        pass  # no cgroup v2 quota here
    return cores


RUNS_PER_HOST_THREAD = 4
"""Runs a split launch is cut into per host thread: the work is uneven (rays through the
molecule against rays past it, bricks at its core against its edge), and a thread that is done
takes the next run."""

LAUNCH_POOL = "cpu-launch"
"""The name its threads' names begin with: the pool lives with the process (its idle threads
end with it)."""


def run_cuts(count: int, threads: int) -> list[tuple[int, int]]:
    """[first, last) of each run `count` items are cut into for `threads` host threads
    (RUNS_PER_HOST_THREAD a thread, at most one an item, one at least)."""
    runs = max(min(threads * RUNS_PER_HOST_THREAD, count), 1)
    cuts = [count * j // runs for j in range(runs + 1)]
    return list(itertools.pairwise(cuts))


_POOLS: dict[int, ThreadPoolExecutor] = {}
_LOADED: dict[tuple[int, str, int | None], Any] = {}
"""Kernels launched on a device with a block size (compiled and loaded there), held so that
their ids stay theirs."""
_POOLS_LOCK = threading.Lock()


def split_launch(
    kernel: Any,
    runs: Sequence[tuple[int, Sequence[Any]]],
    device: str,
    threads: int,
    block_dim: int | None = None,
) -> None:
    """`kernel` launched for each (threads, inputs) of `runs`, launches on the CPU device that
    write apart: on a pool of `threads` host threads (made once per process) once the kernel
    has been loaded on `device` with this block size, else one after the other on this thread
    (the first compiles and loads it: two threads must not). Returns once every run has ended,
    raising the first error."""
    key = (id(kernel), str(device), block_dim)
    with _POOLS_LOCK:
        loaded = key in _LOADED
        pool = _POOLS.get(threads)
        if pool is None and threads > 1 and loaded:
            pool = ThreadPoolExecutor(threads, thread_name_prefix=LAUNCH_POOL)
            _POOLS[threads] = pool
    if pool is None or len(runs) < 2:
        for dim, inputs in runs:
            wp.launch(kernel, dim, inputs, device=device, block_dim=block_dim)
        with _POOLS_LOCK:
            _LOADED[key] = kernel
        return
    futures = [
        pool.submit(wp.launch, kernel, dim, inputs, device=device, block_dim=block_dim)
        for dim, inputs in runs
    ]
    wait(futures)  # every run ends before an error is raised: they write the caller's buffers
    for future in futures:
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
