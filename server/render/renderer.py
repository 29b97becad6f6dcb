"""The Renderer: owns every device buffer and turns topology, positions, parameters and a
camera into an image that stays on the device.

Per frame: positions upload (asynchronous from the pinned `host_positions()` buffer), grid
rebuild on the device, ray cast. The grid is rebuilt whenever positions or a parameter that
shapes the density changed; a camera-only change re-casts rays over the same grid (where
part bounds follow the view, after the cells the new view adds walk for theirs).
Buffers are sized by the topology and the largest image so far, never per frame.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import warp

from protocol import Camera, RenderParams, Topology
from protocol.messages import MAX_CUTOFF_SIGMAS, MIN_CUTOFF_SIGMAS
from server.render import (
    carved,
    colors,
    geodesic_field,
    geodesic_volume,
    raycast,
    segments,
    temporal,
    transfer,
    visibility,
)
from server.render import device as devmod
from server.render.camera import CameraFrame, band_planes, camera_frame
from server.render.density import (
    GAUSSIAN,
    LANES_PER_SAMPLE,
    MEAN_BLOCK,
    MEAN_LANES,
    DensityModel,
    GaussianField,
    UnsortedAtoms,
    gather_atoms_kernel,
    mean_density_kernel,
    partial_sums_kernel,
    total_kernel,
)
from server.render.errors import CapacityError, RenderError
from server.render.geodesic import GAIN, BondGraph, GeodesicScales, route_work
from server.render.graphs import GraphCache
from server.render.grid import CellGrid, Cull, cell_threads
from server.render.outputs import ImageOutputs
from server.render.parttrial import PartTrial
from server.render.reach import reach_sigmas
from server.render.skeleton import GRAPH_CUTOFF_SIGMAS, Skeleton, WarpScales
from server.render.tuning import (
    BOUND_KEEP_FROM,
    CELLS_PER_CUTOFF,
    GRAPH_CACHE,
    LARGE_ATOMS,
    MARCH_BLOCK,
    MARCH_BUDGET,
    MARCH_REGISTERS,
    PIPELINE_ATOMS,
    SPLIT_MIN_ATOMS,
    SPLIT_PIXELS_PER_SM,
    SPLIT_RAYS,
    STILL_VIEWS,
    TRIAL_ATOMS,
    VIEW_ATOMS,
    VIEWS_KEPT,
    VISIBLE_ATOMS,
    PartMode,
    Tuning,
)

wp: Any = warp  # warp's host API is unannotated: calls through it are dynamic

MAX_SIDE = 16384
MAX_PIXELS = 3840 * 2160
"""A renderer's default image limit (`max_pixels`)."""
HISTOGRAM_SIDE = 64
HISTOGRAM_X_MAX = 3.0
AO_STEP_SIGMAS = 0.6
STAGES = ("upload", "grid", "raycast", "total")
MEAN_SAMPLES = 4096
"""Atoms whose density sets the scale of relative levels (every n // 4096-th atom)."""
BOUND_LANES = 8
"""Threads that walk one listed cell's part bounds together on CUDA where the grid lists its
cells in a buffer of its own: a small molecule lists a few hundred to a few thousand cells,
and one thread a cell leaves most of the device idle while each waits on its own chain of
loads (the walk was villin's second kernel after the march, 0.11 of 0.76 ms on one NVIDIA
H200, `benchmarks/results/render_h200_profile_classical.json`)."""
SEGMENT_SLACK = 1.5
"""The segment grid assumes no bond grows beyond this times its length in the first frame."""

log = logging.getLogger(__name__)

View = tuple[CameraFrame, tuple[int, int, int, int] | None]
"""A camera frame and the tile of its image a render casts (None: all of it)."""


@dataclass(frozen=True)
class Derived:
    """Device-side constants of one set of render parameters. `sigma` is the spatial scale of
    the atoms' Gaussians (s3 of the carved density, sigma otherwise)."""

    sigma: float
    per_atom: int
    sigma_per_radius: float
    reach: float
    inv2s2: float
    half_k2: float
    dt: float
    iso: float
    weights: str
    relative: bool
    warp: WarpScales | None
    geo: GeodesicScales | None = None
    volume_h: float = 0.0
    """The geodesic density's grid spacing when its rays read it from a grid
    (`geodesic_volume`), 0 when they walk the routes per sample."""


def _model_name(d: Derived) -> str:
    """The density model a frame draws, as the per-model tables name it."""
    if d.geo is not None:
        return "geodesic"
    return "carved" if d.warp is not None else "gaussian"


def check_finite_positions(arr: npt.NDArray[np.float32]) -> None:
    """RenderError naming the first atom of a frame with a NaN or Inf (one sum over the frame
    when there is none)."""
    if math.isfinite(float(arr.sum(dtype=np.float32))):
        return
    bad = np.nonzero(~np.isfinite(arr).all(axis=1))[0]
    if len(bad):
        raise RenderError(f"positions contain NaN or Inf ({len(bad)} atoms, first index {bad[0]})")
    raise RenderError("positions are too large (beyond ±1e30 angstrom)")


@functools.cache
def whole_samples(model: DensityModel) -> DensityModel:
    """`model` with its marching kernels walking every gated sample whole (no `side4`): one
    model per process, so its kernels are generated once (`raycast.kernels_for` keeps them
    per model)."""
    return dataclasses.replace(model, name=f"{model.name}_whole_samples", side4=None)


class Renderer(ImageOutputs):
    """Ray-casting renderer of the Gaussian molecular density (see docs/rendering.md).

    `density` is the model the ray caster evaluates (any model over `GaussianField`, the sorted
    atoms and cell grid this class builds; the geodesic and carved densities are chosen by the
    render parameters); `tuning` sets how the renderer trades its own work (tuning.py: the
    defaults are the fastest measured, and none but `taper` changes an image)."""

    def __init__(
        self,
        device: str = "auto",
        max_atoms: int = 4_000_000,
        max_pixels: int = MAX_PIXELS,
        *,
        density: DensityModel = GAUSSIAN,
        tuning: Tuning | None = None,
    ) -> None:
        if max_atoms < 0 or max_pixels < 1:
            raise RenderError("max_atoms must be >= 0 and max_pixels >= 1")
        t = tuning if tuning is not None else Tuning()
        self.tuning = t
        self.device: str = devmod.resolve(device)
        self.max_atoms = int(max_atoms)
        self.max_pixels = int(max_pixels)
        self.coverage = False
        """Write coverage alpha over no background (a layer composited with others)."""
        self.cull_to_tile = False
        """A tile's grid keeps only the atoms within reach of its rays (and of the atoms the
        mean density of relative levels is taken at): the same image from a grid of a band's
        share of the atoms, rebuilt when the camera moves. Set by `MultiRenderer` for the
        classical and the geodesic densities; a whole image, or the carved density, keeps every
        atom."""
        self.depth_limit: Any = None
        """A device array of per-pixel distances where volume rays stop (None: the grid's
        end); set by the layer compositor to the nearest opaque surface of the other layers."""
        self.region: tuple[int, float, float, int] | None = None
        """Sort-last (`sortlast.py`): the slab of space (axis, lo, hi) this renderer's rays
        sample, its atoms being those within `halo` of it, and whether a ray may start inside
        the surface (`raycast.CameraData.part_open`); None: all of space."""
        self.scene_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None
        """Sort-last: the whole system's grid box (lo, hi), which the depth cue spans."""
        self._no_limit = wp.zeros(1, dtype=float, device=self.device)
        self._dev = wp.get_device(self.device)
        self._cuda = bool(self._dev.is_cuda)
        if density.field is not GaussianField:
            raise RenderError(f"density {density.name!r} needs a GaussianField to draw with")
        self._density = density
        self._count_passes = t.count_passes
        self._kernel_sets: dict[tuple[str, bool], raycast.RaycastKernels] = {}
        self._kernels_of_model(density, False)  # generated now: bad options fail here
        self.timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self._graphs = GraphCache(
            self.device, GRAPH_CACHE, bool(t.graphs or (t.graphs is None and self._cuda)), "render"
        )
        split = not self._cuda and not self._graphs.enabled  # a capture takes its thread's alone
        self._host_threads = max(t.cpu_threads or devmod.host_threads(), 1) if split else 1
        """Host threads the CPU device's ray passes and geodesic fill are split across
        (`_ray_runs`, `GeodesicVolume`)."""
        trial = t.part_trial if t.part_trial is not None else self._cuda
        self._part_trial = PartTrial() if trial and t.part_bounds is None else None
        self._frame_parts: tuple[Derived, str, PartMode] | None = None
        """This frame's derived parameters, render mode and part choice (`_part_trial`)."""
        self._frame_rule: PartMode | None = None
        self._grid_parts: PartMode | None = None
        self._grid_rule: PartMode | None = None
        """The part choice the held grid was built with, and the rule of sizes then."""
        self._topology_version = 0

        self._topology: Topology | None = None
        self._n = 0
        self._alloc_atoms(0)
        self._r_min = self._r_max = colors.R_REF
        self._have_positions = False
        self._positions_version = 0
        self._grid_key: tuple[Any, ...] | None = None
        self._views_walked: tuple[tuple[Any, ...] | None, set[tuple[Any, ...]]] = (None, set())
        """The key of a grid and the views whose cells have walked for their parts on it."""
        self._views_seen: tuple[tuple[Any, ...] | None, set[tuple[Any, ...]], int] = (
            None,
            set(),
            0,
        )
        """The positions version and derived parameters rendered last (a grid but for its
        part mode), the distinct cameras that saw them (a few counted) and how many saw the
        ones rendered before them (`_many_views`)."""
        self._color_key: tuple[Any, ...] | None = None
        self._given_colors: npt.NDArray[np.uint32] | None = None
        self._tf_key: tuple[Any, ...] | None = None
        self._tf = transfer.build_table()
        self._tf_table = wp.zeros(transfer.TABLE_SIZE, dtype=wp.vec4, device=self.device)
        self._seg_table: wp.array | None = None
        """Volume mode's pre-integrated segments (segments.py), made at its first volume frame."""
        self._seg_key: tuple[Any, ...] | None = None
        self._hist = wp.zeros(4096, dtype=wp.int32, device=self.device)
        self._pixels = 0
        self._alloc_pixels(1)
        self._image: tuple[int, int] | None = None
        self._last: tuple[RenderParams, Derived] | None = None
        self._uploaded = False
        self._upload_ms = 0.0
        self.uploaded_from = "host"
        """Where the last frame came from: the host, page-locked host memory or the device."""
        # per-frame host work between the upload and the launch leaves the GPU idle: reuse
        # what the last frame computed from the same (immutable) parameter and camera objects
        self._params_seen: tuple[RenderParams, str] | None = None
        self._camera_seen: tuple[Camera, int, int, CameraFrame, tuple[Any, ...]] | None = None
        self._field_seen: tuple[Derived, Any] | None = None
        lanes = t.mean_lanes
        self._mean_lanes = lanes if lanes is not None else LANES_PER_SAMPLE if self._cuda else 1
        geo_lanes = geodesic_field.MEAN_LANES_PER_SAMPLE if self._cuda else 1
        self._geo_mean_lanes = lanes if lanes is not None else geo_lanes
        self._density_samples = wp.zeros(
            MEAN_SAMPLES * max(self._mean_lanes, self._geo_mean_lanes),
            dtype=float,
            device=self.device,
        )
        self._density_partial = wp.zeros(MEAN_LANES, dtype=float, device=self.device)
        self._density_total = wp.zeros(1, dtype=float, device=self.device)
        self._pending: tuple[float, float, float, bool, int] | None = None
        if self._cuda:
            self._stream = wp.get_stream(self.device)
            # a frame's stages on the render stream: grid start, cast start, end
            self._events = [wp.Event(self.device, enable_timing=True) for _ in range(3)]
            # positions upload on a stream of their own, into the buffer no render is reading
            self._copy_stream = wp.Stream(self.device)
            self._release = [wp.Event(self.device) for _ in range(2)]
            self._upload_events = [
                [wp.Event(self.device, enable_timing=True) for _ in range(2)] for _ in range(2)
            ]
            self._part_event = wp.Event(self.device)
        self._upload_open: tuple[Any, Any, Any, bool] | None = None
        """An upload begun and not yet closed: (buffer, stream, end event, swap buffers)."""
        self._part_source: wp.array | None = None
        """The buffer this device's part of the last split frame went into."""

    # ------------------------------------------------------------------ buffers

    def _alloc_atoms(self, n: int) -> None:
        d = self.device
        m = max(n, 1)
        self._pos = wp.zeros(m, dtype=wp.vec3, device=d)
        self._part_source = None
        # CUDA, large systems: a second positions buffer and a second page-locked staging
        # buffer, so the next frame uploads while the last one renders (`render(wait=False)`,
        # then set_positions); small systems keep one of each (one graph per frame set-up)
        chosen = self.tuning.double_buffer
        double = chosen if chosen is not None else n >= PIPELINE_ATOMS
        count = 2 if self._cuda and double else 1
        self._pos_buffers = [self._pos] + [
            wp.zeros(m, dtype=wp.vec3, device=d) for _ in range(count - 1)
        ]
        self._stagings = [
            wp.zeros(m, dtype=wp.vec3, device="cpu", pinned=self._cuda) for _ in range(count)
        ]
        self._next_staging = 0
        self._weights = wp.zeros(m, dtype=float, device=d)
        self._radii = wp.zeros(m, dtype=float, device=d)
        self._colors = wp.zeros(m, dtype=wp.uint32, device=d)
        self._sorted = wp.zeros(m, dtype=wp.vec4, device=d)
        self._inv2s2 = wp.zeros(m, dtype=float, device=d)
        self._grid = CellGrid(d, n, self.tuning.grid_sort, cell_list=self.tuning.cell_list)
        self._grid.invalidate()
        self._weights_key: tuple[Any, ...] | None = None
        self._skeleton: Skeleton | None = None
        self._skel: _SkeletonBuffers | None = None
        self._geo: geodesic_field.GeodesicTables | None = None
        self._geo_work: tuple[float, float, float] | None = None
        """(tables' reach, atoms within the cutoff, routes an atom) of the last work check."""
        self._gvol: geodesic_volume.GeodesicVolume | None = None
        self.geodesic_max_routes = geodesic_field.MAX_ROUTES_PER_SAMPLE
        """Most routes a geodesic sample may walk (`_check_geodesic_work`)."""
        self._ref_positions: npt.NDArray[np.float32] | None = None
        self._temporal: temporal.TemporalState | None = None
        self._smoothed = False
        self._raw_source: Any = None
        self._pos_is_raw = False
        if self._cuda:
            self._released = [False, False]
        self._atom_capacity = n
        self._field_seen = None
        self._drop_graphs()

    def _alloc_pixels(self, count: int) -> None:
        if count <= self._pixels:
            return
        d = self.device
        self._hit_k = wp.zeros(count, dtype=wp.int32, device=d)
        self._hit_v = wp.zeros(count, dtype=wp.vec2, device=d)
        self._rgba = wp.zeros(count, dtype=wp.uint32, device=d)
        self._depth = wp.zeros(count, dtype=float, device=d)
        self._ids = wp.zeros(count, dtype=wp.int32, device=d)
        self._queue = wp.zeros(count, dtype=wp.vec4i, device=d)
        self._queue_v = wp.zeros(count, dtype=float, device=d)
        self._queue_len = wp.zeros(1, dtype=wp.int32, device=d)
        self._found = wp.zeros(count, dtype=wp.int32, device=d)
        self._counts = wp.zeros(count if self._count_passes else 1, dtype=wp.int32, device=d)
        self._pixels = count
        self._drop_graphs()

    def memory_bytes(self) -> dict[str, int]:
        """Device bytes by purpose; `per_atom` + `grid` is what the density costs beyond
        positions and image buffers."""
        atom = (self._weights, self._radii, self._colors, self._sorted, self._inv2s2)
        pix = (
            self._hit_k,
            self._hit_v,
            self._rgba,
            self._depth,
            self._ids,
            self._queue,
            self._queue_v,
            self._found,
            self._counts,
        )
        seg = 0 if self._seg_table is None else int(self._seg_table.capacity)
        return {
            "positions": sum(int(a.capacity) for a in self._pos_buffers),
            "per_atom": sum(int(a.capacity) for a in atom),
            "grid": int(self._grid.nbytes),
            "image": sum(int(a.capacity) for a in pix),
            "other": int(self._tf_table.capacity + self._hist.capacity + seg),
            "skeleton": self._skel.nbytes if self._skel is not None else 0,
            "geodesic": (self._geo.nbytes if self._geo is not None else 0)
            + (self._gvol.nbytes if self._gvol is not None else 0),
        }

    # ------------------------------------------------------------------ inputs

    @property
    def n_atoms(self) -> int:
        return self._n

    def set_topology(self, topology: Topology) -> None:
        """Take a topology once: radii, weights and colours are prepared for the device."""
        n = int(topology.n_atoms)
        if n > self.max_atoms:
            raise CapacityError(f"topology has {n} atoms, this renderer allows {self.max_atoms}")
        if n > self._atom_capacity:
            self._alloc_atoms(n)
        self._topology = topology
        self._topology_version += 1
        self._n = n
        self._have_positions = False
        self._grid_key = None
        self._color_key = None
        self._given_colors = None
        self._weights_key = None
        self._skeleton = None
        self._skel = None
        self._geo = None
        self._geo_work = None
        self._gvol = None
        self._ref_positions = None
        self._temporal = None
        self._smoothed = False
        if n:
            radii = colors.atom_radii(topology)
            self._r_min = float(radii.min())
            self._r_max = float(radii.max())
            wp.copy(self._radii, wp.array(radii, dtype=float, device="cpu"), count=n)
        self._grid.invalidate()

    def host_positions(self) -> npt.NDArray[np.float32]:
        """A (n, 3) float32 host buffer (page-locked on CUDA devices): positions written here
        and passed to `set_positions` upload asynchronously, without a host copy. On CUDA
        devices it alternates between two buffers, so ask again for every frame: a frame can
        then be written while the last one uploads. Rewrite a buffer only after the render
        that followed its upload has finished."""
        staging = self._stagings[self._next_staging]
        a: npt.NDArray[np.float32] = staging.numpy().view(np.float32).reshape(-1, 3)
        return a[: self._n]

    def set_positions(
        self,
        positions: npt.ArrayLike | None,
        *,
        check_finite: bool = True,
        staged: npt.NDArray[np.float32] | None = None,
        part: tuple[int, int] | None = None,
        on_device: wp.array | None = None,
    ) -> None:
        """Positions (n, 3) in angstrom for the next render; n must match the topology.

        `check_finite=False` skips the host-side NaN/Inf scan (one pass over the array) for
        positions already validated upstream, e.g. by the protocol decoder; the device still
        refuses a non-finite frame by drawing background only. `staged`: the same positions,
        already copied to page-locked memory (`server.pipeline.staging`), uploaded from there
        asynchronously; keep it unwritten until this render has finished. `part` (a, b):
        only atoms [a, b) are copied from the host; `receive` brings the others from the
        devices that copied them (`MultiRenderer`: each device uploads 1/N of a frame).
        `on_device`: the same positions, already on this renderer's device (a periodic
        display's result, `server.render.periodic`), copied device to device; the work that
        wrote them must be done. With `on_device`, `positions` may be None (no host copy:
        sort-last's parts, `server.render.scatter`), for densities that read no host copy
        (not the carved one, not smoothing in time)."""
        if self._topology is None:
            raise RenderError("set_topology must come before set_positions")
        n = self._n
        arr: npt.NDArray[np.float32] | None = None
        if positions is None:
            if on_device is None:
                raise RenderError("positions, or their copy on the device (on_device), are needed")
        else:
            arr = self._host_frame(positions)
            if check_finite and n:
                check_finite_positions(arr)
        t0 = time.perf_counter()
        self.uploaded_from = "host"
        if n and on_device is not None:
            if part is not None or on_device.device != self._dev or len(on_device) < n:
                raise RenderError(
                    f"a device copy of {len(on_device)} atoms on {on_device.device} for "
                    f"{n} atoms on {self.device}, whole"
                )
            self.uploaded_from = "device"
            if self._cuda:
                self._upload(on_device, n)
            else:
                wp.copy(self._pos, on_device, count=n)
        elif n:
            assert arr is not None
            if staged is not None:
                self.uploaded_from = "page-locked"
                if staged.shape != arr.shape or staged.dtype != np.float32:
                    raise RenderError(f"a staged copy of shape {staged.shape} for {arr.shape}")
                arr = staged
            address = arr.__array_interface__["data"][0]
            own = [i for i, b in enumerate(self._stagings) if b.ptr == address]
            src = (
                self._stagings[own[0]]
                if own
                else wp.array(arr, dtype=wp.vec3, device="cpu", copy=False)
            )
            if own:
                self._next_staging = (own[0] + 1) % len(self._stagings)
            if part is not None:
                self._upload_part(src, part)
            elif self._cuda:
                self._upload(src, n)
            else:
                wp.copy(self._pos, src, count=n)
        self._upload_ms = (time.perf_counter() - t0) * 1e3
        self._raw_source = positions  # the frame `_pos` holds, until smoothing overwrites it
        self._pos_is_raw = True
        if self._ref_positions is None and arr is not None:
            # bonds keep their lengths (the carved density's graph tables use these)
            self._ref_positions = np.array(arr[:n], dtype=np.float32)
        # only a recorded upload is timed: the elapsed time between two unrecorded CUDA events
        # fails and leaves the error for the next CUDA call that checks for one to report
        self._uploaded = n > 0
        self._have_positions = True
        self._positions_version += 1

    def _host_frame(self, positions: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """`positions` as a C-contiguous (n, 3) float32 array, checked against the topology."""
        arr = np.asarray(positions)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise RenderError(f"positions must have shape (n, 3), got {arr.shape}")
        if arr.shape[0] != self._n:
            raise RenderError(f"positions have {arr.shape[0]} atoms, topology has {self._n}")
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise RenderError(f"positions must be real numbers, got dtype {arr.dtype}")
        if arr.dtype != np.float32 or not arr.flags.c_contiguous:
            arr = np.ascontiguousarray(arr, dtype=np.float32)
        return arr

    def _upload(self, src: wp.array, n: int) -> None:
        """Copy a frame to the device. While a render is still queued (`render(wait=False)`)
        and a second buffer exists, the copy goes on the upload stream into the buffer that
        render does not read, which becomes the current one: later work on the render stream
        waits for the copy, the queued render keeps its buffer. Otherwise (the last render has
        finished, or must finish first) the frame replaces the current buffer in order on the
        render stream, so blocking callers keep one buffer and one graph per frame set-up."""
        dest, stream = self._upload_begin()
        wp.copy(dest, src, count=n, stream=stream)
        self._upload_end()

    def _upload_begin(self) -> tuple[wp.array, Any]:
        """The buffer the next frame goes into and the stream that writes it (`_upload`'s
        rules; no stream on the CPU); `_upload_end` closes the upload."""
        if not self._cuda:
            self._upload_open = (self._pos, None, None, False)
            return self._pos, None
        front = 0 if self._pos is self._pos_buffers[0] else 1
        if self._pending is None or len(self._pos_buffers) == 1:
            self.finish()
            start, end = self._upload_events[front]
            self._stream.record_event(start)
            self._upload_open = (self._pos, self._stream, end, False)
            return self._pos, self._stream
        spare = 1 - front
        dest = self._pos_buffers[spare]
        if self._released[spare]:
            self._copy_stream.wait_event(self._release[spare])
        start, end = self._upload_events[spare]
        self._copy_stream.record_event(start)
        self._upload_open = (dest, self._copy_stream, end, True)
        return dest, self._copy_stream

    def _upload_end(self) -> None:
        assert self._upload_open is not None
        dest, stream, end, swap = self._upload_open
        self._upload_open = None
        if stream is None:
            return
        stream.record_event(end)
        if swap:
            self._stream.wait_event(end)
            self._pos = dest

    def _upload_part(self, src: wp.array, part: tuple[int, int]) -> None:
        """Copy atoms [a, b) of a frame from the host and leave the upload open: `receive`
        copies the rest from the devices that uploaded it and closes it."""
        dest, stream = self._upload_begin()
        a, b = part
        if b > a:
            wp.copy(dest, src, dest_offset=a, src_offset=a, count=b - a, stream=stream)
        if stream is not None:
            stream.record_event(self._part_event)
        self._part_source = dest

    def receive(self, parts: Sequence[tuple[Renderer, int, int]]) -> None:
        """The rest of a frame whose part this renderer uploaded (`set_positions(...,
        part=...)`): atoms [a, b) from each renderer that uploaded them, device to device,
        each copy after that renderer's own part has landed."""
        if self._upload_open is None:
            raise RenderError("receive follows set_positions with a part")
        dest, stream, _end, _swap = self._upload_open
        for other, a, b in parts:
            source = other._part_source
            if source is None:
                raise RenderError("receive from a renderer that holds no part of a frame")
            if b > a:
                if stream is not None:
                    stream.wait_event(other._part_event)
                wp.copy(dest, source, dest_offset=a, src_offset=a, count=b - a, stream=stream)
        self._upload_end()

    def set_history(
        self,
        frames: Sequence[tuple[int, npt.NDArray[np.float32]]],
        epoch: int,
        params: RenderParams,
        *,
        live: bool = True,
        lag: int | None = None,
    ) -> None:
        """Recent frames (id, positions), oldest first, for temporal smoothing and motion
        colours; those not seen yet join the ring buffer. A new `epoch` (a seek) starts it
        again. `live` picks the causal kernel for `time_kernel="auto"` (else centred); `lag`
        overrides the centred kernel's display lag (a batch job near a trajectory's end)."""
        if self._topology is None:
            raise RenderError("set_topology must come before set_history")
        if not params.needs_history():
            return
        if self._temporal is None:
            heavy = np.asarray([e.upper() not in ("H", "D") for e in self._topology.elements])
            self._temporal = temporal.TemporalState(self.device, self._n, heavy)
        raw = self._raw_source if self._pos_is_raw else None
        try:
            self._temporal.feed(frames, epoch, params, live, lag, raw, self._pos)
        except ValueError as exc:
            raise RenderError(str(exc)) from None

    def _apply_temporal(self, params: RenderParams) -> None:
        """Smooth the positions over time (or put the raw newest frame back when smoothing
        was just turned off); a changed frame rebuilds the grid."""
        state = self._temporal
        if state is None or not self._n:
            return
        wanted = params.time_smoothing != "off" or params.color_by == "motion"
        if wanted and state.apply(self._pos, params):
            self._smoothed = True
            self._pos_is_raw = False
            self._positions_version += 1
            return
        if self._smoothed and params.time_smoothing == "off":
            state.newest(self._pos)
            state.shown_key = None
            self._smoothed = False
            self._positions_version += 1

    # ------------------------------------------------------------------ checks

    def _check_size(self, width: Any, height: Any) -> tuple[int, int]:
        if isinstance(width, bool) or isinstance(height, bool):
            raise RenderError("image size must be integers")
        try:
            w, h = int(width), int(height)
        except (TypeError, ValueError):
            raise RenderError(f"image size must be integers, got {width!r}x{height!r}") from None
        if w != width or h != height:
            raise RenderError(f"image size must be integers, got {width!r}x{height!r}")
        if w < 1 or h < 1:
            raise RenderError(f"image size must be at least 1x1, got {w}x{h}")
        if w > MAX_SIDE or h > MAX_SIDE:
            raise RenderError(f"image side over the limit of {MAX_SIDE}: {w}x{h}")
        if w * h > self.max_pixels:
            raise RenderError(f"image {w}x{h} has {w * h} pixels, the limit is {self.max_pixels}")
        return w, h

    def check_view(self, camera: Camera, width: Any, height: Any) -> tuple[int, int, CameraFrame]:
        """The image size and camera frame `render` would draw; RenderError for invalid ones."""
        w, h = self._check_size(width, height)
        return w, h, self._check_camera(camera, w, h)

    @staticmethod
    def _check_params(params: RenderParams) -> None:
        def positive(name: str, v: float) -> None:
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise RenderError(f"{name} must be a positive finite number, got {v!r}")

        positive("sigma_A", params.sigma_A)
        positive("iso_level", params.iso_level)
        positive("step_sigmas", params.step_sigmas)
        positive("cutoff_sigmas", params.cutoff_sigmas)
        if params.mode not in ("iso", "volume"):
            raise RenderError(f"mode must be 'iso' or 'volume', got {params.mode!r}")
        if params.radius_mode not in ("uniform", "vdw"):
            raise RenderError(f"radius_mode must be 'uniform' or 'vdw', got {params.radius_mode!r}")
        if not MIN_CUTOFF_SIGMAS <= params.cutoff_sigmas <= MAX_CUTOFF_SIGMAS:
            raise RenderError(
                f"cutoff_sigmas must be within {MIN_CUTOFF_SIGMAS}..{MAX_CUTOFF_SIGMAS}, "
                f"got {params.cutoff_sigmas}"
            )

    @staticmethod
    def _check_camera(camera: Camera, width: int, height: int) -> CameraFrame:
        values = [*camera.target, *camera.orientation, camera.distance, camera.fov_deg]
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            raise RenderError("camera has a non-finite value")
        if not camera.distance > 0:
            raise RenderError(f"camera distance must be positive, got {camera.distance}")
        if camera.projection == "perspective" and not 0 < camera.fov_deg < 180:
            raise RenderError(f"camera fov_deg must be in (0, 180), got {camera.fov_deg}")
        if camera.projection == "orthographic" and not camera.ortho_height > 0:
            raise RenderError(f"camera ortho_height must be positive, got {camera.ortho_height}")
        try:
            return camera_frame(camera, width, height)
        except ValueError as exc:
            raise RenderError(f"invalid camera: {exc}") from None

    def halo(self, params: RenderParams, r_max: float | None = None) -> float:
        """How far from a region of space the atoms lie whose density its rays sample, shade
        and occlude with (sort-last parts hold the atoms within it): the cutoff reach, the
        four lattice steps an iso pass may take past the region's end (one volume step), and
        the ambient occlusion's farthest sample. `r_max`: the largest atom radius of the whole
        system (van der Waals widths), where this renderer holds only some of its atoms."""
        d = self._derive(params, r_max)
        past = max(4.0 * d.dt, self._volume_dt(d))
        return float(d.reach * (1.0 + 1.0e-3) + past + 4.0 * AO_STEP_SIGMAS * d.sigma + 1.0e-3)

    def reach(self, params: RenderParams, r_max: float | None = None) -> float:
        """The cutoff reach of the widest atom: the density is zero beyond it."""
        return float(self._derive(params, r_max).reach)

    def _derive(self, p: RenderParams, r_max: float | None = None) -> Derived:
        warp = None
        if p.scale_space in ("carved", "warped") and p.warp_strength > 0.0:
            warp = WarpScales.of(float(p.sigma_A), float(p.warp_strength))
        sigma = warp.space if warp is not None else float(p.sigma_A)
        # the reach the surface's accuracy needs at this sigma, at most cutoff_sigmas (reach.py;
        # measured for the Gaussian density: the carved density keeps cutoff_sigmas)
        fixed = warp is not None or self.tuning.fixed_cutoff
        k = float(p.cutoff_sigmas) if fixed else reach_sigmas(sigma, p.cutoff_sigmas)
        if p.radius_mode == "vdw":
            spr = sigma / colors.R_REF
            s_max = spr * (self._r_max if r_max is None else max(r_max, self._r_max))
            per_atom = 1
        else:
            spr = 0.0
            s_max = sigma
            per_atom = 0
        out = Derived(
            sigma=sigma,
            per_atom=per_atom,
            sigma_per_radius=spr,
            reach=k * s_max,
            inv2s2=0.5 / (sigma * sigma),
            half_k2=0.5 * k * k,
            dt=float(p.step_sigmas) * sigma,
            iso=float(p.iso_level),
            weights=str(p.density_weights),
            relative=p.level_scale == "mean",
            warp=warp,
        )
        if p.scale_space == "geodesic" and p.warp_strength > 0.0:
            smoothing = float(p.geodesic_smoothing)
            scales = GeodesicScales.of(sigma, float(p.warp_strength), k * s_max, smoothing)
            out = dataclasses.replace(out, geo=scales)
        return out

    # ------------------------------------------------------------------ rendering

    def _field(self, d: Derived) -> Any:
        """The struct the kernels read: a GaussianField, or a CarvedField or GeodesicField
        around one."""
        seen = self._field_seen
        if seen is not None and seen[0] == d:
            return seen[1]
        f: Any = self._gaussian_field(d)
        if d.warp is not None:
            f = self._carved_field(d, f)
        elif d.geo is not None:
            f = self._geodesic_field(d, f)
            if d.volume_h > 0.0:
                f = self._geodesic_volume().field(f)
        self._field_seen = (d, f)
        return f

    def _gaussian_field(self, d: Derived) -> GaussianField:
        f = GaussianField()
        f.atoms = self._sorted
        f.inv2s2 = self._inv2s2
        f.order = self._grid.order
        f.colors = self._colors
        f.cell_start = self._grid.cell_start
        f.bound = self._grid.cell_values
        f.parts = self._grid.parts
        f.brick_bound = self._grid.brick_values
        f.info = self._grid.info
        f.inv2s2_uniform = d.inv2s2
        f.half_k2 = d.half_k2
        f.inv_half_k2 = 1.0 / d.half_k2 if self.tuning.taper else 0.0
        f.per_atom = d.per_atom
        return f

    def _carved_field(self, d: Derived, gauss: GaussianField) -> Any:
        assert d.warp is not None
        skel = self._skeleton_buffers()
        s = carved.SkeletonField()
        s.info = skel.grid.info
        s.cell_start = skel.grid.cell_start
        s.seg_a = skel.seg_a
        s.seg_b = skel.seg_b
        s.r2 = d.warp.reach * d.warp.reach
        s.atten = d.warp.atten
        f = carved.CarvedField()
        f.info = gauss.info
        f.bound = gauss.bound
        f.parts = gauss.parts
        f.brick_bound = gauss.brick_bound
        f.gauss = gauss
        f.skel = s
        return f

    def _geodesic_field(self, d: Derived, gauss: GaussianField) -> Any:
        assert d.geo is not None
        tables = self._geodesic_tables()
        f = geodesic_field.GeodesicField()
        f.info = gauss.info
        f.cell_start = gauss.cell_start
        f.bound = gauss.bound
        f.parts = gauss.parts
        f.brick_bound = gauss.brick_bound
        f.gauss = gauss
        f.routes = tables.routes(d.geo.tau, d.geo.strength, d.half_k2 / (d.reach * d.reach))
        return f

    def _geodesic_tables(self) -> geodesic_field.GeodesicTables:
        """The bond graph and route tables of the topology on the device (made once per
        topology; `_update_geodesic` builds their routes)."""
        if self._geo is None:
            assert self._topology is not None
            self._geo = geodesic_field.GeodesicTables(self.device, BondGraph.of(self._topology))
        return self._geo

    def _update_geodesic(self, d: Derived) -> None:
        """Build the route tables when the weights or the tables' reach change (on the host's
        thread, before a frame's launches: the build synchronises once)."""
        if d.geo is None or not self._n:
            return
        tables = self._geodesic_tables()
        key = (d.weights, d.geo.table_reach)
        if tables.key == key:
            return
        self._check_geodesic_work(d, tables)
        # the field and graphs hold the old tables: let them go before the new are made
        self._field_seen = None
        self._drop_graphs()
        tables.build(self._pos, self._weights, GAIN, d.geo.table_reach)
        tables.key = key
        # the frame's grid stage fills the new tables' distances, whatever else changed
        self._grid_key = None
        if tables.lost:
            log.warning(
                "geodesic density: %d atoms have more than %d atoms within %.1f A along the "
                "bonds; their farthest routes are left out",
                tables.lost,
                geodesic_field.NODES,
                d.geo.table_reach,
            )

    def _check_geodesic_work(self, d: Derived, tables: geodesic_field.GeodesicTables) -> None:
        """Refuse a geodesic density whose samples would walk more routes than
        `geodesic_max_routes` (`geodesic_field.MAX_ROUTES_PER_SAMPLE`), before its tables are
        built: a large sigma reaches every bond of the molecule from every atom, and one such
        frame held the device's thread for every other render. The verdict is kept for the
        tables' reach it was made for."""
        assert d.geo is not None
        reach = d.geo.table_reach
        if self._geo_work is None or self._geo_work[0] != reach:
            near, per_atom = route_work(
                tables.graph, self._pos.numpy(), d.reach, reach, geodesic_field.NODES
            )
            self._geo_work = (reach, near, per_atom)
        _, near, per_atom = self._geo_work
        work = near * per_atom
        if work > self.geodesic_max_routes:
            raise CapacityError(
                f"the geodesic density at sigma {d.sigma:g} A would walk about {work:,.0f} "
                f"routes a sample ({near:,.0f} atoms within its {d.reach:.1f} A cutoff, "
                f"{per_atom:,.0f} routes through the bonds each), over this server's limit of "
                f"{self.geodesic_max_routes:,}; take a smaller sigma, or the classical or "
                f"carved density (their samples walk the {near:,.0f} atoms alone)"
            )

    def _geodesic_volume(self) -> geodesic_volume.GeodesicVolume:
        if self._gvol is None:
            t = self.tuning
            together = self._cuda if t.geodesic_bricks is None else t.geodesic_bricks
            regs = t.geodesic_fill_registers
            self._gvol = geodesic_volume.GeodesicVolume(
                self.device,
                together,
                t.geodesic_fill_lanes,
                t.fast_math,
                geodesic_volume.FILL_REGISTERS if regs is None else regs,
                self._host_threads,
            )
        return self._gvol

    def _plan_volume(self, d: Derived, pixels: int) -> Derived:
        """`d` with the grid spacing of `geodesic_volume` when its rays should read the
        geodesic density from a grid: when the grid has at most `points_per_pixel` points a pixel
        (Tuning.geodesic_volume None), or whenever it fits (True), in half the device's free
        memory at most and at a smoothing of at most MAX_SMOOTHING (the routes per sample
        otherwise). Sizes the grid's buffers from what the last grid built needed (read once
        from the device, after its frame), or from the atoms' box before the first."""
        use = self.tuning.geodesic_volume
        if d.geo is None or not self._n or use is False:
            return d
        if d.geo.tau > geodesic_volume.MAX_SMOOTHING * d.sigma * (1.0 + 1e-9):
            return d
        sigma_min = d.sigma if d.per_atom == 0 else d.sigma_per_radius * self._r_min
        h = geodesic_volume.spacing_of(sigma_min, d.geo.tau)
        vol = self._geodesic_volume()
        last = vol.last_need()
        if last is not None and last[1] > 0:
            points = int(last[1] * (last[0] / h) ** 3) + 1
        else:
            ext = self._atoms_extent(d.reach / self._cells_for(d))
            if ext is None:
                return d
            points = int(np.prod(np.floor((ext + 2.0 * d.reach) / h) + 5.0))
        limit = geodesic_volume.MAX_POINTS
        if use is None:
            limit = min(limit, int(geodesic_volume.points_per_pixel(self._cuda) * pixels))
        free = geodesic_field.free_bytes(self.device)
        room = free is None or vol.bytes_for(points) < free // 2 + vol.nbytes
        if points > limit or not room:
            vol.built = None  # the next plan measures the atoms again: they may shrink back
            return d
        if not vol.fits(points):
            # fields and graphs hold the buffers: let them go first; the grid fills the new
            self._field_seen = None
            self._drop_graphs()
            self._grid_key = None
            vol.reserve(points)
        return dataclasses.replace(d, volume_h=h)

    def _atoms_extent(self, cell: float) -> npt.NDArray[np.float64] | None:
        """The atoms' extent along x, y and z as the atom grid's box holds it: from the last
        grid (its box less its reach on every side; synchronises on that finished frame), or
        before any from the positions (copied to the host once) and a `cell` more, as the grid
        rounds its box up to whole cells; None when not finite."""
        g = self._grid.info.numpy()[0]
        if int(g["valid"]):
            box = np.asarray(g["box_hi"], dtype=np.float64) - np.asarray(g["origin"], np.float64)
            ext: npt.NDArray[np.float64] = np.maximum(box - 2.0 * float(g["reach"]), 0.0)
            return ext
        pos = self._pos.numpy()[: self._n]
        if not np.isfinite(pos).all():
            return None
        spread: npt.NDArray[np.float64] = np.ptp(pos, axis=0).astype(np.float64) + cell
        return spread

    def _model_of(self, d: Derived) -> DensityModel:
        if d.geo is not None and d.volume_h > 0.0:
            return geodesic_volume.GEODESIC_VOLUME
        if d.geo is not None:
            return geodesic_field.GEODESIC
        return self._density if d.warp is None else carved.CARVED

    def _kernels_of(self, d: Derived, mode: str) -> raycast.RaycastKernels:
        """The kernels of this frame's density, with part bounds unless `_parts_for` says
        "none"."""
        return self._kernels_of_model(self._model_of(d), self._parts_for(d, mode) != "none")

    def _parts_for(self, d: Derived, mode: str) -> PartMode:
        """Which cells walk for part bounds in a frame of render mode `mode` (`PART_MODES`):
        none for a density without part bounds; else `part_bounds`; else, on CUDA, what the
        renderer's trial of the rule of sizes against whole cells has this frame take
        (`parttrial.py`); else the rule of sizes (`_parts_by_size`)."""
        if self._model_of(d).part_bounds is None:
            return "none"
        if self.tuning.part_bounds is not None:
            return self.tuning.part_bounds
        now = self._frame_parts
        if now is not None and now[0] == d and now[1] == mode:
            return now[2]
        return self._parts_by_size(d, mode)

    def _parts_by_size(self, d: Derived, mode: str) -> PartMode:
        """The rule of sizes: every open cell below `VISIBLE_ATOMS` atoms and the cells the
        view reaches from there (in iso mode every open cell again for positions seen by many
        views, `_many_views`; in volume mode none from `LARGE_ATOMS`)."""
        if self._n < VISIBLE_ATOMS or (mode == "iso" and self._many_views(d)):
            return "all"
        if mode != "iso" and self._n >= LARGE_ATOMS:
            return "none"
        return "visible"

    def _views_needed(self) -> int:
        """Views of one set of positions from which walking every open cell pays (`VIEW_ATOMS`)."""
        return max(2, -(-self._n // VIEW_ATOMS))

    def _views_of(self, d: Derived) -> tuple[set[tuple[Any, ...]], int]:
        """The cameras counted for the current positions and derived parameters `d` (none
        yet when they are new) and the count of those rendered before them."""
        seen, views, before = self._views_seen
        if seen != (self._positions_version, d):
            return set(), len(views)
        return views, before

    def _count_view(self, d: Derived, camera_key: tuple[Any, ...]) -> None:
        """Count a camera seeing the current positions with derived parameters `d` (up to
        what `_many_views` asks). Cameras, not tiles: the bands of one image are one view."""
        views, before = self._views_of(d)
        if len(views) < max(self._views_needed(), STILL_VIEWS):
            views.add(camera_key)
        self._views_seen = ((self._positions_version, d), views, before)

    def _many_views(self, d: Derived) -> bool:
        """Whether an automatic iso grid walks every open cell for the views of its positions
        and derived parameters `d`: below `LARGE_ATOMS` atoms, when the ones rendered before
        had `_views_needed` views, or these have had as many and at least `STILL_VIEWS`. (A
        new iso level on still positions is a new grid: it goes by the views of the level
        before it, once.)"""
        if self._n >= LARGE_ATOMS:
            return False
        need = self._views_needed()
        views, before = self._views_of(d)
        return before >= need or len(views) >= max(need, STILL_VIEWS)

    def _kernels_of_model(self, model: DensityModel, parts: bool) -> raycast.RaycastKernels:
        own = MARCH_REGISTERS.get(model.name, MARCH_REGISTERS["gaussian"])
        sides = self.tuning.decided_sides
        decide = not self._cuda if sides is None else sides
        if model.side4 is not None and not decide:
            model = whole_samples(model)
        key = (model.name, parts)
        k = self._kernel_sets.get(key)
        if k is None:
            fast, volume_regs = self.tuning.fast_math, self.tuning.volume_max_registers
            regs = own if self.tuning.max_registers is None else self.tuning.max_registers
            k = raycast.kernels_for(model, fast, regs, volume_regs, parts, self._count_passes)
            self._kernel_sets[key] = k
        return k

    def _skeleton_buffers(self) -> _SkeletonBuffers:
        """The bond segments and graph of the topology on the device (built once per topology,
        with the bond lengths of the first frame)."""
        if self._skel is None:
            assert self._topology is not None
            self._skeleton = Skeleton.of(self._topology)
            ref = self._ref_positions if self._ref_positions is not None else np.zeros((self._n, 3))
            self._skel = _SkeletonBuffers(self.device, self._skeleton, ref, self.tuning.grid_sort)
        return self._skel

    def _update_weights(self, d: Derived) -> None:
        """The atoms' weights: uniform or electron counts, smoothed along the bond graph in
        carved mode (when the topology, the weights or the graph scale change)."""
        assert self._topology is not None
        graph = d.warp.graph if d.warp is not None else 0.0
        key = (d.weights, graph)
        if key == self._weights_key or not self._n:
            return
        base = colors.atom_weights(self._topology, d.weights)
        if graph <= 0.0:
            wp.copy(self._weights, wp.array(base, dtype=float, device="cpu"), count=self._n)
        else:
            skel = self._skeleton_buffers()
            skel.smooth(base, graph, self._weights)
        self._weights_key = key

    def set_colors(self, packed: npt.NDArray[np.uint32] | None) -> None:
        """Colours given from outside, (n,) packed RGBA8, drawn instead of the colouring the
        render parameters name (None: that colouring again). A sort-last part colours its atoms
        as the whole system does: chain ranks and the b-factor and charge ranges are the whole
        system's, not its part's."""
        if packed is not None and packed.shape != (self._n,):
            raise RenderError(f"colours for {packed.shape} atoms, the topology has {self._n}")
        self._given_colors = packed
        self._color_key = None

    def _update_colors(self, p: RenderParams) -> None:
        assert self._topology is not None
        given = self._given_colors
        if given is not None:
            if self._color_key != ("given", id(given)) and self._n:
                wp.copy(self._colors, wp.array(given, dtype=wp.uint32, device="cpu"), count=self._n)
                self._color_key = ("given", id(given))
            return
        motion = p.color_by == "motion" and self._temporal is not None
        if motion and self._temporal is not None and self._temporal.colors(self._colors):
            self._color_key = ("motion",)
            return
        key = (p.color_by, tuple(p.uniform_color))
        if key != self._color_key and self._n:
            c = colors.atom_colors(self._topology, p.color_by, p.uniform_color)
            wp.copy(self._colors, wp.array(c, dtype=wp.uint32, device="cpu"), count=self._n)
            self._color_key = key

    def _update_tf(self, p: RenderParams, d: Derived) -> None:
        """The transfer table of `p`, and its segments at this frame's volume step."""
        pts = tuple((q.x, tuple(q.color), q.alpha) for q in p.transfer_function)
        key = (pts, None if pts else p.tf_preset)  # control points replace the preset
        if key != self._tf_key:
            try:
                self._tf = transfer.build_table(p.transfer_function, p.tf_preset)
            except (ValueError, KeyError) as exc:
                raise RenderError(f"invalid transfer function: {exc}") from None
            wp.copy(self._tf_table, wp.array(self._tf.rgba, dtype=wp.vec4, device="cpu"))
            self._tf_key = key
        seg_key = (key, self._volume_dt(d))
        if seg_key != self._seg_key:
            if self._seg_table is None:
                size = transfer.TABLE_SIZE
                self._seg_table = wp.empty((size, size), dtype=wp.vec4, device=self.device)
            segments.build(self._tf_table, self._volume_dt(d), self._seg_table)
            self._seg_key = seg_key

    def _volume_dt(self, d: Derived) -> float:
        """Volume mode's lattice step: `volume_steps` steps of the iso lattice."""
        return d.dt * self.tuning.volume_steps

    def _flat_level(self, d: Derived) -> float:
        """The density at and below which the transfer function is clear (-1: none)."""
        c = self._tf.clear_below
        return -1.0 if c < 0 else (math.inf if math.isinf(c) else c * d.iso)

    def _stop_level(self, p: RenderParams, d: Derived) -> float:
        """Density level the cell bounds are compared with (-1: no skipping)."""
        if not self.tuning.empty_space_skipping:
            return -1.0
        if p.mode == "iso":
            return d.iso
        return self._flat_level(d)

    def _cells_for(self, d: Derived) -> float:
        """Cells per cutoff of this frame's grid: the renderer's, else the density's best."""
        if self.tuning.cells_per_cutoff is not None:
            return self.tuning.cells_per_cutoff
        if self._n >= LARGE_ATOMS:
            return 1.0
        return CELLS_PER_CUTOFF[_model_name(d)]

    def _keep_from(self, d: Derived, parts: PartMode) -> float:
        """The multiple of the level from which empty cells keep their coarse bound (with
        part bounds in every open cell, all are walked: the parts of the cells near the atoms
        save the most samples)."""
        if self.tuning.bound_keep_from is not None:
            return self.tuning.bound_keep_from
        return math.inf if parts == "all" else BOUND_KEEP_FROM[_model_name(d)]

    def _grid_key_for(
        self, d: Derived, stop: float, mode: str, cull: tuple[Any, Cull] | None = None
    ) -> tuple[Any, ...] | None:
        """The key of the grid this frame needs (render mode `mode`; `cull`: the key and
        planes of a culled tile's grid), or None when the last one still holds."""
        key = self._grid_key_with(d, stop, self._parts_for(d, mode), cull)
        return None if key == self._grid_key else key

    def _grid_key_with(
        self, d: Derived, stop: float, parts: PartMode | None, cull: tuple[Any, Cull] | None
    ) -> tuple[Any, ...]:
        key: tuple[Any, ...] = (self._positions_version, d, self._cells_for(d), stop, parts)
        return key if cull is None else (*key, cull[0])

    def _choose_parts(
        self, d: Derived, mode: str, stop: float, cull: tuple[Any, Cull] | None, setup: Any
    ) -> None:
        """This frame's part choice (`_frame_parts`) when the renderer is on trial: a frame
        that builds its grid anyway takes its turn in the set-up's trial (or the trial's
        choice); a frame whose grid holds (still positions, the same set-up) keeps the grid's
        choice, as a turn would rebuild it only to time a build the frames after it do not
        pay, unless the rule of sizes changed on these positions (many views)."""
        self._frame_parts = self._frame_rule = None
        trial = self._part_trial
        if trial is None:
            return
        trial.skip()  # no time of an earlier frame is this one's
        if not self._n or self._n >= TRIAL_ATOMS or self._model_of(d).part_bounds is None:
            return
        rule = self._parts_by_size(d, mode)
        key = (setup, self._topology_version, rule)
        held = self._grid_parts
        choice: PartMode
        if held is not None and self._grid_key_with(d, stop, held, cull) == self._grid_key:
            choice = held if rule == self._grid_rule else trial.chosen(key) or rule
        else:
            choice = trial.mode(key, rule)
        self._frame_parts, self._frame_rule = (d, mode, choice), rule

    def _cull_for(
        self, d: Derived, frame: CameraFrame, camera_key: tuple[Any, ...], tile: Any
    ) -> tuple[Any, Cull] | None:
        """The culled grid of a tile (`cull_to_tile`): its key and the planes of its rows'
        rays, one row wider on each side, kept within the cutoff reach plus the ambient
        occlusion's farthest sample (four steps)."""
        if not self.cull_to_tile or tile is None or d.warp is not None:
            return None
        y0, rows = tile[1], tile[3]
        top, bottom = band_planes(frame, y0 - 1.0, y0 + rows + 1.0)
        c = Cull()
        c.planes = 2
        c.top = wp.vec4(*(float(v) for v in top))
        c.bottom = wp.vec4(*(float(v) for v in bottom))
        c.margin = float(d.reach * (1.0 + 1.0e-3) + 4.0 * AO_STEP_SIGMAS * d.sigma + 1.0e-3)
        # a spline reads the grid 2 steps around it, and the prefilter spreads each value
        c.margin += geodesic_volume.REACH_STEPS * d.volume_h
        return (camera_key, y0, rows), c

    def _view_of(self, d: Derived, mode: str, stop: float, view: View) -> View | None:
        """`view` when this frame's cell bounds follow it ("visible" part bounds), else None."""
        visible = stop > 0.0 and self._parts_for(d, mode) == "visible"
        return view if visible else None

    def _unsorted(self, d: Derived) -> UnsortedAtoms:
        """The atoms in their original order, reached through the grid just built (the mean
        density at the sampled atoms is taken over them)."""
        u = UnsortedAtoms()
        u.positions = self._pos
        u.weights = self._weights
        u.radii = self._radii
        u.order = self._grid.order
        u.cell_start = self._grid.cell_start
        u.info = self._grid.info
        u.inv2s2_uniform = d.inv2s2
        u.sigma_per_radius = d.sigma_per_radius
        u.half_k2 = d.half_k2
        u.inv_half_k2 = 1.0 / d.half_k2 if self.tuning.taper else 0.0
        u.per_atom = d.per_atom
        return u

    def _build_grid(
        self,
        d: Derived,
        f: Any,
        stop: float,
        mode: str,
        view: View | None,
        cull: Cull | None = None,
    ) -> None:
        """Grid, sorted atoms (weights divided by the mean density at the atoms for relative
        levels), the carved density's segments, cell bounds and brick bounds: launches only.
        `view` (camera frame and tile) marks the cells whose part bounds are walked when the
        bounds follow the view."""
        dev = self.device
        n = self._n
        samples = min(n, MEAN_SAMPLES)
        stride = n // samples if d.relative else 0
        self._grid.build(self._pos, n, d.reach, self._cells_for(d), cull, stride)
        # the geodesic density takes its own mean once its atoms are gathered
        classical_mean = d.relative and d.geo is None
        if classical_mean:
            # the density's own scale, from the atoms in their original order through the
            # grid, so the gather below writes the scaled weights in one pass
            lanes = self._mean_lanes
            mean = (self._unsorted(d), n // samples, lanes, self._density_samples)
            wp.launch(mean_density_kernel, samples * lanes, mean, device=dev, block_dim=MEAN_BLOCK)
            partial = (self._density_samples, samples * lanes, self._density_partial)
            wp.launch(partial_sums_kernel, MEAN_LANES, partial, device=dev)
            wp.launch(total_kernel, 1, (self._density_partial, self._density_total), device=dev)
        wp.launch(
            gather_atoms_kernel,
            n,
            (
                self._pos,
                self._weights,
                self._radii,
                self._grid.order,
                d.sigma_per_radius,
                d.per_atom,
                self._density_total,
                float(samples),
                int(classical_mean),
                self._sorted,
                self._inv2s2,
            ),
            device=dev,
        )
        if d.warp is not None:
            self._skeleton_buffers().build(self._pos, d.warp.reach)
        if d.geo is not None:
            geo = f.geo if d.volume_h > 0.0 else f
            self._geodesic_tables().refresh(self._pos, self._weights, GAIN)
            if d.relative:
                lanes = self._geo_mean_lanes
                sampled = (geo, self._pos, n // samples, lanes, self._density_samples)
                wp.launch(
                    devmod.compiled(geodesic_field.sampled_values, self.tuning.fast_math),
                    samples * lanes,
                    sampled,
                    device=dev,
                    block_dim=MEAN_BLOCK,
                )
                partial = (self._density_samples, samples * lanes, self._density_partial)
                wp.launch(partial_sums_kernel, MEAN_LANES, partial, device=dev)
                wp.launch(total_kernel, 1, (self._density_partial, self._density_total), device=dev)
                scale = (self._sorted, self._density_total, float(samples), n)
                wp.launch(geodesic_field.rescale_kernel, n, scale, device=dev)
        kernels = self._kernels_of(d, mode)
        parts = self._parts_for(d, mode)
        # the widest atom's 1 / (2 s^2): reach = k s_max and half_k2 = k^2 / 2
        self._grid.build_coarse(self._sorted, d.half_k2 / (d.reach * d.reach))
        grid = self._grid
        grid.work_count.zero_()
        # with part bounds for the view, every cell first gets its whole-cell bound, and the
        # cells the view marks then walk for their parts
        whole = parts != "all"
        keep = stop * self._keep_from(d, parts) if stop > 0.0 else math.inf
        threads = cell_threads(grid.capacity)
        cells = (grid.cell_start, grid.coarse, f.bound, grid.parts)
        settle = (f, stop, keep, threads, *cells, grid.work, grid.work_count)
        wp.launch(
            kernels.whole_settle if whole else kernels.bound_settle, threads, settle, device=dev
        )
        if whole:
            walk = (f, stop, threads, grid.work, grid.work_count, f.bound, grid.parts)
            wp.launch(kernels.whole_bound, threads, walk, device=dev)
        else:
            self._walk_listed_parts(kernels, f, stop, threads)
        if d.geo is not None and d.volume_h > 0.0:
            # after the cell bounds, which the grid's gate reads first
            cut = geodesic_volume.CUT * stop if stop > 0.0 else 0.0
            self._geodesic_volume().build(f.geo, self._grid.info, d.volume_h, cut)
        if view is not None:
            self._walk_view(kernels, f, stop, view)
        self._grid.build_bricks()

    def _walk_view(self, kernels: raycast.RaycastKernels, f: Any, stop: float, view: View) -> None:
        """Walk the parts of the cells `view` reaches that no view before it reached since
        the grid was built (visibility.py); the caller then updates the brick bounds."""
        dev = self.device
        grid = self._grid
        frame, tile = view
        cam = raycast.camera_data(frame, tile)
        stride = visibility.stride_for(frame.width, frame.height)
        cols, rows = visibility.rays(cam.width, cam.height, stride)
        grid.work_count.zero_()
        marks = (grid.info, cam, stride, cols, rows, visibility.DEPTH, stop, grid.cell_start)
        args = (*marks, f.bound, grid.parts, grid.work, grid.work_count)
        wp.launch(visibility.mark_kernel, cols * rows, args, device=dev)
        threads = min(cell_threads(grid.capacity), int(grid.work.shape[0]))
        self._walk_listed_parts(kernels, f, stop, threads)

    def _bound_lanes(self, kernels: raycast.RaycastKernels) -> int:
        """Threads a listed cell's part walk takes (`Tuning.bound_lanes`; one on the CPU,
        whose tiles are one thread wide: there a block's other lanes would be lost)."""
        if kernels.bound_lanes is None or not self._cuda:
            return 1
        if self.tuning.bound_lanes is not None:
            return self.tuning.bound_lanes
        return BOUND_LANES if self._grid.lists_own_cells else 1

    def _walk_listed_parts(
        self, kernels: raycast.RaycastKernels, f: Any, stop: float, threads: int
    ) -> None:
        """Walk the parts of the cells the grid lists, `threads` threads in all: one a cell,
        or `_bound_lanes` a cell in blocks of that many."""
        grid = self._grid
        listed = (grid.work, grid.work_count, f.bound, grid.parts)
        lanes = self._bound_lanes(kernels)
        if lanes == 1:
            wp.launch(kernels.bound, threads, (f, stop, threads, *listed), device=self.device)
            return
        blocks = max(threads // lanes, 1)
        wp.launch_tiled(
            kernels.bound_lanes,
            dim=[blocks],
            inputs=[f, stop, blocks, lanes, *listed],
            block_dim=lanes,
            device=self.device,
        )

    def _shading(self, p: RenderParams, d: Derived, frame: CameraFrame) -> raycast.Shading:
        step = AO_STEP_SIGMAS * d.sigma
        return raycast.shading(p, frame, iso=d.iso, ao_step=step, coverage=self.coverage)

    def _launch_frame(
        self,
        params: RenderParams,
        d: Derived,
        f: GaussianField,
        stop: float,
        frame: CameraFrame,
        build: bool,
        tile: tuple[int, int, int, int] | None = None,
        view: View | None = None,
        walk_view: bool = False,
        cull: Cull | None = None,
    ) -> float:
        """Every device operation of one frame after the upload, in order: the same calls run
        eagerly or into a graph capture. Returns the host time at the grid/cast boundary.
        `view`: the view the cell bounds follow (`_view_of`); `walk_view`: the grid stays,
        and the cells this view adds walk for their parts."""
        dev = self.device
        k = self._kernels_of(d, params.mode)
        if build:
            self._build_grid(d, f, stop, params.mode, view, cull)
        elif walk_view and view is not None:
            self._walk_view(k, f, stop, view)
            self._grid.build_bricks()
        if self._cuda:
            self._stream.record_event(self._events[1])
        t_cast = time.perf_counter()
        w, h = (tile[2], tile[3]) if tile is not None else (frame.width, frame.height)
        cam = raycast.camera_data(frame, tile, self.region, self.scene_box)
        m = raycast.March()
        m.iso = d.iso
        m.dt = d.dt
        m.skip_below = stop if params.mode == "iso" else -1.0
        passes = self.tuning.refine_passes
        m.refine = raycast.REFINE_PASSES if passes is None else passes
        m.budget = self._budget_for(w * h)
        sh = self._shading(params, d, frame)
        threads = raycast.launch_size(w, h)

        def cam_run() -> raycast.CameraData:
            return raycast.camera_data(frame, tile, self.region, self.scene_box)

        runs = self._ray_runs(threads, cam, m.budget, cam_run)
        if params.mode == "iso":
            hits = (self._hit_k, self._hit_v)
            queued = (*hits, self._queue, self._queue_v, self._queue_len, self._found)
            if m.budget > 0:
                self._queue_len.zero_()
            march = (f, cam, m, *queued, self._counts)
            self._launch_rays(
                k.iso_march, runs, lambda c: (f, c, m, *queued, self._counts, 0), MARCH_BLOCK
            )
            if m.budget > 0 and self.tuning.split_lanes > 1:
                lanes = self.tuning.split_lanes
                rays = min(w * h, SPLIT_RAYS)
                args = (*march, lanes, rays)
                wp.launch(k.iso_split, lanes * rays, args, device=dev, block_dim=MARCH_BLOCK)
            elif m.budget > 0:
                wp.launch(k.iso_march, threads, (*march, 1), device=dev, block_dim=MARCH_BLOCK)
            self._launch_rays(
                k.iso_shade,
                runs,
                lambda c: (f, c, m, sh, *hits, self._rgba, self._depth, self._ids),
            )
        else:
            assert self._seg_table is not None  # made by _update_tf
            m.dt = self._volume_dt(d)
            vol = raycast.Volume()
            vol.seg = self._seg_table
            vol.last = transfer.TABLE_SIZE - 1
            vol.x_to_u = (transfer.TABLE_SIZE - 1) / (self._tf.x_max * d.iso)
            vol.flat = self._flat_level(d)
            vol.ramps = int(self.tuning.volume_ramps)
            vol.clear_level = stop
            lt = params.lighting
            vol.shade = int(lt.diffuse > 0 or lt.specular > 0)
            vol.clip = int(self.depth_limit is not None)
            vol.limit = self._no_limit if self.depth_limit is None else self.depth_limit
            out = (self._rgba, self._depth, self._ids, self._counts)
            self._launch_rays(k.volume, runs, lambda c: (f, c, m, vol, sh, *out), MARCH_BLOCK)
        return t_cast

    def _ray_runs(
        self,
        threads: int,
        cam: raycast.CameraData,
        budget: int,
        cam_run: Callable[[], raycast.CameraData],
    ) -> list[tuple[int, raycast.CameraData]]:
        """(threads, camera) of each launch of a pass over the image's rays: one launch on
        CUDA, or where the march queues rays for a second kernel (the queue holds a launch's
        own thread numbers); on the CPU device, which runs a launch on the thread that makes
        it, runs of whole 8x4 tiles (`device.RUNS_PER_HOST_THREAD` a host thread), each with
        a camera (`cam_run`) that says its first tile: each pixel is its run's alone."""
        n = self._host_threads
        tiles = threads // raycast.TILE
        if self._cuda or n <= 1 or budget > 0 or tiles < 2 * n:
            return [(threads, cam)]
        runs = []
        for lo, hi in devmod.run_cuts(tiles, n):
            c = cam_run()
            c.first_tile = lo
            runs.append(((hi - lo) * raycast.TILE, c))
        return runs

    def _launch_rays(
        self,
        kernel: Any,
        runs: list[tuple[int, raycast.CameraData]],
        args_of: Callable[[raycast.CameraData], tuple[Any, ...]],
        block_dim: int | None = None,
    ) -> None:
        """`kernel` over the image's rays as `runs` (`_ray_runs`) gives them: one launch, or
        runs on the host threads (`device.split_launch`)."""
        launches = [(threads, args_of(c)) for threads, c in runs]
        devmod.split_launch(kernel, launches, self.device, self._host_threads, block_dim)

    def _budget_for(self, pixels: int) -> int:
        """Passes before an iso ray is queued for the split second kernel (0: one kernel)."""
        if self.tuning.march_budget is not None:
            return self.tuning.march_budget
        small = pixels <= SPLIT_PIXELS_PER_SM * int(getattr(self._dev, "sm_count", 0) or 0)
        return MARCH_BUDGET if self._cuda and small and self._n >= SPLIT_MIN_ATOMS else 0

    def _replay_or_launch(self, key: tuple[Any, ...], launch: Callable[[], float]) -> float:
        """Replay the frame's graph when one exists for exactly these launches, capture
        one when the same launches were among the last few (a streamed trajectory, a still
        camera, viewers taking turns with their own cameras), else launch eagerly
        (`server.render.graphs`); the time the cast was launched."""
        launched = self._graphs.run(key, launch)
        return time.perf_counter() if launched is None else launched

    def _drop_graphs(self) -> None:
        """Graphs hold buffer addresses: forget them when buffers are reallocated."""
        self._graphs.clear()

    def render(
        self,
        params: RenderParams,
        camera: Camera,
        width: int,
        height: int,
        tile: tuple[int, int, int, int] | None = None,
        *,
        wait: bool = True,
    ) -> None:
        """Render one image; it stays on the device (read it with `read_rgba` and friends).
        `tile` (x0, y0, w, h) renders only that rectangle of the width x height image, exactly
        as the whole image would have it (the outputs are then w x h). `wait=False` returns
        once the work is queued: the next frame's `set_positions` then uploads while this one
        renders, and `finish` waits for it (reading an output waits too).

        Raises RenderError for invalid input before launching anything."""
        self.finish()
        t_start = time.perf_counter()
        w, h = self._check_size(width, height)
        if tile is not None:
            x0, y0, tw, th = (int(v) for v in tile)
            if tw < 1 or th < 1 or x0 < 0 or y0 < 0 or x0 + tw > w or y0 + th > h:
                raise RenderError(f"tile {tile} is not inside the {w}x{h} image")
            tile = (x0, y0, tw, th)
        seen = self._params_seen
        if seen is None or seen[0] is not params:
            self._check_params(params)
            seen = self._params_seen = (params, params.model_dump_json())
        cam_seen = self._camera_seen
        if cam_seen is None or cam_seen[0] is not camera or cam_seen[1:3] != (w, h):
            frame = self._check_camera(camera, w, h)
            cam_seen = self._camera_seen = (camera, w, h, frame, frame.key())
        frame = cam_seen[3]
        if self._n and not self._have_positions:
            raise RenderError("no positions: call set_positions after set_topology")
        if self._upload_open is not None:
            raise RenderError("a frame uploaded in part: receive the rest before rendering")
        d = self._derive(params)
        if params.mode == "volume":
            self._update_tf(params, d)
        self._apply_temporal(params)
        if self._n:
            self._update_colors(params)
            self._update_weights(d)
            self._update_geodesic(d)
        pw, ph = (tile[2], tile[3]) if tile is not None else (w, h)
        # the whole image's pixels: a tile's device lays the grid over every atom all the same
        d = self._plan_volume(d, w * h)
        self._alloc_pixels(pw * ph)
        stop = self._stop_level(params, d)
        f = self._field(d)
        ev = self._events if self._cuda else None
        self._count_view(d, cam_seen[4])
        cull = self._cull_for(d, frame, cam_seen[4], tile)
        setup = (d, params.mode, w, h, tile, self._n, self.region)
        self._choose_parts(d, params.mode, stop, cull, setup)
        grid_key = self._grid_key_for(d, stop, params.mode, cull) if self._n else None
        # a grid with part bounds for the view walks the cells each new view adds
        view = self._view_of(d, params.mode, stop, (frame, tile)) if self._n else None
        walk_view = False
        if view is not None:
            current = grid_key if grid_key is not None else self._grid_key
            on, walked = self._views_walked
            # a grid built again under the key it had (a part choice back) walked no view
            if on != current or grid_key is not None or len(walked) >= VIEWS_KEPT:
                walked = set()
                self._views_walked = (current, walked)
            view_key = (cam_seen[4], tile)
            walk_view = view_key not in walked
            walked.add(view_key)
        if not self._n:
            self._grid.invalidate()
            self._grid_key = None

        if ev is not None:
            self._stream.record_event(ev[0])
        t_grid = time.perf_counter()
        launch = functools.partial(
            self._launch_frame,
            params,
            d,
            f,
            stop,
            frame,
            grid_key is not None,
            tile,
            view,
            walk_view,
            None if cull is None else cull[1],
        )
        if grid_key is not None:
            self._grid_key = None  # a build that fails part way leaves no grid to reuse
        if self._graphs.enabled:
            clipped = params.mode == "volume" and self.depth_limit is not None
            limit = self.depth_limit.ptr if clipped else None
            # graphs hold the address of the positions they read
            parts = self._parts_for(d, params.mode)
            key: tuple[Any, ...] = (grid_key is not None, walk_view, parts, self._n, d, stop)
            key = (*key, seen[1])
            key = (*key, cam_seen[4], tile, limit, self._pos.ptr, self.region, self.scene_box)
            t_cast = self._replay_or_launch(key, launch)
        else:
            t_cast = launch()
        if grid_key is not None:
            self._held_grid(grid_key, d, params.mode)
        front = 0 if self._pos is self._pos_buffers[0] else 1
        if ev is not None:
            self._stream.record_event(ev[2])
            self._stream.record_event(self._release[front])
            self._released[front] = True
        self._pending = (t_start, t_grid, t_cast, self._uploaded, front)
        self._uploaded = False
        self._image = (pw, ph)
        self._last = (params, d)
        if wait:
            self.finish()

    def _held_grid(self, key: tuple[Any, ...], d: Derived, mode: str) -> None:
        """The grid of `key` is built: it holds until its key changes."""
        self._grid_key = key
        self._grid_parts = self._parts_for(d, mode)
        self._grid_rule = self._frame_rule

    @property
    def last_density(self) -> str | None:
        """The density model the last frame drew (`geodesic_volume` when the geodesic density
        was read from its grid; None before any)."""
        return None if self._last is None else self._model_of(self._last[1]).name

    @property
    def last_parts(self) -> PartMode | None:
        """Which cells the last frame walked for part bounds (`_parts_for`; None before any)."""
        return None if self._last is None else self._parts_for(self._last[1], self._last[0].mode)

    @property
    def pipelined(self) -> bool:
        """Positions set while a render is queued (`render(wait=False)`) upload during it: a
        CUDA renderer with two positions buffers (`double_buffer`, or from `PIPELINE_ATOMS`)."""
        return self._cuda and len(self._pos_buffers) > 1

    def finish(self) -> None:
        """Wait for the last `render` and take its stage times (`timings`)."""
        if self._pending is None:
            return
        t_start, t_grid, t_cast, uploaded, front = self._pending
        self._pending = None
        if self._cuda:
            ev = self._events
            wp.synchronize_event(ev[2])
            grid_ms = wp.get_event_elapsed_time(ev[0], ev[1])
            cast_ms = wp.get_event_elapsed_time(ev[1], ev[2])
            up0, up1 = self._upload_events[front]
            up_ms = wp.get_event_elapsed_time(up0, up1) if uploaded else 0.0
            total = wp.get_event_elapsed_time(up0 if uploaded else ev[0], ev[2])
        else:
            t_end = time.perf_counter()
            grid_ms = (t_cast - t_grid) * 1e3
            cast_ms = (t_end - t_cast) * 1e3
            up_ms = self._upload_ms if uploaded else 0.0
            total = up_ms + (t_end - t_start) * 1e3
        self.timings = {"upload": up_ms, "grid": grid_ms, "raycast": cast_ms, "total": total}
        if self._part_trial is not None:
            self._part_trial.timed(grid_ms + cast_ms)

    # ------------------------------------------------------------------ outputs

    def _outputs(self) -> tuple[wp.array, wp.array, wp.array]:
        return self._rgba, self._depth, self._ids

    def read_pass_counts(self) -> npt.NDArray[np.int32]:
        """(height, width) int32: the density passes (of four samples each) every ray of the
        last image took: in iso mode to its crossing (the shading kernel's refinement is not
        counted), in volume mode to its end. Rays split over several threads
        (`march_budget`, `split_lanes`) also count the passes their lanes took past the
        crossing, which depend on the lanes' timing. Needs `count_passes=True`."""
        if not self._count_passes:
            raise RenderError("pass counts need a Renderer made with count_passes=True")
        counts: npt.NDArray[np.int32] = self._read(self._counts).astype(np.int32)
        return counts

    def pick(self, x: int, y: int) -> tuple[int | None, float | None]:
        """Atom id and depth at pixel (x from the left, y from the top) of the last image."""
        w, h = self._need_image()
        if not (0 <= int(x) < w and 0 <= int(y) < h):
            raise RenderError(f"pixel ({x}, {y}) outside the {w}x{h} image")
        i = int(y) * w + int(x)
        atom = int(self._ids[i : i + 1].numpy()[0])
        depth = float(self._depth[i : i + 1].numpy()[0])
        if atom < 0 or not math.isfinite(depth):
            return None, None
        return atom, depth

    def prepare(self, params: RenderParams) -> Any:
        """Build the grid for `params` (when positions or the density changed) and return the
        device field, for tools that evaluate the density with their own kernels."""
        self._check_params(params)
        if self._n and not self._have_positions:
            raise RenderError("no positions: call set_positions after set_topology")
        d = self._derive(params)
        if params.mode == "volume":
            self._update_tf(params, d)
        self._apply_temporal(params)
        if self._n:
            self._update_colors(params)
            self._update_weights(d)
            self._update_geodesic(d)
        f = self._field(d)
        stop = self._stop_level(params, d)
        if not (self._n and self._have_positions):
            self._grid.invalidate()
            self._grid_key = None
        else:
            key = self._grid_key_for(d, stop, params.mode)
            if key is not None:
                self._grid_key = None  # a build that fails part way leaves no grid to reuse
                self._build_grid(d, f, stop, params.mode, None)
                self._held_grid(key, d, params.mode)
        self._last = (params, d)
        return f

    def density_scale(self) -> float:
        """The density's own scale in the last grid: the mean density at the sampled atoms that
        relative levels are fractions of (1 for absolute levels); synchronises."""
        if self._last is None or not self._last[1].relative or not self._n:
            return 1.0
        samples = min(self._n, MEAN_SAMPLES)
        return float(self._density_partial.numpy().astype(np.float64).sum()) / samples

    def grid_info(self) -> dict[str, Any]:
        """The last grid's layout (origin, cell size, dims, ...); synchronises."""
        return self._grid.read_info()

    def evaluate(
        self, points: npt.ArrayLike
    ) -> tuple[
        npt.NDArray[np.float32],
        npt.NDArray[np.float32],
        npt.NDArray[np.float32],
        npt.NDArray[np.int32],
    ]:
        """Density, (gradient, density), (colour, density) and top atom at points, through
        the same device functions the ray caster uses (for tests and tools)."""
        if self._last is None:
            raise RenderError("render once before evaluating the density")
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        m = len(pts)
        dev = self.device
        wp_pts = wp.array(pts, dtype=wp.vec3, device=dev)
        vals = wp.zeros(max(m, 1), dtype=float, device=dev)
        vgs = wp.zeros(max(m, 1), dtype=wp.vec4, device=dev)
        cols = wp.zeros(max(m, 1), dtype=wp.vec4, device=dev)
        ids = wp.zeros(max(m, 1), dtype=wp.int32, device=dev)
        if m:
            params, d = self._last
            f = self._field(d)
            kernels = self._kernels_of(d, params.mode)
            wp.launch(kernels.evaluate, m, (f, wp_pts, vals, vgs, cols, ids), device=dev)
        return (
            vals.numpy()[:m].copy(),
            vgs.numpy()[:m].copy(),
            cols.numpy()[:m].copy(),
            ids.numpy()[:m].copy(),
        )

    def density_histogram(
        self, bins: int = 64
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """Counts and bin edges of the density (in units of the iso level, the transfer
        function's x) at a 64^3 lattice of points over the last frame's grid box. Zero density
        is left out; values beyond the last edge count in the last bin."""
        if not 1 <= int(bins) <= self._hist.shape[0]:
            raise RenderError(f"bins must be in [1, {self._hist.shape[0]}], got {bins}")
        bins = int(bins)
        if self._last is None:
            raise RenderError("render once before asking for a histogram")
        params, d = self._last
        x_hi = max(HISTOGRAM_X_MAX, self._tf.x_max if params.mode == "volume" else 0.0)
        edges = np.linspace(0.0, x_hi, bins + 1)
        self._hist.zero_()
        if self._n and self._have_positions:
            f = self._field(d)
            s = HISTOGRAM_SIDE
            wp.launch(
                self._kernels_of(d, params.mode).histogram,
                (s, s, s),
                (f, s, bins / (x_hi * d.iso), bins, self._hist),
                device=self.device,
            )
        counts = self._hist.numpy()[:bins].astype(np.int64)
        return counts, edges


class _SkeletonBuffers:
    """The carved density's device tables for one topology: the segments (and their cell
    grid, rebuilt every frame) and the bond graph for the along-graph smoothing."""

    def __init__(
        self, device: str, skeleton: Skeleton, reference: npt.ArrayLike, sort: str = "counting"
    ) -> None:
        self.device = device
        self.skeleton = skeleton
        self.reference = np.asarray(reference, dtype=np.float64)
        m = len(skeleton.segments)
        self.count = m
        self.ends = wp.array(skeleton.segments, dtype=wp.vec2i, device=device)
        self.mids = wp.zeros(max(m, 1), dtype=wp.vec3, device=device)
        self.seg_a = wp.zeros(max(m, 1), dtype=wp.vec4, device=device)
        self.seg_b = wp.zeros(max(m, 1), dtype=wp.vec4, device=device)
        self.grid = CellGrid(device, m, sort)
        self.grid.invalidate()
        self.half_length = 0.5 * SEGMENT_SLACK * skeleton.max_segment(self.reference)
        self.adj_start = wp.array(skeleton.adj_start, dtype=wp.int32, device=device)
        self.adj_atom = wp.array(skeleton.adj_atom, dtype=wp.int32, device=device)
        self.cells = wp.array(skeleton.cell_weights(self.reference), dtype=float, device=device)

    @property
    def nbytes(self) -> int:
        arrays = (self.ends, self.mids, self.seg_a, self.seg_b, self.adj_start, self.adj_atom)
        return sum(int(a.capacity) for a in arrays) + int(self.grid.nbytes)

    def build(self, positions: wp.array, reach: float) -> None:
        """Segments from this frame's positions into the cells of their midpoints."""
        if not self.count:
            self.grid.invalidate()
            return
        dev = self.device
        args = (positions, self.ends, self.mids)
        wp.launch(carved.segment_mids_kernel, self.count, args, device=dev)
        self.grid.build(self.mids, self.count, reach + self.half_length, 2.0)
        gather = (positions, self.ends, self.grid.order, self.seg_a, self.seg_b)
        wp.launch(carved.gather_segments_kernel, self.count, gather, device=dev)

    def smooth(self, densities: npt.NDArray[np.float32], scale: float, out: wp.array) -> None:
        """dt: `densities` smoothed along the bond graph at warped scale `scale`, into `out`."""
        sk = self.skeleton
        n = sk.n_atoms
        lengths = sk.warped_lengths(self.reference, densities)
        along = lengths[sk.adj_bond].astype(np.float32)
        adj_length = wp.array(along, dtype=float, device=self.device)
        dens = wp.array(np.asarray(densities, dtype=np.float32), dtype=float, device=self.device)
        args = (
            self.adj_start,
            self.adj_atom,
            adj_length,
            self.cells,
            dens,
            float(scale),
            float(GRAPH_CUTOFF_SIGMAS * scale),
            out,
        )
        wp.launch(carved.smooth_densities_kernel, n, args, device=self.device)
