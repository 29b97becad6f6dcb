"""The GPU queue: a thread owns each device, and every render — live sessions and batch jobs —
runs on its device's thread: a live session's work first, one-off renders and jobs in turn
(`server.pipeline.turns`), each slot's work in submission order.

With several devices (`--gpus`) a lone session is drawn across all of them (sort-first,
`MultiRenderer`, driven from the first device's thread, which then takes every other render too);
from the second session on, each session is placed on a device of its own (the least busy), and
jobs and one-off renders go to the least busy device. A session drawn across every device is
moved onto one, and back, as sessions come and go: the threads whose devices change are drained
first, so no two threads ever drive one device.

A live render overlaps the next frame's upload: once its launches are queued, the newest frame
already staged in page-locked memory uploads into the renderer's spare positions buffer while
the image renders, and the next request for that frame finds it on the device.

Work arrives as `RenderRequest`s naming a *slot*: each slot (a session, a job, a one-off REST
render) keeps its own Renderer, so its topology and buffers stay resident between requests. A
request carries a `Snapshot` (topology and positions with the ids that tell whether the slot's
copies are current), so a slot uploads what changed and nothing else.

Kept whole: `GpuQueue` owns the device threads and where each slot is placed on them; the upload
overlap and the moves between devices change the same state under its one lock.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeGuard, TypeVar

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.bands import BandPlan, advice_for, footprint, reach_of
from server.pipeline.staging import FrameStager, Staging
from server.pipeline.turns import TurnExecutor, rank_of
from server.render.errors import CapacityError, RenderError
from server.threads import name_thread

STAGE_ATOMS = 100_000
"""Frames of at least this many atoms are copied to page-locked memory as they arrive."""

if TYPE_CHECKING:
    from server.pipeline.encoder import DeviceJpeg
    from server.render import Renderer
    from server.render.boxes import Options, Shown
    from server.render.layerplan import LayerPlan
    from server.render.layers import LayeredRenderer
    from server.render.multi import MultiRenderer
    from server.render.periodic import PeriodicTransform
    from server.render.sortlast import SortLastRenderer
    from server.render.tuning import Tuning

T = TypeVar("T")
log = logging.getLogger("scalesteer.gpu")

CPU_KERNELS = threading.Lock()
"""Held by a lane on the CPU device while it works. Warp's CPU kernels keep state in statics of
their JIT-compiled code (its JIT has no thread-local storage), and two threads running them at
once crash the process: lanes on CPU devices (`--gpus cpu,cpu`) take turns."""


class RenderAbandonedError(RenderError):
    """A one-off render given up between its bands: its client went away."""


def _tiles(renderer: Any) -> TypeGuard[Renderer]:
    """Whether `renderer` draws a tile of an image (one device's; not one split across
    several, which splits the image itself)."""
    from server.render import Renderer

    return isinstance(renderer, Renderer)


def _serial(fn: Callable[..., T], *args: Any) -> T:
    with CPU_KERNELS:
        return fn(*args)


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
    jpeg_quality: int | None = None
    """JPEG viewers take this image at this quality: where the queue has an encoder for the
    render's device (`GpuQueue.jpeg`) the lane encodes it there and only the JPEG comes back
    (`RenderOutput.jpeg`; the RGBA image then is not read back for them)."""
    tile: tuple[int, int, int, int] | None = None
    """(x0, y0, w, h): draw only that rectangle of the image, where the slot's renderer can
    (one device: `RenderOutput.tile` says what was drawn); None: all of it."""


@dataclass(frozen=True)
class DisplayRequest:
    """One frame of `slot` to show as `options` say (molecules made whole, centred, wrapped,
    followed, fitted; `server.render.periodic`), on the device the slot renders on, which keeps
    what spans its frames (where each atom was, the fit's reference). `restart`: this frame
    does not follow the last one (a seek, new options); `reference`: the fit superposes the
    frames that follow onto this one."""

    slot: str
    topology: p.Topology
    positions: npt.NDArray[np.float32]
    box: npt.NDArray[np.float32] | None
    options: Options
    restart: bool = False
    reference: bool = False


@dataclass
class RenderOutput:
    rgba: npt.NDArray[np.uint8] | None
    """(h, w, 4) RGBA; None when the request said it needs none and planes came back, or when
    only JPEG viewers take it and its JPEG came back (`jpeg`)."""
    timings: dict[str, float]
    histogram: npt.NDArray[np.float32] | None = None
    i420: npt.NDArray[np.uint8] | None = None
    """The image at the request's `video_size` as I420 planes (CUDA devices only)."""
    jpeg: bytes | None = None
    """The image as JPEG at the request's `jpeg_quality`, encoded on its device."""
    jpeg_ms: float = 0.0
    """The time that encode took (packing the pixels included)."""
    tile: tuple[int, int, int, int] | None = None
    """The request's tile when only it was drawn (None: the whole image)."""
    seconds: float = 0.0
    """How long the render held its device's thread."""

    def image(self) -> npt.NDArray[np.uint8]:
        """The RGBA image, which every request has unless it said `rgba=False` or its JPEG
        came back instead."""
        if self.rgba is None:
            raise RuntimeError("this render brought back no RGBA image (video planes or JPEG)")
        return self.rgba


@dataclass
class _Slot:
    renderer: Renderer | MultiRenderer | SortLastRenderer
    topology_id: int = -1
    positions_id: int = -1
    layered: LayeredRenderer | None = None
    on_cuda: bool = False
    """CUDA devices draw it (one or several, not the CPU)."""
    stageable: bool = False
    """`on_cuda` and its last request had no layers: its new frames are staged."""
    stager: FrameStager | None = None
    """Its page-locked frames (made on the stage thread; gone with the slot)."""
    periodic: PeriodicTransform | None = None
    """Its frames' periodic steps (made at its first `display`)."""
    shown: npt.NDArray[np.float32] | None = None
    """The host copy of the frame `periodic` displayed last, while its device copy is on the
    renderer's device: a render of this very array copies it there device to device."""
    prefetched: tuple[FrameStager, Any] | None = None
    """A staged frame uploaded while the last render ran, released after the next render."""


@dataclass(eq=False)
class _Lane:
    """A device and the one thread that drives it."""

    device: str
    pool: TurnExecutor
    slots: set[str] = field(default_factory=set)
    busy_since: float | None = None
    """When the work now on its thread began (monotonic; None: idle)."""
    threads: list[threading.Thread] = field(default_factory=list)
    """The pool's thread once it has started (`close` joins it)."""

    @classmethod
    def start(cls, device: str, name: str) -> _Lane:
        """A lane whose one thread is named `name` (gpu_0, gpu_1, ...) for the OS too."""
        threads: list[threading.Thread] = []

        def begin() -> None:
            name_thread(name)
            threads.append(threading.current_thread())

        return cls(device, TurnExecutor(initializer=begin), threads=threads)

    def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn` on this lane's thread, its start and end noted for `busy_s`."""
        self.busy_since = time.monotonic()
        try:
            if self.device.startswith("cuda"):
                return fn(*args)
            return _serial(fn, *args)
        finally:
            self.busy_since = None


WARM_UP_SLOT = "warm-up"


def _warm_up_request() -> RenderRequest:
    """A bonded water molecule at the default parameters (its own slot, never a session's)."""
    n = 3
    topology = p.Topology(
        n_atoms=n,
        elements=["O", "H", "H"],
        names=["OW", "HW1", "HW2"],
        residue_ids=p.WireArray.from_numpy(np.ones(n, np.int32), "<i4"),
        residue_names=["SOL"] * n,
        chain_ids=["W"] * n,
        bonds=p.WireArray.from_numpy(np.array([[0, 1], [0, 2]], np.int32), "<i4"),
    )
    positions = np.array([[0.0, 0.0, 0.0], [0.96, 0.0, 0.0], [-0.24, 0.93, 0.0]], np.float32)
    camera = p.Camera(target=(0.2, 0.3, 0.0), distance=12.0)
    snapshot = Snapshot(topology, positions)
    return RenderRequest(WARM_UP_SLOT, snapshot, p.RenderParams(), camera, 64, 48)


@dataclass
class GpuQueue:
    """Device work, each device's on its own thread (`_Lane`); methods named `*_sync` run on
    the thread of the slot they serve."""

    device: str = "auto"
    devices: tuple[str, ...] = ()
    """Several devices: a lone session is drawn across them, several are placed one a device."""
    max_atoms: int = 4_000_000
    max_pixels: int = 3840 * 2160
    device_atoms: int | None = None
    """Atoms one device's renderer holds (None: `max_atoms`). With several devices, a session
    alone on them whose system is larger is split across them by space (sort-last,
    `server/render/sortlast.py`), and stays on all of them while other work comes."""
    _slots: dict[str, _Slot] = field(default_factory=dict)
    actual_device: str = ""
    stage_atoms: int = STAGE_ATOMS
    """Frames of at least this many atoms are staged in page-locked memory as they arrive."""
    staging: Staging = field(default_factory=Staging)
    """Their copy's threads and a render's wait for it (benchmarks: the control)."""
    _stage_pool: ThreadPoolExecutor = field(
        default_factory=lambda: ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="stage", initializer=name_thread
        )
    )
    tuning: Tuning | None = None
    """The renderers' tuning (benchmarks and tests; None: the defaults)."""
    prefetch: bool = True
    """Upload the newest staged frame while a live render runs (off: the baseline)."""
    warmed: bool = False
    """The warm-up render (`warm_up`) has drawn its molecule and given its slot back."""
    jpeg: DeviceJpeg | None = None
    """An encoder that reads images on the device they were rendered on: renders there that
    ask for a JPEG (`RenderRequest.jpeg_quality`) come back encoded (None: none is set, or
    it failed)."""
    _lanes: list[_Lane] = field(default_factory=list)
    _lane_of: dict[str, int] = field(default_factory=dict)
    _spread: str | None = None
    """The session drawn across every device (its work and all other work on lane 0)."""
    _whole: set[str] = field(default_factory=set)
    """Slots whose systems one device does not hold, drawn across every device by space
    (sort-last) from their thread: later work joins that thread, and a spread session among
    them is never gathered onto one device."""
    _placing: asyncio.Lock | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        names = self.devices if self.devices else (self.device,)
        self._lanes = [_Lane.start(d, f"gpu_{i}") for i, d in enumerate(names)]

    @property
    def device_name(self) -> str:
        """The device renders run on: the one the first renderer took, or before any render
        what `device` resolves to ("auto": the first CUDA device, else the CPU); `device` as
        given where it does not resolve (the first render then says why)."""
        if self.actual_device:
            return self.actual_device
        from server.render.device import resolve

        try:
            return resolve(self.device)
        except RenderError:
            return self.device

    @property
    def spread(self) -> str | None:
        """The session drawn across every device now, if one is."""
        return self._spread

    def lane_device(self, slot: str) -> str | None:
        """The device whose thread serves `slot` (None: not placed yet)."""
        lane = self._lane_of.get(slot)
        return None if lane is None else self._lanes[lane].device

    async def _run(self, lane: int, fn: Callable[..., T], *args: Any, slot: str | None = None) -> T:
        """`fn(*args)` on the lane's thread, in the turn of `slot`'s rank (None: live)."""
        on = self._lanes[lane]
        future = on.pool.submit_ranked(rank_of(slot), on.run, fn, *args)
        result: T = await asyncio.wrap_future(future)
        return result

    def busy(self) -> list[dict[str, Any]]:
        """Each device and how long the work now on its thread has run (s; 0 when idle): a
        render that holds a device for minutes shows here while the server itself answers."""
        now = time.monotonic()
        return [
            {"device": lane.device, "busy_s": 0.0 if t is None else round(now - t, 3)}
            for lane in self._lanes
            for t in (lane.busy_since,)
        ]

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run `fn` on the first device's thread."""
        return await self._run(0, fn, *args)

    async def _lane(self, slot: str) -> int:
        """The lane of `slot`, placing it (and moving a session drawn across every device onto
        one of its own when a second session comes) on its first request."""
        lane = self._lane_of.get(slot)
        if lane is not None:
            return lane
        if self._placing is None:
            self._placing = asyncio.Lock()
        async with self._placing:
            lane = self._lane_of.get(slot)
            if lane is not None:
                return lane
            with self._lock:
                whole = [self._lane_of[k] for k in self._whole if k in self._lane_of]
            if whole:
                # a system is drawn across every device (sort-last): all work goes on its
                # thread beside it, so no two threads drive one device
                return self._place(slot, whole[0])
            session = slot.startswith("session:")
            several = len(self._lanes) > 1
            if session and several and self._spread is None and not self._sessions():
                self._spread = slot
                return self._place(slot, 0)
            if self._spread is not None and session:
                await self._gather_spread()
            if self._spread is not None:  # a job or one-off render beside the lone session
                return self._place(slot, 0)
            if slot in self._whole:  # a system to split, the others moved to the first lane
                return self._place(slot, 0)
            return self._place(slot, self._least_busy())

    def _sessions(self) -> list[str]:
        return [k for k in self._lane_of if k.startswith("session:")]

    def _least_busy(self) -> int:
        return min(range(len(self._lanes)), key=lambda i: (len(self._lanes[i].slots), i))

    def _place(self, slot: str, lane: int) -> int:
        with self._lock:
            self._lane_of[slot] = lane
            self._lanes[lane].slots.add(slot)
        return lane

    async def _gather_spread(self) -> None:
        """The session drawn across every device moves onto the first device alone: its
        renderer is dropped on its thread (after any render of it) and made again there."""
        spread = self._spread
        assert spread is not None
        await self._run(0, self._drop_sync, spread, slot=spread)
        self._spread = None

    async def _spread_again(self) -> None:
        """One session left on several devices: every lane drains, and it is drawn across all
        of them again (its renderer made again on the first device's thread)."""
        sessions = self._sessions()
        if len(self._lanes) < 2 or len(sessions) != 1 or self._spread is not None:
            return
        (last,) = sessions
        others = [k for k in self._lane_of if not k.startswith("session:")]
        if others:
            return  # jobs or one-off renders still hold their devices
        for i in range(len(self._lanes)):
            await self._run(i, lambda: None)
        lane = self._lane_of[last]
        await self._run(lane, self._drop_sync, last, slot=last)
        with self._lock:
            self._lanes[lane].slots.discard(last)
            del self._lane_of[last]
        self._spread = last
        self._place(last, 0)

    async def render(self, request: RenderRequest) -> RenderOutput:
        await self._room_for(request.slot, self._whole_atoms(request))
        lane = await self._lane(request.slot)
        return await self._run(lane, self.render_sync, request, slot=request.slot)

    async def render_bands(
        self,
        request: RenderRequest,
        limit_s: float,
        gone: Callable[[], Awaitable[bool]] | None = None,
    ) -> RenderOutput:
        """A one-off image drawn in bands of rows, each its own turn on the device's thread,
        so live work goes between them; refused (`bands.TooCostlyError`) once its bands say the
        whole would take more than `limit_s` seconds of the device (`bands`), and abandoned
        (`RenderAbandonedError`) between bands once `gone()` says nobody waits for it. A slot
        drawn across several devices takes the whole image in one turn."""
        await self._room_for(request.slot, self._whole_atoms(request))
        from server.render.camera import camera_frame
        from server.render.layerplan import visible_atoms

        frame = camera_frame(request.camera, request.width, request.height)
        positions = request.snapshot.positions
        if request.layers is not None:  # hidden atoms (solvent, ions) cost nothing
            positions = positions[visible_atoms(request.layers, len(positions))]
        reach = reach_of(request.params, request.layers)
        blocks = await asyncio.to_thread(footprint, positions, frame, reach)
        plan = BandPlan(request.width, request.height, limit_s, blocks, advice_for(request.params))
        tile: tuple[int, int, int, int] | None = plan.first()
        image = np.empty((request.height, request.width, 4), dtype=np.uint8)
        timings: dict[str, float] = {}
        while tile is not None:
            if plan.bands and gone is not None and await gone():
                raise RenderAbandonedError(
                    f"abandoned after {plan.y} of its {request.height} rows: nobody waits for it"
                )
            lane = await self._lane(request.slot)
            band = dataclasses.replace(request, tile=tile)
            out = await self._run(lane, self.render_sync, band, slot=request.slot)
            if out.tile is None:  # drawn whole
                return out
            x0, y0, w, h = tile
            image[y0 : y0 + h, x0 : x0 + w] = out.image()
            for key, ms in out.timings.items():
                timings[key] = timings.get(key, 0.0) + ms
            cast = out.timings.get("raycast")
            tile = plan.drawn(tile, out.seconds, None if cast is None else cast / 1000.0)
        return RenderOutput(image, timings, seconds=plan.spent_s)

    @staticmethod
    def _whole_atoms(request: RenderRequest) -> int:
        """The atoms `request` draws on one renderer (0 for layers: each draws its own)."""
        return 0 if request.layers is not None else request.snapshot.topology.n_atoms

    async def _room_for(self, slot: str, n_atoms: int) -> None:
        """Before a system one device does not hold is drawn across every device by space:
        every other slot moves onto the first device's thread (its renderer dropped on its own
        thread after its last render, made again there at its next request), and so does this
        one (`_lane` places it), so that the system is alone on the devices' threads however
        the slots were placed (sessions nobody watches keep their slots)."""
        if n_atoms <= self.per_device or len(self._lanes) < 2 or slot in self._whole:
            return
        if self._placing is None:
            self._placing = asyncio.Lock()
        async with self._placing:
            with self._lock:
                split = [self._lane_of[k] for k in self._whole if k in self._lane_of]
                home = split[0] if split else 0
                away = [(k, lane) for k, lane in self._lane_of.items() if lane != home]
            for key, lane in away:
                await self._move(key, lane, home if key != slot else None)
            if self._spread is not None and self._spread != slot:
                await self._gather_spread()
            with self._lock:
                self._whole.add(slot)  # later slots are placed beside it from now on
            if away:
                log.info("%s: every slot moved to %s to split it", slot, self._lanes[home].device)

    async def _spread_out(self) -> None:
        """No system is split any more: sessions gathered beside one go back to devices of
        their own (least busy first; each renderer made again there at its next request)."""
        with self._lock:
            if self._whole:
                return
            crowded = [lane for lane in self._lanes if len(lane.slots) > 1]
        for lane in crowded:
            i = self._lanes.index(lane)
            for key in sorted(k for k in lane.slots if k.startswith("session:"))[1:]:
                target = self._least_busy()
                if len(self._lanes[target].slots) + 1 >= len(lane.slots):
                    break
                await self._move(key, i, target)

    async def _move(self, key: str, lane: int, to: int | None) -> None:
        """Drop `key`'s renderer on its lane's thread (after its last render) and place it on
        lane `to` (None: `_lane` places it at its next request), where it is made again."""
        await self._run(lane, self._drop_sync, key, slot=key)
        with self._lock:
            self._lanes[lane].slots.discard(key)
            self._lane_of.pop(key, None)
        if to is not None:
            self._place(key, to)

    async def warm_up(self) -> None:
        """Render a small molecule once and forget it, so the render kernels are loaded from
        warp's kernel cache before a first session's picture waits for them (about 0.7 s on
        the CPU device of a 2-core machine)."""
        drawn = False
        try:
            await self.render(_warm_up_request())
            drawn = True
        except Exception:  # the first session loads them instead; nothing else depends on it
            log.exception("the warm-up render failed")
        finally:
            await self.release(WARM_UP_SLOT)
        self.warmed = drawn

    async def pick(
        self, request: RenderRequest, x: int, y: int
    ) -> tuple[int | None, float | None, str | None]:
        """The atom, depth and layer name at pixel (x, y) of the image `request` draws."""
        await self._room_for(request.slot, self._whole_atoms(request))
        lane = await self._lane(request.slot)
        return await self._run(lane, self.pick_sync, request, x, y, slot=request.slot)

    async def release(self, slot: str) -> None:
        lane = self._lane_of.get(slot)
        if lane is None:
            return
        if self._placing is None:
            self._placing = asyncio.Lock()
        async with self._placing:
            was_split = slot in self._whole
            # in the live turn: its caller has awaited the slot's work, and a one-off render's
            # answer waits for this, not for the renders queued after its own
            await self._run(lane, self.release_sync, slot)
            with self._lock:
                self._lanes[lane].slots.discard(slot)
                self._lane_of.pop(slot, None)
            if self._spread == slot:
                self._spread = None
            self._whole.discard(slot)
            if was_split:
                await self._spread_out()
            await self._spread_again()

    async def display(self, request: DisplayRequest) -> Shown:
        """A frame as displayed (periodic steps on the slot's device, on its thread), read
        back."""
        await self._room_for(request.slot, request.topology.n_atoms)
        lane = await self._lane(request.slot)
        return await self._run(lane, self.display_sync, request, slot=request.slot)

    def stage(self, slot: str, positions_id: int, positions: npt.NDArray[np.float32]) -> None:
        """A new frame for `slot` arrived (called on the event loop): copy it into page-locked
        memory on the stage thread, so that its render uploads it without holding the device
        thread (`server.pipeline.staging`). Only frames of `stage_atoms` or more for a slot
        that one CUDA device draws without layers; any other frame uploads as before."""
        target = self._slots.get(slot)
        n = len(positions)
        if target is None or not target.stageable or n < self.stage_atoms:
            return
        if positions is target.shown:
            return  # displayed on the device already: its render copies it from there
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
                stager = slot.stager = FrameStager(
                    len(positions), self._stage_pool, policy=self.staging
                )
            except Exception:  # no page-locked memory to be had: frames upload as before
                log.exception("could not page-lock staging buffers for %d atoms", len(positions))
                return
        stager.offer(positions_id, positions)

    def _device_of(self, key: str) -> str:
        lane = self._lane_of.get(key, 0)
        return self._lanes[lane].device

    def _slot(self, key: str) -> _Slot:
        with self._lock:
            slot = self._slots.get(key)
        if slot is None:
            from server.render import Renderer

            renderer: Renderer | MultiRenderer | SortLastRenderer
            if self._spread == key:
                renderer = self._across_devices(split_by_space=False)
            else:
                renderer = Renderer(
                    device=self._device_of(key),
                    max_atoms=self.per_device,
                    max_pixels=self.max_pixels,
                    tuning=self.tuning,
                )
            self.actual_device = renderer.device
            on_cuda = all(d.startswith("cuda") for d in renderer.device.split(","))
            slot = _Slot(renderer, on_cuda=on_cuda)
            with self._lock:
                self._slots[key] = slot
        return slot

    @property
    def per_device(self) -> int:
        """Atoms one device's renderer holds."""
        return self.device_atoms if self.device_atoms is not None else self.max_atoms

    def _across_devices(self, *, split_by_space: bool) -> MultiRenderer | SortLastRenderer:
        """A renderer over every lane's device: sort-first bands, or slabs of space for a
        system one device does not hold."""
        names = tuple(lane.device for lane in self._lanes)
        options: dict[str, Any] = {
            "max_atoms": self.per_device,
            "max_pixels": self.max_pixels,
            "tuning": self.tuning,
        }
        if split_by_space:
            from server.render.sortlast import SortLastRenderer

            return SortLastRenderer(names, **options)
        from server.render.multi import MultiRenderer

        return MultiRenderer(names, **options)

    def _fit(self, key: str, slot: _Slot, n_atoms: int) -> None:
        """(On the slot's thread, before it takes a new topology.) A system one device does not
        hold is split across every device by space (sort-last; the measured rule:
        docs/rendering.md, "Several devices (sort-last)") while every slot is on this slot's
        thread (a session alone on the devices, the jobs and one-off renders beside it), so no
        two threads drive one device, and later slots join that thread; otherwise it is refused,
        saying why. A smaller system goes back to image bands (the session alone) or to one
        device."""
        from server.render import Renderer
        from server.render.sortlast import SortLastRenderer

        large = n_atoms > self.per_device and len(self._lanes) > 1
        split = isinstance(slot.renderer, SortLastRenderer)
        if large == split:
            return
        if large:
            with self._lock:
                mine = self._lane_of.get(key, 0)
                alone = all(lane == mine for lane in self._lane_of.values())
                if alone:
                    self._whole.add(key)
            if not alone:
                raise CapacityError(
                    f"{n_atoms} atoms: one device holds {self.per_device} (--device-atoms), and "
                    "work placed on the other devices' threads has not moved beside it yet; "
                    "the next frame splits it across them"
                )
        else:
            with self._lock:
                self._whole.discard(key)
        old = slot.renderer
        with contextlib.suppress(Exception):
            old.finish()
        close = getattr(old, "close", None)
        if close is not None:
            with contextlib.suppress(Exception):
                close()
        slot.prefetched = None
        slot.shown = None  # a displayed frame's device copy was the old renderer's
        if large or self._spread == key:
            slot.renderer = self._across_devices(split_by_space=large)
        else:
            slot.renderer = Renderer(
                device=self._device_of(key),
                max_atoms=self.per_device,
                max_pixels=self.max_pixels,
                tuning=self.tuning,
            )
        log.info(
            "%s: %d atoms drawn on %s%s",
            key,
            n_atoms,
            slot.renderer.device,
            " by slabs of space (sort-last)" if large else "",
        )

    def _prepare(
        self, request: RenderRequest, held: list[tuple[FrameStager, Any]], *, wait: bool = True
    ) -> Renderer | MultiRenderer | SortLastRenderer | LayeredRenderer:
        """Bring the slot up to `request`'s snapshot and render it (`wait=False`: queue the
        render of a slot without layers and return). A staged copy the upload reads from goes
        into `held`, to be released once the device is done with it."""
        slot = self._slot(request.slot)
        snap = request.snapshot
        slot.stageable = slot.on_cuda and request.layers is None
        if request.layers is not None:
            slot.stager = None  # layers upload their own subsets
            return self._prepare_layers(slot, request)
        if slot.topology_id != snap.topology_id:
            self._fit(request.slot, slot, snap.topology.n_atoms)
            try:
                slot.renderer.set_topology(snap.topology)
            except RenderError as exc:
                if snap.topology.n_atoms <= self.per_device:
                    raise
                raise CapacityError(
                    f"{exc}: one device holds {self.per_device} atoms (--device-atoms); "
                    "several devices (--gpus) split a larger system across them"
                ) from None
            slot.topology_id = snap.topology_id
            slot.positions_id = -1
        if slot.positions_id != snap.positions_id:
            # frames were checked finite when decoded; skip the host-side scan
            stager = slot.stager
            staged = None
            from server.render import Renderer

            single = slot.renderer
            shown = (
                slot.periodic is not None
                and snap.positions is slot.shown
                and isinstance(single, Renderer)
            )
            if not shown and stager is not None and stager.n == len(snap.positions):
                staged = stager.take(snap.positions_id)
            if shown:
                assert slot.periodic is not None and isinstance(single, Renderer)
                single.set_positions(
                    snap.positions, check_finite=False, on_device=slot.periodic.device_result
                )
            elif stager is None or staged is None:
                slot.renderer.set_positions(snap.positions, check_finite=False)
            else:  # only a slot CUDA devices draw has a stager
                held.append((stager, staged))
                slot.renderer.set_positions(snap.positions, check_finite=False, staged=staged)
            slot.positions_id = snap.positions_id
        renderer = slot.renderer
        if snap.history:
            renderer.set_history(
                snap.history, snap.history_epoch, request.params, live=snap.live, lag=snap.lag
            )
        size = (request.params, request.camera, request.width, request.height)
        if request.tile is not None and _tiles(renderer):
            renderer.render(*size, request.tile, wait=wait)
        else:
            renderer.render(*size, wait=wait)
        return renderer

    def _prefetch(self, slot: _Slot, request: RenderRequest) -> None:
        """While the slot's render runs, upload the newest frame staged since (into the spare
        positions buffer): its render will find it on the device. Only for renderers that
        upload during a render, and frames without a history to smooth over."""
        renderer = slot.renderer
        stager = slot.stager
        if not self.prefetch or stager is None or request.snapshot.history:
            return
        if not getattr(renderer, "pipelined", False):
            return
        newest = stager.newest(slot.positions_id)
        if newest is None:
            return
        positions_id, array = newest
        try:
            renderer.set_positions(array, check_finite=False, staged=array)
        except Exception:
            stager.release(array)
            raise
        slot.positions_id = positions_id
        slot.prefetched = (stager, array)

    def _prepare_layers(self, slot: _Slot, request: RenderRequest) -> LayeredRenderer:
        """Draw `request`'s layers, each with a renderer of its own on the slot's device (one
        device: a layer it cannot hold is refused, saying so)."""
        assert request.layers is not None
        n = request.snapshot.topology.n_atoms
        total = 0
        for plan in request.layers:
            held = n if plan.atoms is None else len(plan.atoms)
            total += held
            if held > self.per_device:
                raise CapacityError(
                    f"layer {plan.name!r} has {held} atoms: layers are drawn on one device, "
                    f"which holds {self.per_device} (--device-atoms); without layers "
                    "(`layers: []`), several devices (--gpus) split the system across them"
                )
        if self.device_atoms is not None and total > self.device_atoms:
            # each layer holds its atoms in a renderer of its own on the one device
            raise CapacityError(
                f"the {len(request.layers)} layers hold {total} atoms together: layers are "
                f"drawn on one device, which holds {self.device_atoms} (--device-atoms); "
                "fewer or smaller layers fit"
            )
        if slot.layered is None:
            from server.render import Renderer
            from server.render.layers import LayeredRenderer

            device = self._device_of(request.slot)
            slot.layered = LayeredRenderer(
                lambda: Renderer(
                    device=device, max_atoms=self.per_device, max_pixels=self.max_pixels
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
            tile=request.tile,
        )
        return slot.layered

    def render_sync(self, request: RenderRequest) -> RenderOutput:
        t0 = time.perf_counter()
        slot = self._slot(request.slot)
        before = slot.prefetched
        slot.prefetched = None
        with self._staged() as held:
            if before is not None:
                held.append(before)  # its upload is done once this render has read it
            renderer = self._prepare(request, held, wait=request.layers is not None)
            if request.layers is None:
                self._prefetch(slot, request)
                slot.renderer.finish()
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
            jpeg = None
            if request.rgba and request.jpeg_quality is not None:
                jpeg = self._jpeg_on_device(renderer, request.jpeg_quality)
            video_needs_rgba = i420 is None and (request.video_size is not None or not request.rgba)
            rgba = None
            if (request.rgba and jpeg is None) or video_needs_rgba:
                rgba = renderer.read_rgba()
            out = RenderOutput(rgba, dict(renderer.timings), hist, i420)
            if jpeg is not None:
                out.jpeg, out.jpeg_ms = jpeg
            if request.tile is not None and (request.layers is not None or _tiles(renderer)):
                out.tile = request.tile
            out.seconds = time.perf_counter() - t0
            return out

    def _jpeg_on_device(self, renderer: Any, quality: int) -> tuple[bytes, float] | None:
        """(On the lane's thread.) The image as JPEG encoded where it was rendered, with the
        time taken; None when this queue's encoder is for another device, or the renderer
        draws across several. An encoder that fails is dropped for good (one warning): the
        images are read back and encoded on the host from then on."""
        encoder = self.jpeg
        device_rgb = getattr(renderer, "device_rgb", None)  # a several-device render has none
        if encoder is None or device_rgb is None or renderer.device != encoder.device:
            return None
        t0 = time.perf_counter()
        try:
            data = encoder.encode_on_device(device_rgb(), quality)
        except Exception as exc:
            if self.jpeg is encoder:
                self.jpeg = None
                log.warning(
                    "JPEG on %s failed (%s: %s); images are encoded on the host from now on",
                    encoder.device,
                    type(exc).__name__,
                    exc,
                )
            return None
        return data, (time.perf_counter() - t0) * 1000.0

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
                    for device in self.actual_device.split(","):
                        wp.synchronize_device(device)
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

    def display_sync(self, request: DisplayRequest) -> Shown:
        slot = self._slot(request.slot)
        transform = slot.periodic
        if transform is None:
            from server.render.periodic import PeriodicTransform

            # a session drawn across several devices displays on the first, its lane's
            transform = slot.periodic = PeriodicTransform(slot.renderer.device.split(",")[0])
        transform.set_topology(request.topology)
        if request.restart:
            transform.restart()
        slot.shown = None
        shown = transform.apply(request.positions, request.box, request.options, request.reference)
        if "," not in slot.renderer.device:  # one device: the transform's own
            slot.shown = shown.positions
        return shown

    def _drop_sync(self, key: str) -> None:
        """(On the slot's thread.) Forget the slot's renderer (its next request makes one
        again where it is placed then), after its last render."""
        with self._lock:
            slot = self._slots.pop(key, None)
            self._whole.discard(key)
        if slot is None:
            return
        with contextlib.suppress(Exception):
            slot.renderer.finish()
        if slot.prefetched is not None:
            slot.prefetched[0].release(slot.prefetched[1])
        close = getattr(slot.renderer, "close", None)
        if close is not None:
            with contextlib.suppress(Exception):
                close()

    def release_sync(self, slot: str) -> None:
        self._drop_sync(slot)

    def close(self, wait_s: float | None = None) -> list[tuple[str, float]]:
        """Drop queued work, wait for the work running on each device's thread (at most
        `wait_s` in all; None: as long as it takes), then free the renderers. Returns (device,
        seconds it has run) of the work still running at the deadline: its thread is left to
        it, the renderers are kept, and the process cannot end normally until it returns (a
        stopping server exits without it: `server.commands.serve`)."""
        deadline = None if wait_s is None else time.monotonic() + wait_s
        for lane in self._lanes:
            lane.pool.shutdown(wait=False, cancel_futures=True)
        busy = []
        for lane in self._lanes:
            for thread in list(lane.threads):
                # an idle thread ends at once; a little grace for one the deadline has reached
                left = None if deadline is None else max(0.5, deadline - time.monotonic())
                thread.join(left)
            if any(t.is_alive() for t in lane.threads):
                since = lane.busy_since
                busy.append((lane.device, 0.0 if since is None else time.monotonic() - since))
        self._stage_pool.shutdown(wait=True, cancel_futures=True)
        if busy:
            return busy
        with self._lock:
            slots = list(self._slots.values())
            self._slots.clear()
        for slot in slots:
            close = getattr(slot.renderer, "close", None)
            if close is not None:
                with contextlib.suppress(Exception):
                    close()
        return []
