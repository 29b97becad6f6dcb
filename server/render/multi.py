"""One image rendered across several devices of a host (sort-first).

Every device holds all positions, builds its own grid and casts the rays of one horizontal band
of the image (`Renderer.render(..., tile=...)`); the bands are gathered into one image. A band's
rays are computed with the whole image's arithmetic, so the gathered image equals the image one
device would render, bit for bit. Bands are balanced by the last frame's cost: each device gets
rows in proportion to the rows per millisecond it managed, so a band over the molecule and a band
over the background take about as long.

Sort-last (each device a slab of atoms, images composited by depth) would need every device to
cast every ray through its slab and a compositing pass over partial densities: for an iso-surface
of a density summed over all atoms, the slabs' densities add before the level is tested, so each
sample needs every slab's value, which sort-first avoids. It wins only when one device cannot
hold all positions and a grid (beyond about 60M atoms per 80 GB at 64 bytes per atom plus
positions and images), the regime where the grid build, not the ray cast, is the frame.

A device that fails is dropped with an error in the log; its band goes to the others from then
on, and the frame is rendered again without it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Camera, RenderParams, Topology
from server.render.errors import RenderError
from server.render.renderer import Renderer

log = logging.getLogger("scalesteer.render")

MIN_ROWS = 4
"""A band is at least one row of 8x4 tiles."""


def split_rows(height: int, cuts: Sequence[float]) -> list[tuple[int, int]]:
    """(y0, rows) of contiguous bands between the fractions `cuts` of the image height (one
    fewer than the devices), each at least `MIN_ROWS` rows (or what is left)."""
    bands: list[tuple[int, int]] = []
    y = 0
    for i in range(len(cuts) + 1):
        left = height - y
        last = i == len(cuts)
        rows = left if last else min(left, max(MIN_ROWS, round(cuts[i] * height) - y))
        bands.append((y, rows))
        y += rows
    return [(y0, rows) for y0, rows in bands if rows > 0]


def balance(
    bands: Sequence[tuple[int, int]], times: Sequence[float], height: int, devices: int
) -> list[float]:
    """Cuts (fractions of the height) that give every device the same cost, from the last
    frame's cost per row of each band (rows over the molecule cost more than background)."""
    edges = [0.0]
    cost = [0.0]
    for (y0, rows), t in zip(bands, times, strict=True):
        edges.append(float(y0 + rows))
        cost.append(cost[-1] + max(t, 1e-6))
    total = cost[-1]
    cuts = []
    for k in range(1, devices):
        target = total * k / devices
        cuts.append(float(np.interp(target, cost, edges)) / height)
    return cuts


class MultiRenderer:
    """The `Renderer` interface over several devices; the image is split in bands."""

    def __init__(self, devices: Sequence[str], **options: Any) -> None:
        if len(devices) < 2:
            raise ValueError("a multi-device renderer needs at least two devices")
        self.renderers = [Renderer(device=d, **options) for d in devices]
        self.devices = [r.device for r in self.renderers]
        self.labels = [
            d if self.devices.count(d) == 1 else f"{d}#{i}" for i, d in enumerate(self.devices)
        ]
        """Unique names of the devices (two CPU devices stand in for two GPUs in tests)."""
        n = len(self.renderers)
        self.cuts = [k / n for k in range(1, n)]
        """Where the bands meet, as fractions of the height (balanced frame by frame)."""
        # one thread per device; a CUDA device named twice (one GPU standing in for two) is
        # driven from one thread, as graph capture on a device must not race another thread
        cuda_twice = len({d for d in self.devices if d.startswith("cuda")}) < sum(
            d.startswith("cuda") for d in self.devices
        )
        workers = 1 if cuda_twice else len(self.renderers)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="device")
        self._bands: list[tuple[int, int]] = []
        self._size: tuple[int, int] | None = None
        self.timings: dict[str, float] = {}
        self.device_ms: dict[str, float] = {}

    @property
    def device(self) -> str:
        return ",".join(self.devices)

    def _all(self, method: str, *args: Any, **kwargs: Any) -> None:
        for r in self.renderers:
            getattr(r, method)(*args, **kwargs)

    def set_topology(self, topology: Topology) -> None:
        self._all("set_topology", topology)

    def set_positions(self, positions: npt.ArrayLike, *, check_finite: bool = True) -> None:
        self._all("set_positions", positions, check_finite=check_finite)

    def set_history(self, *args: Any, **kwargs: Any) -> None:
        self._all("set_history", *args, **kwargs)

    def render(self, params: RenderParams, camera: Camera, width: int, height: int) -> None:
        t0 = time.perf_counter()
        while True:
            if len(self.cuts) != len(self.renderers) - 1:  # a device was dropped
                n = len(self.renderers)
                self.cuts = [k / n for k in range(1, n)]
            bands = split_rows(int(height), self.cuts)
            jobs = [
                self._pool.submit(
                    r.render, params, camera, width, height, (0, y0, int(width), rows)
                )
                for r, (y0, rows) in zip(self.renderers, bands, strict=False)
            ]
            failed = [i for i, j in enumerate(jobs) if j.exception() is not None]
            if not failed:
                break
            for i in reversed(failed):
                exc = jobs[i].exception()
                if isinstance(exc, RenderError):
                    raise exc  # bad input: the same on every device
                if len(self.renderers) == 1:
                    raise RuntimeError(f"the last render device failed: {exc}") from exc
                log.error("render device %s failed (%s); going on without it", self.devices[i], exc)
                del self.renderers[i], self.devices[i], self.labels[i]
        self._bands = bands[: len(jobs)]
        self._size = (int(width), int(height))
        times = [max(r.timings.get("total", 0.0), 1e-3) for r in self.renderers[: len(bands)]]
        if len(bands) == len(self.renderers) > 1:
            # halfway to the balanced cuts: a frame's noise does not swing the bands
            target = balance(self._bands, times, int(height), len(self.renderers))
            self.cuts = [0.5 * (a + b) for a, b in zip(self.cuts, target, strict=True)]
        self.device_ms = dict(zip(self.labels, times, strict=False))
        used = self.renderers[: len(times)]
        self.timings = {
            "upload": max(r.timings.get("upload", 0.0) for r in used),
            "grid": max(r.timings.get("grid", 0.0) for r in used),
            "raycast": max(r.timings.get("raycast", 0.0) for r in used),
            "total": (time.perf_counter() - t0) * 1e3,
            **{f"device:{d}": t for d, t in self.device_ms.items()},
        }

    def _gather(self, read: str) -> Any:
        if self._size is None:
            raise RenderError("nothing rendered yet")
        parts = [getattr(r, read)() for r in self.renderers[: len(self._bands)]]
        return np.concatenate(parts, axis=0)

    def read_rgba(self) -> npt.NDArray[np.uint8]:
        out: npt.NDArray[np.uint8] = self._gather("read_rgba")
        return out

    def read_depth(self) -> npt.NDArray[np.float32]:
        out: npt.NDArray[np.float32] = self._gather("read_depth")
        return out

    def read_atom_ids(self) -> npt.NDArray[np.int32]:
        out: npt.NDArray[np.int32] = self._gather("read_atom_ids")
        return out

    def pick(self, x: int, y: int) -> tuple[int | None, float | None]:
        if self._size is None:
            raise RenderError("nothing rendered yet")
        w, h = self._size
        if not (0 <= int(x) < w and 0 <= int(y) < h):
            raise RenderError(f"pixel ({x}, {y}) outside the {w}x{h} image")
        for r, (y0, rows) in zip(self.renderers, self._bands, strict=False):
            if y0 <= int(y) < y0 + rows:
                return r.pick(int(x), int(y) - y0)
        return None, None

    def density_histogram(self, *args: Any, **kwargs: Any) -> Any:
        return self.renderers[0].density_histogram(*args, **kwargs)

    def memory_bytes(self) -> dict[str, int]:
        return self.renderers[0].memory_bytes()

    def close(self) -> None:
        self._pool.shutdown(wait=True)
