"""One image rendered across several devices of a host (sort-first).

Every device holds all positions, builds its own grid and casts the rays of one horizontal band
of the image (`Renderer.render(..., tile=...)`); the bands are gathered into one image. A band's
rays are computed with the whole image's arithmetic, so the gathered image equals the image one
device would render, bit for bit. Bands are balanced by the last frame's cost: each device gets
rows in proportion to the rows per millisecond it managed, so a band over the molecule and a band
over the background take about as long.

On CUDA devices a frame is issued from one thread without waiting in between. The positions go
to every device at once from one page-locked host buffer, each device copying on its own stream;
with `upload="split"` (the default where every pair of devices has peer access) each copies
only 1/N of the atoms from the host and the rest from the other devices over their peer links,
so the host's memory bandwidth is shared by 1/N of the bytes. Every device's render is then
queued in turn, and each band is copied into one page-locked host image as its device finishes.
Queueing from one thread is cheap once a frame set-up repeats and each device replays its graph
(0.1-0.7 ms per device at 1M-10M atoms on H200s); a host thread per device was measured slower
(6-9 ms to queue, the threads contending for the interpreter). The host never holds a device while
another waits, and no copy runs through a pageable bounce buffer. Band edges move in whole row
quanta, so a balanced frame set-up repeats and each device replays its captured graph. CPU
devices (which stand in for GPUs in tests) render their bands one after another on the calling
thread.

A device that fails is dropped with an error in the log; its band goes to the others from then
on, and the frame is rendered again without it.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
import warp

from protocol import Camera, RenderParams, Topology
from server.render.errors import RenderError
from server.render.renderer import Renderer

wp: Any = warp  # warp's host API is unannotated: calls through it are dynamic
log = logging.getLogger("scalesteer.render")

MIN_ROWS = 4
"""A band is at least one row of 8x4 tiles."""
ROW_QUANTUM = 8
"""Band edges fall on multiples of this many rows (two rows of 8x4 tiles): balancing moves them
in steps, so a frame set-up repeats and each device replays its captured graph of it."""
UNEVEN = 1.05
"""Bands are balanced again only when the slowest device's work exceeds the mean by this
factor."""
STAGING = 2
"""Page-locked positions buffers a CUDA multi-device renderer writes frames into in turn."""


def split_rows(height: int, cuts: Sequence[float]) -> list[tuple[int, int]]:
    """(y0, rows) of contiguous bands between the fractions `cuts` of the image height (one
    fewer than the devices), each edge on a multiple of `ROW_QUANTUM` rows where the image is
    tall enough and each band at least `MIN_ROWS` rows (or what is left)."""
    quantum = ROW_QUANTUM if height >= ROW_QUANTUM * (len(cuts) + 1) else 1
    bands: list[tuple[int, int]] = []
    y = 0
    for i in range(len(cuts) + 1):
        left = height - y
        last = i == len(cuts)
        edge = round(cuts[i] * height / quantum) * quantum if not last else height
        rows = left if last else min(left, max(MIN_ROWS, edge - y))
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


def split_atoms(n: int, devices: int) -> list[tuple[int, int]]:
    """Contiguous atom ranges [a, b), one per device, covering all `n` atoms (the part of a
    frame each device uploads from the host)."""
    edges = [n * k // devices for k in range(devices + 1)]
    return list(itertools.pairwise(edges))


def enable_peer_access(devices: Sequence[str]) -> bool:
    """Let every pair of distinct CUDA devices read each other's memory, pooled allocations
    (warp's default allocator) included; False where a pair cannot (copies between them would
    be staged through host memory, slower than uploading from the host)."""
    distinct = sorted(set(devices))
    for a in distinct:
        for b in distinct:
            if a == b:
                continue
            if not wp.is_peer_access_supported(a, b):
                return False
            wp.set_peer_access_enabled(a, b, True)
            if wp.is_mempool_enabled(a):
                if not wp.is_mempool_access_supported(a, b):
                    return False
                wp.set_mempool_access_enabled(a, b, True)
    return True


def _pinned(count: int, dtype: Any) -> tuple[Any, npt.NDArray[Any]]:
    """A page-locked host array (warp's allocation, portable to every device of the host) and
    its numpy view."""
    owner = wp.empty(max(count, 1), dtype=dtype, device="cpu", pinned=True)
    return owner, owner.numpy()


def _address(a: npt.NDArray[Any]) -> int:
    return int(a.__array_interface__["data"][0])


class MultiRenderer:
    """The `Renderer` interface over several devices; the image is split in bands."""

    def __init__(self, devices: Sequence[str], *, upload: str = "split", **options: Any) -> None:
        """`options` are the `Renderer`'s (max_atoms, max_pixels, tuning), for every device.
        `upload` (CUDA devices): "split" (each device uploads 1/N of a frame and takes the
        rest from the others, device to device, where every pair has peer access), or "whole"
        (every device uploads all of it: the control the benchmark measures against)."""
        if len(devices) < 2:
            raise ValueError("a multi-device renderer needs at least two devices")
        if upload not in ("split", "whole"):
            raise ValueError(f"upload must be 'split' or 'whole', not {upload!r}")
        self.renderers = [Renderer(device=d, **options) for d in devices]
        for r in self.renderers:
            r.cull_to_tile = True  # each device's grid holds the atoms its band reaches
        self.devices = [r.device for r in self.renderers]
        self.labels = [
            d if self.devices.count(d) == 1 else f"{d}#{i}" for i, d in enumerate(self.devices)
        ]
        """Unique names of the devices (two CPU devices stand in for two GPUs in tests)."""
        n = len(self.renderers)
        self.cuts = [k / n for k in range(1, n)]
        """Where the bands meet, as fractions of the height (balanced frame by frame)."""
        self.cuda = all(d.startswith("cuda") for d in self.devices)
        """Every device is a CUDA device: bands are queued on each and run at once. CPU devices
        run their bands one after another on the calling thread: warp's CPU kernels keep state in
        statics of their JIT-compiled code, and two threads running them at once crash."""
        peers = not self.cuda or enable_peer_access(self.devices)
        self.split_upload = upload == "split" and peers
        """Each device uploads 1/N of a frame from the host, and copies the rest from the
        other devices (NVLink or PCIe peer copies), instead of N uploads of all of it."""
        self._staging: list[tuple[Any, npt.NDArray[np.float32]]] = []
        self._next_staging = 0
        self._n = 0
        self._host_image: tuple[Any, npt.NDArray[np.uint32]] | None = None
        self._bands: list[tuple[int, int]] = []
        self._size: tuple[int, int] | None = None
        self._params: RenderParams | None = None
        self._pending: Any = None
        self.timings: dict[str, float] = {}
        self.device_ms: dict[str, float] = {}
        self.issue_ms: list[float] = []
        """Host time each device's render took to queue in the last frame."""

    @property
    def device(self) -> str:
        return ",".join(self.devices)

    def _all(self, method: str, *args: Any, **kwargs: Any) -> None:
        for r in self.renderers:
            getattr(r, method)(*args, **kwargs)

    def set_topology(self, topology: Topology) -> None:
        self._all("set_topology", topology)
        n = int(topology.n_atoms)
        if self.cuda and n != self._n:
            self._staging = [_pinned(n, wp.vec3) for _ in range(STAGING)]
            self._staging = [(o, v.view(np.float32).reshape(-1, 3)[:n]) for o, v in self._staging]
        self._n = n

    def host_positions(self) -> npt.NDArray[np.float32]:
        """A (n, 3) float32 page-locked host buffer (CUDA devices): a frame written here and
        passed to `set_positions` goes to every device without a host copy. Ask again for every
        frame (the buffers alternate)."""
        if not self._staging:
            return np.empty((self._n, 3), dtype=np.float32)
        return self._staging[self._next_staging][1]

    def _staged(self, positions: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
        """`positions` in page-locked memory: one of the staging buffers as it is, anything else
        copied into the next one (one host copy instead of a pageable upload per device)."""
        arr = np.asarray(positions)
        for i, (_owner, view) in enumerate(self._staging):
            if _address(view) == _address(arr) and arr.shape == view.shape:
                self._next_staging = (i + 1) % len(self._staging)
                return view
        view = self._staging[self._next_staging][1]
        self._next_staging = (self._next_staging + 1) % len(self._staging)
        np.copyto(view, arr, casting="same_kind")
        return view

    def set_positions(
        self,
        positions: npt.ArrayLike,
        *,
        check_finite: bool = True,
        staged: npt.NDArray[np.float32] | None = None,
    ) -> None:
        """Positions for the next render on every device; the first device checks them.
        `staged`: the same positions already in page-locked memory."""
        first, rest = self.renderers[0], self.renderers[1:]
        if not self.cuda and not self.split_upload:
            first.set_positions(positions, check_finite=check_finite)
            for r in rest:
                r.set_positions(positions, check_finite=False)
            return
        # the checks (shape, dtype, finite) before a host copy is made of a bad frame
        arr = np.asarray(positions)
        if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] != self._n:
            first.set_positions(arr, check_finite=check_finite)  # raises the renderer's error
        if check_finite and self._n and not np.isfinite(arr).all():
            first.set_positions(arr, check_finite=True)  # raises the renderer's error
        src = arr if not self.cuda else staged if staged is not None else self._staged(arr)
        if not self.split_upload or not self._n:
            for r in self.renderers:
                r.set_positions(src, check_finite=False)
            return
        parts = split_atoms(self._n, len(self.renderers))
        for r, part in zip(self.renderers, parts, strict=True):
            r.set_positions(src, check_finite=False, part=part)
        owners = list(zip(self.renderers, parts, strict=True))
        for r in self.renderers:
            r.receive([(o, a, b) for o, (a, b) in owners if o is not r])

    def set_history(self, *args: Any, **kwargs: Any) -> None:
        self._all("set_history", *args, **kwargs)

    def _queue(
        self, params: RenderParams, camera: Camera, w: int, h: int, bands: list[tuple[int, int]]
    ) -> list[BaseException | None]:
        """Queue every band's render (`wait=False`) in turn, timing each; the error each device
        raised (None where it queued)."""
        pairs = list(zip(self.renderers, bands, strict=False))
        errors: list[BaseException | None] = [None] * len(pairs)
        self.issue_ms = [0.0] * len(pairs)
        for i, (r, (y0, rows)) in enumerate(pairs):
            t0 = time.perf_counter()
            try:
                r.render(params, camera, w, h, (0, y0, w, rows), wait=False)
            except Exception as exc:  # a device's failure, judged by the caller
                errors[i] = exc
            self.issue_ms[i] = (time.perf_counter() - t0) * 1e3
        return errors

    def _issue(
        self, params: RenderParams, camera: Camera, w: int, h: int, bands: list[tuple[int, int]]
    ) -> list[BaseException | None]:
        """Render every band; the error each device raised (None where it rendered)."""
        pairs = list(zip(self.renderers, bands, strict=False))
        errors = self._queue(params, camera, w, h, bands)
        for i, (r, _band) in enumerate(pairs):
            if errors[i] is None:
                try:
                    r.finish()
                except Exception as exc:
                    errors[i] = exc
        return errors

    def render(
        self,
        params: RenderParams,
        camera: Camera,
        width: int,
        height: int,
        *,
        wait: bool = True,
    ) -> None:
        """Render the image across the devices. `wait=False` (CUDA devices) returns once every
        device's band is queued: positions set meanwhile upload while the bands render, and
        `finish` (or reading an output) waits for them."""
        self.finish()
        t0 = time.perf_counter()
        w, h = int(width), int(height)
        if self.cuda and not wait and len(self.renderers) > 1:
            bands = split_rows(h, self.cuts)
            pairs = list(zip(self.renderers, bands, strict=False))
            if any(e is not None for e in self._queue(params, camera, w, h, bands)):
                for r, _band in pairs:  # a device's failure: the blocking path judges it
                    with contextlib.suppress(Exception):
                        r.finish()
            else:
                self._pending = (params, w, h, bands, t0, camera)
                return
        self._render_blocking(params, camera, w, h, t0)

    def finish(self) -> None:
        """Wait for a render queued with `wait=False`; a device that failed in it is dropped
        and the image rendered again on the others."""
        pending = self._pending
        if pending is None:
            return
        self._pending = None
        params, w, h, bands, t0, camera = pending
        errors: list[BaseException | None] = []
        for r in self.renderers[: len(bands)]:
            try:
                r.finish()
                errors.append(None)
            except Exception as exc:  # judged by the blocking path
                errors.append(exc)
        if any(e is not None for e in errors):
            self._render_blocking(params, camera, w, h, t0)
            return
        self._after(params, w, h, bands, t0)

    def _render_blocking(
        self, params: RenderParams, camera: Camera, w: int, h: int, t0: float
    ) -> None:
        while True:
            if len(self.cuts) != len(self.renderers) - 1:  # a device was dropped
                n = len(self.renderers)
                self.cuts = [k / n for k in range(1, n)]
            bands = split_rows(h, self.cuts)
            errors = self._issue(params, camera, w, h, bands)
            failed = [i for i, e in enumerate(errors) if e is not None]
            if not failed:
                break
            for i in reversed(failed):
                exc = errors[i]
                assert exc is not None
                if isinstance(exc, RenderError):
                    raise exc  # bad input: the same on every device
                if len(self.renderers) == 1:
                    raise RuntimeError(f"the last render device failed: {exc}") from exc
                log.error("render device %s failed (%s); going on without it", self.devices[i], exc)
                del self.renderers[i], self.devices[i], self.labels[i]
                self.cuda = all(d.startswith("cuda") for d in self.devices)
        self._after(params, w, h, bands[: len(errors)], t0)

    def _after(
        self,
        params: RenderParams,
        w: int,
        h: int,
        bands: list[tuple[int, int]],
        t0: float,
    ) -> None:
        """A finished frame's bands, balance and timings."""
        self._bands = bands
        self._size = (w, h)
        self._params = params
        used = self.renderers[: len(bands)]
        times = [max(r.timings.get("total", 0.0), 1e-3) for r in used]
        if len(bands) == len(self.renderers) > 1:
            # the devices' own work (their totals also hold the wait for the host to queue
            # them), halfway to the balanced cuts: a frame's noise does not swing the bands;
            # they move only when the slowest device is more than `UNEVEN` over the mean and
            # by more than a row quantum, so set-ups repeat and graphs replay (a band that
            # moves every frame launches eagerly, at a host cost per device)
            work = [
                max(r.timings.get("grid", 0.0) + r.timings.get("raycast", 0.0), 1e-3) for r in used
            ]
            uneven = max(work) > UNEVEN * (sum(work) / len(work))
            target = balance(self._bands, work, h, len(self.renderers))
            cuts = [0.5 * (a + b) for a, b in zip(self.cuts, target, strict=True)]
            moved = max(abs(a - b) * h for a, b in zip(cuts, self.cuts, strict=True))
            if uneven and moved > ROW_QUANTUM:
                self.cuts = cuts
        self.device_ms = dict(zip(self.labels, times, strict=False))
        self.timings = {
            "upload": max(r.timings.get("upload", 0.0) for r in used),
            "grid": max(r.timings.get("grid", 0.0) for r in used),
            "raycast": max(r.timings.get("raycast", 0.0) for r in used),
            "total": (time.perf_counter() - t0) * 1e3,
            **{f"device:{d}": t for d, t in self.device_ms.items()},
            **{f"issue:{d}": t for d, t in zip(self.labels, self.issue_ms, strict=False)},
        }

    @property
    def pipelined(self) -> bool:
        """Positions set while a render is queued upload during it (CUDA devices that keep two
        positions buffers each)."""
        return self.cuda and all(r.pipelined for r in self.renderers)

    def _gather(self, read: str) -> Any:
        self.finish()
        if self._size is None:
            raise RenderError("nothing rendered yet")
        parts = [getattr(r, read)() for r in self.renderers[: len(self._bands)]]
        return np.concatenate(parts, axis=0)

    def _gather_rgba(self, dest: Any) -> None:
        """Each band copied from its device into its rows of `dest` (a host warp array of w * h
        uint32), every device's copy queued before any is waited for."""
        w, _h = self._need_size()
        used = list(zip(self.renderers, self._bands, strict=False))
        for r, (y0, rows) in used:
            src = r.device_outputs()[0]
            wp.copy(dest, src, dest_offset=y0 * w, count=w * rows, stream=wp.get_stream(r.device))
        for r, _band in used:
            wp.synchronize_stream(wp.get_stream(r.device))

    def _need_size(self) -> tuple[int, int]:
        self.finish()
        if self._size is None:
            raise RenderError("nothing rendered yet")
        return self._size

    def read_rgba(self) -> npt.NDArray[np.uint8]:
        if not self.cuda:
            out: npt.NDArray[np.uint8] = self._gather("read_rgba")
            return out
        w, h = self._need_size()
        held = self._host_image
        if held is None or held[1].size < w * h:
            held = self._host_image = _pinned(w * h, wp.uint32)
        self._gather_rgba(held[0])
        image: npt.NDArray[np.uint8] = held[1][: w * h].copy().view(np.uint8).reshape(h, w, 4)
        return image

    def read_rgba_into(self, out: npt.NDArray[np.uint8]) -> None:
        """The image into `out` ((height, width, 4) uint8, C-contiguous), each device copying
        its band straight into its rows (page-locked `out`: no host copy at all)."""
        w, h = self._need_size()
        if out.shape != (h, w, 4) or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise RenderError(f"read_rgba_into needs a C-contiguous ({h}, {w}, 4) uint8 array")
        if not self.cuda:
            out[...] = self.read_rgba()
            return
        flat = out.reshape(-1).view(np.uint32)
        self._gather_rgba(wp.array(flat, dtype=wp.uint32, device="cpu", copy=False))

    def read_depth(self) -> npt.NDArray[np.float32]:
        out: npt.NDArray[np.float32] = self._gather("read_depth")
        return out

    def read_atom_ids(self) -> npt.NDArray[np.int32]:
        out: npt.NDArray[np.int32] = self._gather("read_atom_ids")
        return out

    def pick(self, x: int, y: int) -> tuple[int | None, float | None]:
        self.finish()
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
        """The histogram over the whole grid box: the first device builds a grid of every atom
        for it (its band's next frame culls again)."""
        self.finish()
        first = self.renderers[0]
        if self._params is None:
            raise RenderError("render once before asking for a histogram")
        first.prepare(self._params)
        return first.density_histogram(*args, **kwargs)

    def memory_bytes(self) -> dict[str, int]:
        return self.renderers[0].memory_bytes()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.finish()
