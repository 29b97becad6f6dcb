"""One image rendered across several devices by splitting the atoms (sort-last).

Sort-first (`multi.py`) puts every atom on every device and splits the image; the system it can
draw is limited by one device's memory, and every device receives every position. Here space is
cut into slabs along the system's longest axis, one slab per device, cut where each holds as many
atoms as the others. A device holds only the atoms within its `halo` of its slab (the cutoff
reach, the march's last lattice steps past the slab and the ambient occlusion's farthest sample),
so the density its rays sample inside the slab is the whole system's, and each device receives
about 1/N of the positions. Its rays sample only inside its slab and one lattice step past it
(`CameraData.part_axis`): a crossing or a volume segment that straddles the cut belongs to the
slab in front of it. The samples lie on the same global lattice as on one device.

The parts' images are then combined on the first device, front to back in the order the pixel's
ray passes the slabs (ascending along the axis for a ray going that way, descending otherwise):
an iso surface is the first part's hit, a volume is the parts' premultiplied colours blended in
that order, which is exact for emission and absorption. Atom ids are mapped back to the whole
system's indices.

Relative levels are fractions of the mean density at every n // 4096-th atom of the whole
system. Each part takes the density at the sampled atoms inside its slab, and the parts then
render with the absolute level that mean gives (one synchronisation per frame whose positions or
density changed). The depth cue spans the whole system's box, not a part's.

Each frame, every device uploads one contiguous 1/N of the frame and picks the parts' atoms out
of it on the device, sending other parts' picks device to device (`server.render.scatter`; the
same pass measures the frame's box and the slack's check). With `gather="host"` (the control)
the host gathers every part's positions into that part's page-locked upload buffer, in ranges on
several threads, and takes the box and the check from the same ranges. Parts on distinct CUDA
devices take their share of the mean density from a thread each.

The atoms a part holds are chosen with a slack: a frame whose atoms have moved further than the
slack along the axis since the split, or parameters whose halo is wider than the split's, split
again. Only the classical density is split this way: the carved and geodesic densities read
their bond graphs over every atom, and smoothing in time reads every atom's history; those
render with sort-first.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp

from protocol import Camera, RenderParams, Topology, WireArray
from protocol.limits import MAX_COORDINATE_A
from server.render import colors
from server.render.camera import CameraFrame
from server.render.errors import CapacityError, RenderError
from server.render.layerplan import subset_topology
from server.render.outputs import ImageOutputs
from server.render.raycast import CameraData, camera_data, camera_ray, pack_rgba, unpack_rgba
from server.render.renderer import MEAN_SAMPLES, Renderer, check_finite_positions
from server.render.scatter import Scatter

wp: Any = warp  # warp's host API is unannotated

SLACK_HALO = 0.25
"""The atoms a part holds reach this fraction of the halo beyond it (at least `SLACK_MIN_A`):
atoms may move that far along the axis before the system is split again."""
SLACK_MIN_A = 2.0
SPREAD = 0.01
"""The split axis is the one whose 1st to 99th percentile of the atoms spans furthest."""
GATHER_CHUNK = 1 << 18
"""Atoms per range a gathering thread copies or checks at a time."""
GATHER_THREADS = 8
"""Threads that gather the parts' positions (at least one per part)."""
SPLITTABLE = (
    "a system larger than one device holds (--device-atoms) is split across the devices by "
    "space, which draws the classical density (scale_space 'classical', or warp_strength 0) "
    "without smoothing in time (time_smoothing 'off', not color_by 'motion') or layers (layers [])"
)
"""What a refusal adds: why sort-last is drawing, and what it can draw."""
SCENE_PAD = 1.0e-4
"""The depth cue's box is the atoms' box widened by the reach, padded as one device's grid box
is (`grid.setup_kernel`)."""


@wp.kernel(enable_backward=False)
@no_type_check
def sort_last_kernel(
    rgba: wp.array(dtype=wp.uint32),
    depth: wp.array(dtype=float),
    ids: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    members: wp.array(dtype=wp.int32),
    parts: int,
    pixels: int,
    cam: CameraData,
    axis: int,
    background: wp.vec3,
    out_rgba: wp.array(dtype=wp.uint32),
    out_depth: wp.array(dtype=float),
    out_ids: wp.array(dtype=wp.int32),
):
    """Blend one pixel's parts front to back in the order its ray passes their slabs
    (premultiplied colours with coverage in the alpha byte)."""
    pix = wp.tid()
    x = pix % cam.width
    y = pix // cam.width
    _o, d = camera_ray(cam, x, y)
    ascending = d[axis] >= 0.0
    acc = wp.vec3(0.0, 0.0, 0.0)
    alpha = float(0.0)
    front = wp.int32(-1)
    for q in range(parts):
        k = q
        if not ascending:
            k = parts - 1 - q
        at = k * pixels + pix
        col, a = unpack_rgba(rgba[at])
        if a > 0.0:
            acc += col * (1.0 - alpha)
            alpha += a * (1.0 - alpha)
        if front < 0 and depth[at] < wp.inf:
            front = k
    out_rgba[pix] = pack_rgba(acc + background * (1.0 - alpha))
    if front < 0:
        out_depth[pix] = wp.inf
        out_ids[pix] = -1
    else:
        at = front * pixels + pix
        out_depth[pix] = depth[at]
        local = ids[at]
        atom = wp.int32(-1)
        if local >= 0:
            atom = members[offsets[front] + local]
        out_ids[pix] = atom


def spread_axis(pos: npt.NDArray[np.float32]) -> int:
    """The axis along which most of the atoms spread furthest (1st to 99th percentile): a
    stray atom far out does not turn the cuts across the system."""
    if not len(pos):
        return 0
    spans = [
        float(np.subtract(*np.quantile(pos[:, k], [SPREAD, 1.0 - SPREAD])[::-1])) for k in range(3)
    ]
    return int(np.argmax(spans))


def chunks(n: int, size: int | None = None) -> list[tuple[int, int]]:
    """[a, b) ranges of at most `size` (`GATHER_CHUNK`) covering 0..n (one empty range when n
    is 0)."""
    size = size or GATHER_CHUNK
    return [(a, min(a + size, n)) for a in range(0, n, size)] or [(0, 0)]


def split_slabs(coord: npt.NDArray[np.float32], parts: int) -> list[tuple[float, float]]:
    """`parts` slabs along one coordinate holding equal numbers of atoms; the outer ones
    reach to infinity, so every point of space lies in exactly one (lo <= x < hi). Without
    atoms the first slab is all of space."""
    if not len(coord):
        return [(-math.inf, math.inf)] + [(math.inf, math.inf)] * (parts - 1)
    cuts = [float(v) for v in np.quantile(coord, [k / parts for k in range(1, parts)])]
    edges = [-math.inf, *cuts, math.inf]
    return [(edges[k], edges[k + 1]) for k in range(parts)]


class SortLastRenderer(ImageOutputs):
    """Renders one image with a `Renderer` per device, each holding the atoms of one slab of
    space and its halo; answers like a `Renderer` (`read_rgba`, `read_depth`,
    `read_atom_ids`, `pick`, `timings`)."""

    def __init__(self, devices: Sequence[str], *, gather: str = "device", **options: Any) -> None:
        if len(devices) < 1:
            raise RenderError("sort-last needs at least one device")
        if gather not in ("device", "host"):
            raise RenderError(f"gather must be 'device' or 'host', got {gather!r}")
        self.gather = gather
        """Where the parts' positions are picked from a frame: on the devices, each from the
        1/N of the frame it uploads (`server.render.scatter`), or on the host (the control)."""
        self._scatter: Scatter | None = None
        self._parts = [Renderer(dev, **options) for dev in devices]
        for r in self._parts:
            r.coverage = True
        names = [r.device for r in self._parts]
        self._home = names[0]
        """The device the parts' images are blended on."""
        self.device = ",".join(names)
        self.labels = [d if names.count(d) == 1 else f"{d}#{i}" for i, d in enumerate(names)]
        """Unique names of the devices (a device may hold several parts)."""
        self.timings: dict[str, float] = {}
        self._topology: Topology | None = None
        self._r_max = colors.R_REF
        self._radii = np.zeros(0, dtype=np.float32)
        self._positions: npt.NDArray[np.float32] | None = None
        self._version = 0
        self._split: dict[str, Any] | None = None
        self._sent: list[int] = []
        self._mean: tuple[tuple[Any, ...], float] | None = None
        self._image: tuple[int, int] | None = None
        self._pixels = 0
        self._box: tuple[int, npt.NDArray[Any], npt.NDArray[Any]] | None = None
        self._colored: tuple[Any, ...] | None = None
        self._whole_colors: tuple[tuple[Any, ...], npt.NDArray[Any]] | None = None
        self._serial = 0
        """Counts the splits (what was computed for one split is keyed by its number)."""
        self._concurrent = len(set(names)) == len(names) and all(
            wp.get_device(d).is_cuda for d in names
        )
        """Every part on its own CUDA device: the parts' work can be issued from a thread
        each (CPU devices keep state in warp's kernels; two parts on one device would capture
        their graphs on it at once)."""
        threads = max(len(self._parts), min(GATHER_THREADS, os.cpu_count() or 1))
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="sort-last")

    @property
    def renderers(self) -> list[Renderer]:
        """The parts' renderers, one per device (their `timings` say where a frame went)."""
        return list(self._parts)

    def set_topology(self, topology: Topology) -> None:
        """Take a topology; the atoms are split among the devices at the first render."""
        if topology.n_atoms > self._parts[0].max_atoms * len(self._parts):
            raise CapacityError(
                f"topology has {topology.n_atoms} atoms, {len(self._parts)} devices of "
                f"{self._parts[0].max_atoms} each hold fewer"
            )
        self._topology = topology
        # the whole system's radii, given to each part's topology (a part does not derive
        # them again from its elements' names: at 50M atoms that took tens of seconds)
        self._radii = colors.atom_radii(topology)
        self._r_max = float(self._radii.max()) if topology.n_atoms else 1.0
        self._positions = None
        self._split = None
        self._mean = None
        self._whole_colors = None

    def set_positions(
        self,
        positions: npt.ArrayLike,
        *,
        check_finite: bool = True,
        staged: npt.NDArray[np.float32] | None = None,
    ) -> None:
        """Positions (n, 3) in angstrom for the next render; kept on the host until then, when
        each device receives its part. `staged`: the same positions in page-locked memory
        (a live session's), read from there."""
        if staged is not None:
            positions = staged
        if self._topology is None:
            raise RenderError("set_topology must come before set_positions")
        arr = np.ascontiguousarray(positions, dtype=np.float32)
        n = self._topology.n_atoms
        if arr.ndim != 2 or arr.shape != (n, 3):
            raise RenderError(f"positions must have shape ({n}, 3), got {arr.shape}")
        if check_finite and n:
            check_finite_positions(arr)
        self._positions = arr
        self._version += 1

    def _split_atoms(self, pos: npt.NDArray[np.float32], halo: float) -> None:
        """Cut space into slabs and give each part its slab's atoms with the halo and slack."""
        assert self._topology is not None
        axis = spread_axis(pos)
        coord = pos[:, axis]
        slabs = split_slabs(coord, len(self._parts))
        slack = max(SLACK_HALO * halo, SLACK_MIN_A)
        reach = halo + slack
        members: list[npt.NDArray[np.int32]] = []
        for r, (lo, hi) in zip(self._parts, slabs, strict=True):
            atoms = np.flatnonzero((coord >= lo - reach) & (coord < hi + reach)).astype(np.int32)
            if len(atoms) > r.max_atoms:
                self._split = None
                span = float(coord.max() - coord.min())
                if span <= 2.0 * reach:
                    raise CapacityError(
                        f"the {len(coord)}-atom system spans {span:.1f} A along its longest "
                        f"axis, within twice the {reach:.1f} A a slab's halo and slack reach: "
                        f"no cut splits it (a narrower sigma narrows the halo), and a device "
                        f"holds {r.max_atoms}"
                    )
                raise CapacityError(
                    f"a slab of the {len(coord)}-atom system holds {len(atoms)} atoms with the "
                    f"atoms within {reach:.1f} A of it (its halo and slack); a device holds "
                    f"{r.max_atoms}: more devices, or a smaller sigma (a narrower halo), would "
                    "split it"
                )
            members.append(atoms)
            part = subset_topology(self._topology, atoms)
            radii = WireArray.from_numpy(self._radii[atoms], "<f4")
            r.set_topology(part.model_copy(update={"radii": radii}))
        offsets = np.cumsum([0] + [len(m) for m in members[:-1]]).astype(np.int32)
        dev = self._home
        self._serial += 1
        self._split = {
            "serial": self._serial,
            "axis": axis,
            "slabs": slabs,
            "halo": halo,
            "slack": slack,
            "members": members,
            "checked": self._version,
            "offsets": wp.array(offsets, dtype=wp.int32, device=dev),
            "flat": wp.array(np.concatenate(members), dtype=wp.int32, device=dev),
        }
        self._sent = [-1] * len(self._parts)
        self._scatter = None
        if self.gather == "device":  # the devices keep the reference and measure the move
            self._scatter = Scatter([r.device for r in self._parts], members, axis, coord)
        else:  # the host's gather and check of the slack
            self._split["gather"] = [m.astype(np.intp) for m in members]  # take's index type
            self._split["reference"] = coord.copy()
            self._split["moved"] = np.empty(len(coord), dtype=np.float32)
        self._mean = None

    def _send_on_host(self, pos: npt.NDArray[np.float32], halo: float) -> bool:
        """Split when the last split no longer serves, then gather each part's positions on
        the host; False: the frame draws background (a coordinate not finite or too far)."""
        if not self._split_holds(pos, halo):
            if not self._drawable(pos):
                return False
            self._split_atoms(pos, halo)
        self._send(pos)
        return self._drawable(pos)  # a bad coordinate off the split's axis

    def _send_on_devices(self, pos: npt.NDArray[np.float32], halo: float) -> bool:
        """Split when needed, then each device uploads its 1/N of the frame and picks the
        parts' atoms from it (`Scatter`); a frame the devices find moved past the slack is
        split again, one with a bad coordinate draws background (False)."""
        s = self._split
        if s is None or halo > s["halo"]:
            if not self._drawable(pos):
                return False
            self._split_atoms(pos, halo)
        if self._sent and min(self._sent) == self._version:
            return self._drawable(pos)
        assert self._scatter is not None and self._split is not None
        found = self._scatter.send(pos)
        if found.bad or not found.moved <= self._split["slack"]:
            self._box = None
            if not self._drawable(pos):
                return False
            self._split_atoms(pos, halo)
            assert self._scatter is not None
            found = self._scatter.send(pos)
        self._box = (self._version, found.lo, found.hi)
        for r, inbox in zip(self._parts, self._scatter.inbox, strict=True):
            r.set_positions(None, check_finite=False, on_device=inbox)
        self._sent = [self._version] * len(self._parts)
        return self._drawable(pos)

    def _split_holds(self, pos: npt.NDArray[np.float32], halo: float) -> bool:
        """Whether the last split still serves this frame: its halo is wide enough and no atom
        has moved further than the slack along the axis since (a coordinate that is not
        finite fails too). The check runs in ranges on the gathering threads."""
        s = self._split
        if s is None or halo > s["halo"]:
            return False
        if s["checked"] == self._version or not len(pos):
            return True
        coord, ref, moved = pos[:, s["axis"]], s["reference"], s["moved"]

        def drift(span: tuple[int, int]) -> float:
            a, b = span
            np.subtract(coord[a:b], ref[a:b], out=moved[a:b])
            np.abs(moved[a:b], out=moved[a:b])
            return float(moved[a:b].max())

        worst = max(self._pool.map(drift, chunks(len(pos))))
        if not worst <= s["slack"]:  # NaN fails
            return False
        s["checked"] = self._version
        return True

    def _send(self, pos: npt.NDArray[np.float32]) -> None:
        """Each part's atoms to its device (only after new positions or a new split): gathered
        in ranges on the threads (numpy's take releases the interpreter) straight into each
        part's page-locked upload buffer, the frame's box taken from the same ranges (every
        atom is in some part, so the parts' boxes together are the system's)."""
        assert self._split is not None
        members, gathers = self._split["members"], self._split["gather"]
        todo = [k for k in range(len(self._parts)) if self._sent[k] != self._version]
        if not todo:
            return
        buffers = {k: self._parts[k].host_positions() for k in todo}

        def gather(job: tuple[int, int, int]) -> npt.NDArray[np.float64]:
            k, a, b = job
            out = buffers[k][a:b]
            # "clip": indices within range, so take writes straight into `out` (with "raise"
            # numpy buffers the result and copies it)
            np.take(pos, gathers[k][a:b], axis=0, out=out, mode="clip")
            if not len(out):
                return np.array([[np.inf] * 3, [-np.inf] * 3])
            cols = [out[:, c] for c in range(3)]  # a column at a time (see `_bounds`)
            return np.array([[c.min() for c in cols], [c.max() for c in cols]], np.float64)

        jobs = [(k, a, b) for k in todo for a, b in chunks(len(members[k]))]
        boxes = list(self._pool.map(gather, jobs))
        for k in todo:
            self._parts[k].set_positions(buffers[k], check_finite=False)
            self._sent[k] = self._version
        if len(todo) == len(self._parts) and boxes:
            both = np.stack(boxes)
            self._box = (self._version, both[:, 0].min(axis=0), both[:, 1].max(axis=0))

    def _bounds(self, pos: npt.NDArray[np.float32]) -> tuple[npt.NDArray[Any], npt.NDArray[Any]]:
        """The atoms' box (kept for the frame; `_send` gives it from its ranges), a column at
        a time: numpy's reduction over the first axis of an (n, 3) array runs three values per
        inner loop (1M atoms: 50 ms against 2 ms)."""
        if self._box is None or self._box[0] != self._version:
            lo = np.array([pos[:, k].min() for k in range(3)], dtype=np.float64)
            hi = np.array([pos[:, k].max() for k in range(3)], dtype=np.float64)
            self._box = (self._version, lo, hi)
        return self._box[1], self._box[2]

    def _drawable(self, pos: npt.NDArray[np.float32]) -> bool:
        """A frame with a coordinate that is not finite or lies past `MAX_COORDINATE_A` draws
        background only, as on one device (whose grid flags it); it is never split."""
        if not len(pos):
            return True
        lo, hi = self._bounds(pos)
        return bool(
            np.isfinite(lo).all()
            and np.isfinite(hi).all()
            and max(float(np.abs(lo).max()), float(np.abs(hi).max())) <= MAX_COORDINATE_A
        )

    def _background(self, params: RenderParams, w: int, h: int) -> None:
        """The image of a frame that draws nothing: background, no depth, no atom."""
        pixels = w * h
        self._alloc(pixels)
        c = [int(min(max(v, 0.0), 1.0) * 255.0 + 0.5) for v in params.background]
        packed = c[0] | (c[1] << 8) | (c[2] << 16) | (255 << 24)
        self._out_rgba.fill_(packed)
        self._out_depth.fill_(float("inf"))
        self._out_ids.fill_(-1)
        self._image = (w, h)

    def _open(self, frame: CameraFrame, reach: float, pos: npt.NDArray[np.float32]) -> int:
        """1 when a ray may start within reach of an atom (the eye, or an orthographic image
        plane, near the atoms): parts entered at their near boundary then look for a way out
        of the surface too, as one device would."""
        if not len(pos):
            return 0
        lo, hi = self._bounds(pos)
        if frame.ortho:
            corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).reshape(3, -1).T
            ahead = (corners - np.asarray(frame.eye)) @ np.asarray(frame.forward)
            return int(float(ahead.min()) <= reach)
        eye = np.asarray(frame.eye, dtype=np.float64)
        gap = np.maximum(np.maximum(lo - eye, eye - hi), 0.0)
        return int(float(np.linalg.norm(gap)) <= reach)

    def _mean_density(self, params: RenderParams, pos: npt.NDArray[np.float32]) -> float:
        """The whole system's mean density at its sampled atoms (as one device takes it for
        relative levels), each sample taken by the part whose slab holds it."""
        assert self._split is not None
        key = (
            self._version,
            self._split["serial"],
            params.sigma_A,
            params.radius_mode,
            params.cutoff_sigmas,
            params.density_weights,
        )
        if self._mean is not None and self._mean[0] == key:
            return self._mean[1]
        n = len(pos)
        samples = min(n, MEAN_SAMPLES)
        stride = n // samples
        points = pos[np.arange(samples) * stride]
        s = self._split
        his = np.array([hi for _lo, hi in s["slabs"]])
        owner = np.searchsorted(his, points[:, s["axis"]], side="right")
        probe = params.model_copy(update={"level_scale": "absolute", "mode": "iso"})

        def part_sum(k: int) -> float:
            mine = points[owner == k]
            if not len(mine):
                return 0.0
            self._parts[k].prepare(probe)
            return float(self._parts[k].evaluate(mine)[0].astype(np.float64).sum())

        ks = range(len(self._parts))
        sums = self._pool.map(part_sum, ks) if self._concurrent else map(part_sum, ks)
        mean = sum(sums) / samples
        self._mean = (key, mean)
        return mean

    def _color_parts(self, params: RenderParams) -> None:
        """Every part's atoms in the whole system's colours (a chain's rank, the b-factor and
        charge ranges are the system's, not a part's)."""
        assert self._topology is not None and self._split is not None
        scheme = (params.color_by, tuple(params.uniform_color))
        key = (*scheme, self._split["serial"])
        if self._colored == key:
            return
        if self._whole_colors is None or self._whole_colors[0] != scheme:
            # kept across splits: a system re-split as it moves keeps its colours
            whole = colors.atom_colors(self._topology, params.color_by, params.uniform_color)
            self._whole_colors = (scheme, whole)
        whole = self._whole_colors[1]
        for r, atoms in zip(self._parts, self._split["members"], strict=True):
            r.set_colors(whole[atoms])
        self._colored = key

    def _scene(self, params: RenderParams, pos: npt.NDArray[np.float32]) -> Any:
        if params.lighting.depth_cue <= 0.0 or not len(pos):
            return None
        lo, hi = self._bounds(pos)
        amax = float(max(np.abs(lo).max(), np.abs(hi).max()))
        r = self._parts[0].reach(params, self._r_max) * (1.0 + SCENE_PAD) + amax * 4.0e-7 + 1.0e-6
        lo = lo - r
        hi = hi + r
        return (tuple(float(v) for v in lo), tuple(float(v) for v in hi))

    @staticmethod
    def refusal(params: RenderParams) -> str | None:
        """Why these parameters cannot be split by space (None: they can)."""
        if params.scale_space != "classical" and params.warp_strength > 0.0:
            return f"the {params.scale_space} density reads every atom's bonds"
        if params.needs_history():
            return "smoothing in time reads every atom's history"
        if params.layers:
            return "layers draw their own selections"
        return None

    def render(
        self,
        params: RenderParams,
        camera: Camera,
        width: int,
        height: int,
        *,
        wait: bool = True,
    ) -> None:
        """Render one image across the parts and combine it on the first device. Raises
        RenderError for parameters sort-last cannot split (`refusal`) and for invalid input."""
        why = self.refusal(params)
        if why is not None:
            raise RenderError(f"sort-last cannot draw these parameters: {why}; {SPLITTABLE}")
        if self._topology is None or self._positions is None:
            raise RenderError("no positions: call set_topology, then set_positions")
        t0 = time.perf_counter()
        pos = self._positions
        w, h, frame = self._parts[0].check_view(camera, width, height)
        halo = self._parts[0].halo(params, self._r_max)
        sent = self._send_on_devices if self.gather == "device" else self._send_on_host
        if not sent(pos, halo):
            self._background(params, w, h)
            self.timings = {"total_ms": (time.perf_counter() - t0) * 1e3, "total": 0.0}
            return
        t_split = time.perf_counter()
        p = params
        if params.level_scale == "mean" and len(pos):
            level = float(params.iso_level) * self._mean_density(params, pos)
            if not level > 0.0:
                level = float(params.iso_level)
            p = params.model_copy(update={"level_scale": "absolute", "iso_level": level})
        t_mean = time.perf_counter()
        self._color_parts(params)
        scene = self._scene(params, pos)
        s = self._split
        assert s is not None
        opened = self._open(frame, self._parts[0].reach(params, self._r_max), pos)
        for r, (lo, hi) in zip(self._parts, s["slabs"], strict=True):
            r.region = (s["axis"], lo, hi, opened)
            r.scene_box = scene
            r.render(p, camera, w, h, wait=False)
        t_queued = time.perf_counter()
        self._combine(params, frame, w, h)
        t_end = time.perf_counter()
        parts = self._parts
        self.timings = {
            "split_ms": (t_split - t0) * 1e3,
            "mean_ms": (t_mean - t_split) * 1e3,
            "queue_ms": (t_queued - t_mean) * 1e3,
            "combine_ms": (t_end - t_queued) * 1e3,
            "total_ms": (t_end - t0) * 1e3,
            # as one device's and sort-first's renders say it (a session's stats)
            "upload": max(r.timings.get("upload", 0.0) for r in parts),
            "grid": max(r.timings.get("grid", 0.0) for r in parts),
            "raycast": max(r.timings.get("raycast", 0.0) for r in parts),
            "total": (t_end - t0) * 1e3,
            **{
                f"device:{d}": r.timings.get("grid", 0.0) + r.timings.get("raycast", 0.0)
                for d, r in zip(self.labels, parts, strict=True)
            },
        }
        if wait:
            self.finish()

    def _alloc(self, pixels: int) -> None:
        n = len(self._parts)
        if pixels > self._pixels:
            dev = self._home
            self._pixels = pixels
            self._stack_rgba = wp.zeros(n * pixels, dtype=wp.uint32, device=dev)
            self._stack_depth = wp.zeros(n * pixels, dtype=float, device=dev)
            self._stack_ids = wp.zeros(n * pixels, dtype=wp.int32, device=dev)
            self._out_rgba = wp.zeros(pixels, dtype=wp.uint32, device=dev)
            self._out_depth = wp.zeros(pixels, dtype=float, device=dev)
            self._out_ids = wp.zeros(pixels, dtype=wp.int32, device=dev)

    def _combine(self, params: RenderParams, frame: Any, w: int, h: int) -> None:
        """Each part's image onto the first device, then one blend in slab order."""
        assert self._split is not None
        pixels = w * h
        self._alloc(pixels)
        stacks = (self._stack_rgba, self._stack_depth, self._stack_ids)
        for k, r in enumerate(self._parts):
            r.finish()
            for dest, src in zip(stacks, r.device_outputs()[:3], strict=True):
                wp.copy(dest, src, dest_offset=k * pixels, count=pixels)
        s = self._split
        args = (
            *stacks,
            s["offsets"],
            s["flat"],
            len(self._parts),
            pixels,
            camera_data(frame),
            s["axis"],
            wp.vec3(*(float(v) for v in params.background)),
            self._out_rgba,
            self._out_depth,
            self._out_ids,
        )
        wp.launch(sort_last_kernel, pixels, args, device=self._home)
        self._image = (w, h)

    def finish(self) -> None:
        """Wait for the last render's combine."""
        wp.synchronize_device(self._home)

    def _outputs(self) -> tuple[Any, Any, Any]:
        return self._out_rgba, self._out_depth, self._out_ids

    def pick(self, x: int, y: int) -> tuple[int | None, float | None]:
        """The atom (whole-system index) and depth at pixel (x, y) of the last image."""
        w, h = self._need_image()
        if not (0 <= x < w and 0 <= y < h):
            raise RenderError(f"pixel ({x}, {y}) is outside the {w}x{h} image")
        atom = int(self.read_atom_ids()[y, x])
        depth = float(self.read_depth()[y, x])
        return (atom if atom >= 0 else None), (depth if math.isfinite(depth) else None)

    @property
    def pipelined(self) -> bool:
        """A frame is gathered into its parts when it is drawn, not uploaded during a render."""
        return False

    def set_history(self, *args: Any, **kwargs: Any) -> None:
        """Smoothing in time is not split by space: refused with the reason."""
        raise RenderError(
            "sort-last cannot draw these parameters: smoothing in time reads every atom's "
            f"history; {SPLITTABLE}"
        )

    def density_histogram(
        self, bins: int = 64
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
        """The parts' density histograms summed (`Renderer.density_histogram`; each over its
        own grid's box, so the halos between slabs count twice): the shape a transfer function
        is drawn over."""
        if self._image is None:
            raise RenderError("render once before asking for a histogram")
        counts: npt.NDArray[np.int64] | None = None
        edges = np.zeros(0)
        for r in self._parts:
            c, edges = r.density_histogram(bins)
            counts = c if counts is None else counts + c
        assert counts is not None
        return counts, edges

    def atoms_held(self) -> list[int]:
        """How many atoms each part holds (its slab's and its halo's)."""
        if self._split is None:
            return [0] * len(self._parts)
        return [len(m) for m in self._split["members"]]

    def memory_bytes(self) -> list[dict[str, int]]:
        """Each part's device memory, by what it holds (with the frame's share and the picks
        its device holds for the device-side gather)."""
        held = [r.memory_bytes() for r in self._parts]
        if self._scatter is not None:
            for part, extra in zip(held, self._scatter.device_bytes(), strict=True):
                part["scatter"] = extra
        return held

    def close(self) -> None:
        """Let the gathering threads go."""
        self._pool.shutdown(wait=False)
