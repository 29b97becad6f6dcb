"""The GPU queue: one thread owns the device, and every render — live sessions and batch jobs —
runs on it in submission order.

Work arrives as `RenderRequest`s naming a *slot*: each slot (a session, a job, a one-off REST
render) keeps its own Renderer, so its topology and buffers stay resident between requests. A
request carries a `Snapshot` (topology and positions with the ids that tell whether the slot's
copies are current), so a slot uploads what changed and nothing else.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.staging import FrameStager
from server.threads import name_thread

STAGE_ATOMS = 100_000
"""Frames of at least this many atoms are copied to page-locked memory as they arrive."""
STAGE_WAIT_S = 0.005
"""Longest a render waits for its frame's staged copy to finish (a 12 MB copy takes 2-3 ms)
before uploading from the frame itself."""

if TYPE_CHECKING:
    from server.render import Renderer
    from server.render.layerplan import LayerPlan
    from server.render.layers import LayeredRenderer
    from server.render.multi import MultiRenderer

T = TypeVar("T")
log = logging.getLogger("scalesteer.gpu")


@dataclass(frozen=True)
class Snapshot:
    """The molecule one render draws: a topology and one simulation frame's positions.

    `topology_id` and `positions_id` change whenever their arrays do (the GPU slot compares them
    with what it holds); `step` is the simulation step of the positions; `version` counts every
    change to what a session would draw (positions or render parameters)."""

    topology: p.Topology
    positions: npt.NDArray[np.float32]
    topology_id: int = 1
    positions_id: int = 1
    step: int = 0
    version: int = 0
    history: tuple[tuple[int, npt.NDArray[np.float32]], ...] = ()
    """Recent frames (positions_id, positions), oldest first, for temporal smoothing."""
    history_epoch: int = 0
    """Changes when the history starts again (a replay seeked)."""
    live: bool = True
    """A live simulation (the causal kernel by default), not a replay."""
    lag: int | None = None
    """Frames between the shown frame and the newest of `history` (None: the kernel's own)."""


@dataclass(frozen=True)
class RenderRequest:
    """One image of `snapshot` for the renderer of `slot`; `histogram` also measures the
    density histogram (for the transfer-function editor)."""

    slot: str
    snapshot: Snapshot
    params: p.RenderParams
    camera: p.Camera
    width: int
    height: int
    histogram: bool = False
    layers: tuple[LayerPlan, ...] | None = None
    """The visible layers, their selections evaluated (None: every atom, drawn the single way
    `params` says)."""
    video_size: tuple[int, int] | None = None
    """A video stream encodes this image at this size: on a CUDA device the image also comes
    back as I420 planes at that size (`RenderOutput.i420`), converted and scaled there."""
    rgba: bool = True
    """False: only video viewers take this image, so when its I420 planes come back the RGBA
    image is not read back (`RenderOutput.rgba` is then None)."""


@dataclass
class RenderOutput:
    rgba: npt.NDArray[np.uint8] | None
    """(h, w, 4) RGBA; None only when the request said it needs none and planes came back."""
    timings: dict[str, float]
    histogram: npt.NDArray[np.float32] | None = None
    i420: npt.NDArray[np.uint8] | None = None
    """The image at the request's `video_size` as I420 planes (CUDA devices only)."""

    def image(self) -> npt.NDArray[np.uint8]:
        """The RGBA image, which every request has unless it said `rgba=False`."""
        if self.rgba is None:
            raise RuntimeError("this render was asked for video planes only")
        return self.rgba


@dataclass
class _Slot:
    renderer: Renderer | MultiRenderer
    topology_id: int = -1
    positions_id: int = -1
    layered: LayeredRenderer | None = None
    one_cuda: bool = False
    """One CUDA device draws it (not several, not the CPU)."""
    stageable: bool = False
    """`one_cuda` and its last request had no layers: its new frames are staged."""
    stager: FrameStager | None = None
    """Its page-locked frames (made on the stage thread; gone with the slot)."""


@dataclass
class GpuQueue:
    """Serialises device work on one thread; methods named `*_sync` run on that thread."""

    device: str = "auto"
    devices: tuple[str, ...] = ()
    """Several devices: each session's images are rendered across them (sort-first)."""
    max_atoms: int = 4_000_000
    max_pixels: int = 3840 * 2160
    _pool: ThreadPoolExecutor = field(
        default_factory=lambda: ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="gpu", initializer=name_thread
        )
    )
    _slots: dict[str, _Slot] = field(default_factory=dict)
    actual_device: str = ""
    stage_atoms: int = STAGE_ATOMS
    """Frames of at least this many atoms are staged in page-locked memory as they arrive."""
    _stage_pool: ThreadPoolExecutor = field(
        default_factory=lambda: ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="stage", initializer=name_thread
        )
    )

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    async def render(self, request: RenderRequest) -> RenderOutput:
        return await self.call(self.render_sync, request)

    async def pick(
        self, request: RenderRequest, x: int, y: int
    ) -> tuple[int | None, float | None, str | None]:
        """The atom, depth and layer name at pixel (x, y) of the image `request` draws."""
        return await self.call(self.pick_sync, request, x, y)

    async def release(self, slot: str) -> None:
        await self.call(self.release_sync, slot)

    def stage(self, slot: str, positions_id: int, positions: npt.NDArray[np.float32]) -> None:
        """A new frame for `slot` arrived (called on the event loop): copy it into page-locked
        memory on the stage thread, so that its render uploads it without holding the device
        thread (`server.pipeline.staging`). Only frames of `stage_atoms` or more for a slot
        that one CUDA device draws without layers; any other frame uploads as before."""
        target = self._slots.get(slot)
        n = len(positions)
        if target is None or not target.stageable or n < self.stage_atoms:
            return
        stager = target.stager
        if stager is not None and stager.n == n:
            stager.offer(positions_id, positions)
            return
        with contextlib.suppress(RuntimeError):  # the queue is closing: nothing to stage
            self._stage_pool.submit(self._new_stager, target, positions_id, positions)

    def _new_stager(
        self, slot: _Slot, positions_id: int, positions: npt.NDArray[np.float32]
    ) -> None:
        """(On the stage thread.) Buffers for `slot`'s frames, then the frame that asked. A
        slot released meanwhile takes its buffers with it."""
        stager = slot.stager
        if stager is None or stager.n != len(positions):
            try:
                stager = slot.stager = FrameStager(len(positions), self._stage_pool)
            except Exception:  # no page-locked memory to be had: frames upload as before
                log.exception("could not page-lock staging buffers for %d atoms", len(positions))
                return
        stager.offer(positions_id, positions)

    def _slot(self, key: str) -> _Slot:
        slot = self._slots.get(key)
        if slot is None:
            from server.render import Renderer

            renderer: Renderer | MultiRenderer
            if len(self.devices) > 1 and key.startswith("session:"):
                from server.render.multi import MultiRenderer

                renderer = MultiRenderer(
                    self.devices, max_atoms=self.max_atoms, max_pixels=self.max_pixels
                )
            else:
                device = self.devices[0] if self.devices else self.device
                renderer = Renderer(
                    device=device, max_atoms=self.max_atoms, max_pixels=self.max_pixels
                )
            self.actual_device = renderer.device
            one_cuda = renderer.device.startswith("cuda") and len(self.devices) <= 1
            slot = self._slots[key] = _Slot(renderer, one_cuda=one_cuda)
        return slot

    def _prepare(
        self, request: RenderRequest, held: list[tuple[FrameStager, Any]]
    ) -> Renderer | MultiRenderer | LayeredRenderer:
        """Bring the slot up to `request`'s snapshot and render it. A staged copy the upload
        reads from goes into `held`, to be released once the device is done with it."""
        slot = self._slot(request.slot)
        snap = request.snapshot
        slot.stageable = slot.one_cuda and request.layers is None
        if request.layers is not None:
            slot.stager = None  # layers upload their own subsets
            return self._prepare_layers(slot, request)
        if slot.topology_id != snap.topology_id:
            slot.renderer.set_topology(snap.topology)
            slot.topology_id = snap.topology_id
            slot.positions_id = -1
        if slot.positions_id != snap.positions_id:
            # frames were checked finite when decoded; skip the host-side scan
            stager = slot.stager
            staged = None
            if stager is not None and stager.n == len(snap.positions):
                staged = stager.take(snap.positions_id, STAGE_WAIT_S)
            if stager is None or staged is None:
                slot.renderer.set_positions(snap.positions, check_finite=False)
            else:  # only a slot one CUDA device draws (a `Renderer`) has a stager
                held.append((stager, staged))
                one = cast("Renderer", slot.renderer)
                one.set_positions(snap.positions, check_finite=False, staged=staged)
            slot.positions_id = snap.positions_id
        renderer = slot.renderer
        if snap.history:
            renderer.set_history(
                snap.history, snap.history_epoch, request.params, live=snap.live, lag=snap.lag
            )
        renderer.render(request.params, request.camera, request.width, request.height)
        return renderer

    def _prepare_layers(self, slot: _Slot, request: RenderRequest) -> LayeredRenderer:
        """Draw `request`'s layers, each with a renderer of its own on the slot's device."""
        assert request.layers is not None
        if slot.layered is None:
            from server.render import Renderer
            from server.render.layers import LayeredRenderer

            device = self.devices[0] if self.devices else self.device
            slot.layered = LayeredRenderer(
                lambda: Renderer(
                    device=device, max_atoms=self.max_atoms, max_pixels=self.max_pixels
                )
            )
        snap = request.snapshot
        slot.layered.render(
            request.layers,
            snap.topology,
            snap.topology_id,
            snap.positions,
            snap.positions_id,
            request.camera,
            request.width,
            request.height,
            history=snap.history,
            history_epoch=snap.history_epoch,
            live=snap.live,
            lag=snap.lag,
            background=request.params.background,
        )
        return slot.layered

    def render_sync(self, request: RenderRequest) -> RenderOutput:
        with self._staged() as held:
            renderer = self._prepare(request, held)
            hist = None
            if request.histogram:
                counts, _edges = renderer.density_histogram(64)
                hist = np.asarray(counts, dtype=np.float32)
            i420 = None
            read_i420 = getattr(renderer, "read_i420", None)  # a multi-device render has none
            if request.video_size is not None and read_i420 is not None and self._on_cuda():
                try:
                    i420 = read_i420(request.video_size)
                except Exception:  # the encoder converts the RGBA image itself: slower
                    log.exception("converting a video frame on %s failed", self.actual_device)
            rgba = renderer.read_rgba() if request.rgba or i420 is None else None
            return RenderOutput(rgba, dict(renderer.timings), hist, i420)

    @contextlib.contextmanager
    def _staged(self) -> Iterator[list[tuple[FrameStager, Any]]]:
        """The staged buffers a render uploads from, given back once the device has read them:
        a render's read-back waits for its upload; after a failure, the device is waited for
        here."""
        held: list[tuple[FrameStager, Any]] = []
        try:
            yield held
        except BaseException:
            if held:
                import warp as wp

                with contextlib.suppress(Exception):
                    wp.synchronize_device(self.actual_device)
            raise
        finally:
            for stager, array in held:
                stager.release(array)

    def _on_cuda(self) -> bool:
        """On the CPU device swscale converts faster than a kernel there: no I420 then."""
        return self.actual_device.startswith("cuda")

    def pick_sync(
        self, request: RenderRequest, x: int, y: int
    ) -> tuple[int | None, float | None, str | None]:
        if request.layers is not None:
            return self._prepare_layers(self._slot(request.slot), request).pick_layer(x, y)
        with self._staged() as held:
            atom, depth = self._prepare(request, held).pick(x, y)
        return atom, depth, None

    def release_sync(self, slot: str) -> None:
        self._slots.pop(slot, None)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._stage_pool.shutdown(wait=True, cancel_futures=True)
        self._slots.clear()
