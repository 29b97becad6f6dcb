"""Layers: parts of one system, each drawn at its own scale, combined into one image.

A layer is a set of atoms (the server evaluates its selection) and the parameters it is drawn
with. Each layer is ray-cast by a `Renderer` of its own that holds only the layer's atoms, so
hidden atoms (solvent in a water box) cost their upload from the simulation and nothing in
the grid or the march. Every layer image keeps its depth and coverage (`Renderer.coverage`);
one compositing kernel then orders the layers per pixel by depth and blends front to back:
an opaque surface hides every layer behind it (two overlapping iso layers give the nearer hit),
translucent layers blend over what lies behind them, and the pick buffer holds the front
layer's atom as an index into the whole system, with the layer beside it.

Clouds (volume layers) are cast last: each stops at the nearest opaque surface of the other
layers, so a cloud around a surface shows only its part in front of it, blended over the
surface. A cloud is then placed by the depth where its opacity first reaches the caster's
depth threshold; two clouds, or a cloud and a translucent surface, that interleave along a ray
blend as wholes in that order.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp

from protocol import MAX_LAYERS, Camera, RenderParams, Topology
from server.render.errors import RenderError
from server.render.geometry import GeometryRenderer
from server.render.layerplan import LayerPlan, subset_topology
from server.render.outputs import ImageOutputs
from server.render.renderer import Renderer

wp: Any = warp

_HISTORY_KEEP = 80
"""Per layer, the gathered history frames kept for reuse (the longest smoothing window + a
margin)."""


@wp.kernel(enable_backward=False)
@no_type_check
def composite_kernel(
    rgba: wp.array2d(dtype=wp.uint32),
    depth: wp.array2d(dtype=float),
    ids: wp.array2d(dtype=wp.int32),
    opacity: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    index_map: wp.array(dtype=wp.int32),
    layers: int,
    background: wp.vec3,
    out_rgba: wp.array(dtype=wp.uint32),
    out_depth: wp.array(dtype=float),
    out_ids: wp.array(dtype=wp.int32),
    out_layer: wp.array(dtype=wp.int32),
):
    """Blend one pixel's layers front to back in depth order (premultiplied colours)."""
    pix = wp.tid()
    acc = wp.vec3(0.0, 0.0, 0.0)
    alpha = float(0.0)
    used = wp.int32(0)  # bit mask of the layers blended so far
    front = wp.int32(-1)
    for _ in range(layers):
        # the nearest layer not blended yet (ties: the earlier layer)
        best = wp.int32(-1)
        best_t = float(wp.inf)
        for k in range(layers):
            if (used & (wp.int32(1) << k)) == 0:
                t = depth[k, pix]
                if best < 0 or t < best_t:
                    best = k
                    best_t = t
        used = used | (wp.int32(1) << best)
        c = rgba[best, pix]
        a = float((c >> wp.uint32(24)) & wp.uint32(255)) / 255.0 * opacity[best]
        if a > 0.0:
            col = wp.vec3(
                float(c & wp.uint32(255)),
                float((c >> wp.uint32(8)) & wp.uint32(255)),
                float((c >> wp.uint32(16)) & wp.uint32(255)),
            ) * (opacity[best] / 255.0)
            acc += col * (1.0 - alpha)
            if front < 0 and best_t < wp.inf:
                front = best
            alpha += a * (1.0 - alpha)
    acc += background * (1.0 - alpha)
    r = wp.uint32(wp.clamp(acc[0], 0.0, 1.0) * 255.0 + 0.5)
    g = wp.uint32(wp.clamp(acc[1], 0.0, 1.0) * 255.0 + 0.5)
    b = wp.uint32(wp.clamp(acc[2], 0.0, 1.0) * 255.0 + 0.5)
    out_rgba[pix] = (
        r | (g << wp.uint32(8)) | (b << wp.uint32(16)) | (wp.uint32(255) << wp.uint32(24))
    )
    out_layer[pix] = front
    if front < 0:
        out_depth[pix] = wp.inf
        out_ids[pix] = -1
    else:
        out_depth[pix] = depth[front, pix]
        local = ids[front, pix]
        atom = local
        base = offsets[front]
        if local >= 0 and base >= 0:
            atom = index_map[base + local]
        out_ids[pix] = atom


@wp.kernel(enable_backward=False)
@no_type_check
def nearer_kernel(depth: wp.array(dtype=float), limit: wp.array(dtype=float)):
    """limit = min(limit, depth): the nearest opaque surface so far, per pixel."""
    i = wp.tid()
    limit[i] = wp.min(limit[i], depth[i])


MAX_RUNS = 512
"""A selection in at most this many contiguous runs (a protein, a chain, a ligand: the usual)
is gathered by slices; a scattered one by `np.take`."""


def contiguous_runs(atoms: npt.NDArray[np.int32]) -> npt.NDArray[np.int64] | None:
    """(k, 2) start/stop of the runs of consecutive indices in sorted `atoms`; None when
    there are more than MAX_RUNS."""
    if not len(atoms):
        return np.zeros((0, 2), dtype=np.int64)
    breaks = np.flatnonzero(np.diff(atoms) != 1) + 1
    if len(breaks) + 1 > MAX_RUNS:
        return None
    starts = np.concatenate([[0], breaks])
    stops = np.concatenate([breaks, [len(atoms)]])
    return np.stack([atoms[starts], atoms[stops - 1] + 1], axis=1).astype(np.int64)


def gather_into(
    positions: npt.NDArray[np.float32],
    atoms: npt.NDArray[np.int32],
    runs: npt.NDArray[np.int64] | None,
    out: npt.NDArray[np.float32],
) -> None:
    """out[:] = positions[atoms], by slices when the atoms lie in a few runs."""
    if runs is None:
        np.take(positions, atoms, axis=0, out=out)
        return
    at = 0
    for start, stop in runs:
        n = int(stop - start)
        out[at : at + n] = positions[start:stop]
        at += n


def _same_codes(a: npt.NDArray[np.uint8] | None, b: npt.NDArray[np.uint8] | None) -> bool:
    return a is b or (a is not None and b is not None and np.array_equal(a, b))


def _is_cloud(plan: LayerPlan) -> bool:
    return plan.style == "density" and plan.params.mode == "volume"


@dataclass
class _Child:
    renderer: Renderer | GeometryRenderer
    style: str = "density"
    secondary: Any = None
    runs: npt.NDArray[np.int64] | None = None
    """The layer's atoms as contiguous runs (start, stop) in the frame, when there are few."""
    atoms_key: Any = None
    topology_id: int = -1
    positions_id: int = -1
    gathered: dict[int, npt.NDArray[np.float32]] = field(default_factory=dict)


class LayeredRenderer(ImageOutputs):
    """Renders a list of `LayerPlan`s into one image (one `Renderer` per layer position,
    kept with its atoms and buffers between frames) and answers like a `Renderer`:
    `read_rgba`, `read_depth`, `read_atom_ids`, `read_layers`, `pick`, `timings`."""

    def __init__(self, make: Callable[[], Renderer]) -> None:
        self._make = make
        self._children: list[_Child] = []
        self.device = ""
        self.timings: dict[str, float] = {}
        self._image: tuple[int, int] | None = None
        self._pixels = 0
        self._plans: tuple[LayerPlan, ...] = ()
        self._map_key: tuple[Any, ...] | None = None

    def _child(self, k: int, style: str = "density") -> _Child:
        """The renderer of layer position `k`, of the kind `style` draws with."""
        while len(self._children) <= k:
            r = self._make()
            r.coverage = True
            self.device = r.device
            self._children.append(_Child(r))
        child = self._children[k]
        if child.style != style:
            made: Renderer | GeometryRenderer
            if style == "density":
                made = self._make()
            else:
                made = GeometryRenderer(self.device, "tube" if style == "tube" else "licorice")
            made.coverage = True
            child = self._children[k] = _Child(made, style)
        return child

    def _alloc(self, layers: int, pixels: int) -> None:
        dev = self.device
        if pixels > self._pixels or not hasattr(self, "_out_rgba"):
            self._pixels = max(pixels, 1)
            self._limit = wp.zeros(self._pixels, dtype=float, device=dev)
            self._out_rgba = wp.zeros(self._pixels, dtype=wp.uint32, device=dev)
            self._out_depth = wp.zeros(self._pixels, dtype=float, device=dev)
            self._out_ids = wp.zeros(self._pixels, dtype=wp.int32, device=dev)
            self._out_layer = wp.zeros(self._pixels, dtype=wp.int32, device=dev)
            self._stack_shape = (0, 0)
        shape = (max(layers, 1), self._pixels)
        if self._stack_shape != shape:
            self._stack_rgba = wp.zeros(shape, dtype=wp.uint32, device=dev)
            self._stack_depth = wp.full(shape, float("inf"), dtype=float, device=dev)
            self._stack_ids = wp.full(shape, -1, dtype=wp.int32, device=dev)
            self._stack_shape = shape

    def _index_map(self, plans: Sequence[LayerPlan]) -> None:
        key = tuple(id(p.atoms) if p.atoms is not None else None for p in plans)
        if key == self._map_key:
            return
        offsets: list[int] = []
        parts: list[npt.NDArray[np.int32]] = []
        at = 0
        for plan in plans:
            if plan.atoms is None:
                offsets.append(-1)
            else:
                offsets.append(at)
                parts.append(plan.atoms)
                at += len(plan.atoms)
        flat = np.concatenate(parts).astype(np.int32) if parts else np.zeros(1, np.int32)
        self._offsets = wp.array(np.asarray(offsets or [-1], np.int32), device=self.device)
        self._map = wp.array(flat, dtype=wp.int32, device=self.device)
        self._map_key = key
        self._map_plans = tuple(plans)  # keeps the arrays the key names alive

    def render(
        self,
        plans: Sequence[LayerPlan],
        topology: Topology,
        topology_id: int,
        positions: npt.NDArray[np.float32],
        positions_id: int,
        camera: Camera,
        width: int,
        height: int,
        history: Sequence[tuple[int, npt.NDArray[np.float32]]] = (),
        history_epoch: int = 0,
        live: bool = True,
        lag: int | None = None,
        background: tuple[float, float, float] | None = None,
        tile: tuple[int, int, int, int] | None = None,
    ) -> None:
        """Render every layer of `plans` and composite them over `background` (default: the
        first layer's); the image stays on the device. `tile` (x0, y0, w, h): only that
        rectangle of the width x height image, as the whole image has it (outputs w x h)."""
        if len(plans) > MAX_LAYERS:
            raise RenderError(f"{len(plans)} layers, at most {MAX_LAYERS} are drawn")
        t0 = time.perf_counter()
        totals = {"upload": 0.0, "grid": 0.0, "raycast": 0.0}
        self._child(0)  # the device, even with nothing to draw
        size = (int(tile[2]), int(tile[3])) if tile is not None else (int(width), int(height))
        pixels = size[0] * size[1]
        self._alloc(len(plans), pixels)
        self._limit.fill_(float("inf"))
        opaque = False
        # clouds last: they stop at the nearest opaque surface of the layers drawn before
        for k in sorted(range(len(plans)), key=lambda i: _is_cloud(plans[i])):
            plan = plans[k]
            child = self._child(k, plan.style)
            r = child.renderer
            if child.atoms_key != plan.atoms_key or child.topology_id != topology_id:
                sub = topology if plan.atoms is None else subset_topology(topology, plan.atoms)
                r.set_topology(sub)
                child.atoms_key = plan.atoms_key
                child.topology_id = topology_id
                child.positions_id = -1
                child.secondary = None
                child.gathered.clear()
                child.runs = None if plan.atoms is None else contiguous_runs(plan.atoms)
            smoothing = bool(history) and plan.style == "density" and plan.params.needs_history()
            if child.positions_id != positions_id:
                if plan.atoms is not None and isinstance(r, Renderer) and not smoothing:
                    # straight into the renderer's page-locked buffer: an asynchronous upload
                    staged = r.host_positions()
                    gather_into(positions, plan.atoms, child.runs, staged)
                    r.set_positions(staged, check_finite=False)
                else:
                    mine = self._gather(child, plan, positions_id, positions)
                    r.set_positions(mine, check_finite=False)
                child.positions_id = positions_id
            if smoothing:
                frames = [(i, self._gather(child, plan, i, pos)) for i, pos in history]
                r.set_history(frames, history_epoch, plan.params, live=live, lag=lag)
            if isinstance(r, GeometryRenderer):
                if r.style == "tube" and not _same_codes(plan.secondary, child.secondary):
                    r.set_secondary(plan.secondary)
                    child.secondary = plan.secondary
                    child.positions_id = -1  # the spans change with the codes
                    r.set_positions(self._gather(child, plan, positions_id, positions))
                    child.positions_id = positions_id
                r.render(plan.params, camera, width, height, plan.radius_A, tile=tile)
            else:
                r.depth_limit = self._limit if opaque and _is_cloud(plan) else None
                r.render(plan.params, camera, width, height, tile)
            for key in totals:
                totals[key] += r.timings.get(key, 0.0)
            if not _is_cloud(plan) and plan.opacity >= 1.0:
                _rgba, depth, _ids, count = r.device_outputs()
                wp.launch(nearer_kernel, count, (depth, self._limit), device=self.device)
                opaque = True
        t_comp = time.perf_counter()
        for k, _plan in enumerate(plans):
            rgba, depth, ids, count = self._children[k].renderer.device_outputs()
            wp.copy(self._stack_rgba, rgba, dest_offset=k * self._pixels, count=count)
            wp.copy(self._stack_depth, depth, dest_offset=k * self._pixels, count=count)
            wp.copy(self._stack_ids, ids, dest_offset=k * self._pixels, count=count)
        self._index_map(plans)
        opacity = np.asarray([p.opacity for p in plans] or [0.0], dtype=np.float32)
        bg = background or (plans[0].params.background if plans else RenderParams().background)
        wp.launch(
            composite_kernel,
            pixels,
            (
                self._stack_rgba,
                self._stack_depth,
                self._stack_ids,
                wp.array(opacity, dtype=float, device=self.device),
                self._offsets,
                self._map,
                len(plans),
                wp.vec3(*(float(v) for v in bg)),
                self._out_rgba,
                self._out_depth,
                self._out_ids,
                self._out_layer,
            ),
            device=self.device,
        )
        wp.synchronize_device(self.device)
        t_end = time.perf_counter()
        totals["composite"] = (t_end - t_comp) * 1e3
        totals["total"] = (t_end - t0) * 1e3 + totals["upload"]
        self.timings = totals
        self._image = size
        self._plans = tuple(plans)
        for child in self._children[len(plans) :]:
            child.atoms_key = None  # a layer position no longer drawn frees nothing but is redone

    @staticmethod
    def _gather(
        child: _Child, plan: LayerPlan, frame_id: int, positions: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float32]:
        """This layer's atoms of one frame (kept for the frames smoothing will ask for again)."""
        if plan.atoms is None:
            return positions
        got = child.gathered.get(frame_id)
        if got is None:
            got = np.empty((len(plan.atoms), 3), dtype=np.float32)
            gather_into(positions, plan.atoms, child.runs, got)
            child.gathered[frame_id] = got
            while len(child.gathered) > _HISTORY_KEEP:
                child.gathered.pop(next(iter(child.gathered)))
        return got

    # ------------------------------------------------------------------ outputs

    def _outputs(self) -> tuple[Any, Any, Any]:
        """The composite: the front layer's atom as an index into the whole system."""
        return self._out_rgba, self._out_depth, self._out_ids

    def read_layers(self) -> npt.NDArray[np.int32]:
        """(height, width) position in the plan list of the front layer; -1 none."""
        layer: npt.NDArray[np.int32] = self._read(self._out_layer).astype(np.int32)
        return layer

    def pick(self, x: int, y: int) -> tuple[int | None, float | None]:
        """Atom (index in the whole system) and depth at pixel (x, y) of the last image."""
        atom, depth, _layer = self.pick_layer(x, y)
        return atom, depth

    def pick_layer(self, x: int, y: int) -> tuple[int | None, float | None, str | None]:
        """Atom, depth and the name of its layer at pixel (x, y)."""
        w, h = self._need_image()
        if not (0 <= int(x) < w and 0 <= int(y) < h):
            raise RenderError(f"pixel ({x}, {y}) outside the {w}x{h} image")
        i = int(y) * w + int(x)
        atom = int(self._out_ids[i : i + 1].numpy()[0])
        layer = int(self._out_layer[i : i + 1].numpy()[0])
        if atom < 0 or layer < 0:
            return None, None, None
        depth = float(self._out_depth[i : i + 1].numpy()[0])
        return atom, depth, self._plans[layer].name

    def density_histogram(
        self, bins: int = 64
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """The density histogram of the first volume layer (else the first layer), for the
        transfer-function editor."""
        if not self._plans:
            edges = np.linspace(0.0, 1.0, bins + 1)
            return np.zeros(bins, dtype=np.int64), edges
        density = [i for i, p in enumerate(self._plans) if p.style == "density"]
        if not density:
            return np.zeros(bins, dtype=np.int64), np.linspace(0.0, 1.0, bins + 1)
        k = next((i for i in density if self._plans[i].params.mode == "volume"), density[0])
        renderer = self._children[k].renderer
        assert isinstance(renderer, Renderer)
        return renderer.density_histogram(bins)
