"""Atoms and bonds as solid shapes, for layers beside the density: licorice (a capsule along
each half bond, coloured by its atom, and a sphere at each atom without bonds) and a backbone
tube (capsules along a Catmull-Rom spline through the CA / P trace of each chain; with
secondary structure, helices as wide cylinders along their axes and strands wider).

A capsule (a segment with a radius; a sphere when both ends meet) is hit analytically. The
capsules sit in a BVH over their boxes, refitted on the device every frame (a new topology
builds it again); a ray visits the boxes it crosses and keeps the nearest hit, pruning boxes
beyond it. Shading is the density caster's (`raycast.lit`, the depth cue), so a licorice layer
and a surface layer are lit alike, and the outputs are a layer renderer's: premultiplied
colour with coverage, distance along the ray, the atom hit.
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal, no_type_check

import numpy as np
import numpy.typing as npt
import warp

from protocol import Camera, RenderParams, Topology
from server.render import colors, raycast
from server.render import device as devmod
from server.render.camera import camera_frame
from server.render.errors import RenderError
from server.render.outputs import ImageOutputs

wp: Any = warp

Style = Literal["licorice", "tube"]
STICK_RADIUS_A = 0.25
TUBE_RADIUS_A = 0.6
TUBE_SUBDIVISIONS = 4
"""Spline pieces per residue step: enough for a round tube at dashboard sizes."""
HELIX_SCALE = 3.5
"""A helix is a cylinder along its axis, 3.5 tube radii wide (2.1 A at the default radius)."""
STRAND_SCALE = 1.6
SECONDARY = {"-": 0, "H": 1, "E": 2}
"""Secondary-structure codes per atom, as MDAnalysis's DSSP names them (coil, helix, strand)."""
HELIX_MIN = 4
"""Residues a helix needs before it is drawn as a cylinder (its axis: the mean of four CA)."""
TRACE_BREAK_A = {"CA": 4.6, "P": 8.5}
"""Consecutive trace atoms further apart than this (at the first frame) start a new piece."""


@wp.func
@no_type_check
def ray_sphere(o: wp.vec3, d: wp.vec3, c: wp.vec3, r: float):
    """Entry distance of a ray (unit `d`) into a sphere; -1 on a miss or from inside."""
    oc = o - c
    b = wp.dot(d, oc)
    h = b * b - (wp.dot(oc, oc) - r * r)
    t = float(-1.0)
    if h >= 0.0:
        t = -b - wp.sqrt(h)
    return t


@wp.func
@no_type_check
def ray_capsule(o: wp.vec3, d: wp.vec3, a: wp.vec3, b: wp.vec3, r: float):
    """Entry distance of a ray (unit `d`) into the capsule a-b of radius r; -1 on a miss."""
    best = float(-1.0)
    ba = b - a
    baba = wp.dot(ba, ba)
    if baba > 1.0e-12:
        oa = o - a
        bard = wp.dot(ba, d)
        baoa = wp.dot(ba, oa)
        k2 = baba - bard * bard
        if k2 > 1.0e-12:
            k1 = baba * wp.dot(d, oa) - baoa * bard
            k0 = baba * wp.dot(oa, oa) - baoa * baoa - r * r * baba
            h = k1 * k1 - k2 * k0
            if h >= 0.0:
                t = (-k1 - wp.sqrt(h)) / k2
                y = baoa + t * bard
                if t >= 0.0 and y > 0.0 and y < baba:
                    best = t
    # the round ends: the body's hit, if any, is nearer than a cap's on the same side
    for end in range(2):
        c = a
        if end == 1:
            c = b
        t = ray_sphere(o, d, c, r)
        if t >= 0.0 and (best < 0.0 or t < best):
            best = t
    return best


@wp.func
@no_type_check
def capsule_normal(p: wp.vec3, a: wp.vec3, b: wp.vec3):
    ba = b - a
    baba = wp.dot(ba, ba)
    s = float(0.0)
    if baba > 1.0e-12:
        s = wp.clamp(wp.dot(p - a, ba) / baba, 0.0, 1.0)
    return wp.normalize(p - (a + ba * s))


@wp.kernel(enable_backward=False)
@no_type_check
def half_bonds_kernel(
    positions: wp.array(dtype=wp.vec3),
    atom: wp.array(dtype=wp.int32),
    other: wp.array(dtype=wp.int32),
    p0: wp.array(dtype=wp.vec3),
    p1: wp.array(dtype=wp.vec3),
):
    """Licorice: capsule k runs from its atom to the middle of its bond (to itself: a ball)."""
    k = wp.tid()
    pa = positions[atom[k]]
    p0[k] = pa
    j = other[k]
    if j >= 0:
        p1[k] = (pa + positions[j]) * 0.5
    else:
        p1[k] = pa


@wp.kernel(enable_backward=False)
@no_type_check
def bounds_kernel(
    p0: wp.array(dtype=wp.vec3),
    p1: wp.array(dtype=wp.vec3),
    r: float,
    scale: wp.array(dtype=float),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    k = wp.tid()
    rk = r * scale[k]
    pad = wp.vec3(rk, rk, rk)
    lowers[k] = wp.min(p0[k], p1[k]) - pad
    uppers[k] = wp.max(p0[k], p1[k]) + pad


@wp.kernel(enable_backward=False)
@no_type_check
def capsule_kernel(
    bvh: wp.uint64,
    p0: wp.array(dtype=wp.vec3),
    p1: wp.array(dtype=wp.vec3),
    r: float,
    scale: wp.array(dtype=float),
    color: wp.array(dtype=wp.uint32),
    atom: wp.array(dtype=wp.int32),
    cam: raycast.CameraData,
    sh: raycast.Shading,
    fog_near: float,
    fog_far: float,
    rgba: wp.array(dtype=wp.uint32),
    depth: wp.array(dtype=float),
    ids: wp.array(dtype=wp.int32),
):
    x, y, ok = raycast.pixel_of(cam, wp.tid())
    if ok == 0:
        return
    pix = y * cam.width + x
    o, d = raycast.camera_ray(cam, x, y)
    query = wp.bvh_query_ray(bvh, o, d)
    best = float(wp.inf)
    hit = wp.int32(-1)
    k = wp.int32(0)
    while wp.bvh_query_next(query, k, best):
        t = ray_capsule(o, d, p0[k], p1[k], r * scale[k])
        if t >= 0.0 and t < best:
            best = t
            hit = k
    if hit < 0:
        rgba[pix] = raycast.pack_rgba(sh.background)
        if sh.coverage != 0:
            rgba[pix] = wp.uint32(0)
        depth[pix] = wp.inf
        ids[pix] = -1
        return
    p = o + d * best
    n = capsule_normal(p, p0[hit], p1[hit])
    if wp.dot(n, d) > 0.0:
        n = -n
    c = color[hit]
    base = wp.vec3(
        float(c & wp.uint32(255)) / 255.0,
        float((c >> wp.uint32(8)) & wp.uint32(255)) / 255.0,
        float((c >> wp.uint32(16)) & wp.uint32(255)) / 255.0,
    )
    lit = raycast.lit(sh, base, n, -d, 1.0)
    if sh.depth_cue > 0.0:
        f = sh.depth_cue * wp.clamp(
            (best - fog_near) / wp.max(fog_far - fog_near, 1.0e-6), 0.0, 1.0
        )
        lit = lit * (1.0 - f) + sh.background * f
    rgba[pix] = raycast.pack_rgba(lit)
    depth[pix] = best
    ids[pix] = atom[hit]


def licorice_capsules(topology: Topology) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    """(atom, other) per capsule: both halves of every bond, and a ball (other = -1) for each
    atom without a bond."""
    n = topology.n_atoms
    bonds = topology.bonds.to_numpy().reshape(-1, 2).astype(np.int32)
    bonds = bonds[bonds[:, 0] != bonds[:, 1]]
    bonded = np.zeros(n, dtype=bool)
    bonded[bonds.ravel()] = True
    lone = np.flatnonzero(~bonded).astype(np.int32)
    atom = np.concatenate([bonds[:, 0], bonds[:, 1], lone]).astype(np.int32)
    other = np.concatenate([bonds[:, 1], bonds[:, 0], np.full(len(lone), -1, np.int32)])
    return atom, other.astype(np.int32)


def trace_pieces(
    topology: Topology, positions: npt.NDArray[np.float32]
) -> list[npt.NDArray[np.int32]]:
    """The CA (protein) or P (nucleic) atoms of each unbroken piece of chain, in order: a new
    piece where the chain changes, the residue numbers jump, or two neighbours are too far
    apart for a bond between residues."""
    names = np.asarray(topology.names)
    chains = np.asarray(topology.chain_ids)
    resids = topology.residue_ids.to_numpy()
    pieces: list[npt.NDArray[np.int32]] = []
    for name, gap in TRACE_BREAK_A.items():
        idx = np.flatnonzero(names == name).astype(np.int32)
        if len(idx) < 2:
            continue
        step = np.linalg.norm(np.diff(positions[idx].astype(np.float64), axis=0), axis=1)
        breaks = (chains[idx][1:] != chains[idx][:-1]) | (np.diff(resids[idx]) != 1) | (step > gap)
        for piece in np.split(idx, np.flatnonzero(breaks) + 1):
            if len(piece) >= 2:
                pieces.append(piece)
    return pieces


def catmull_rom(points: npt.NDArray[np.float64], pieces: int) -> npt.NDArray[np.float64]:
    """A centripetal-free (uniform) Catmull-Rom curve through `points`, `pieces` spans per
    step, ends clamped: (pieces * (len - 1) + 1, 3)."""
    p = np.concatenate([points[:1], points, points[-1:]])
    s = np.arange(pieces, dtype=np.float64) / pieces
    s2, s3 = s * s, s * s * s
    out = []
    for i in range(1, len(p) - 2):
        a, b, c, d = p[i - 1], p[i], p[i + 1], p[i + 2]
        out.append(
            0.5
            * (
                (2 * b)[None]
                + np.outer(s, c - a)
                + np.outer(s2, 2 * a - 5 * b + 4 * c - d)
                + np.outer(s3, -a + 3 * b - 3 * c + d)
            )
        )
    out.append(points[-1:])
    return np.concatenate(out)


def _runs(codes: npt.NDArray[np.uint8]) -> list[tuple[int, int, int]]:
    """(start, stop, code) of each run of equal codes."""
    if not len(codes):
        return []
    cuts = np.flatnonzero(np.diff(codes.astype(np.int16))) + 1
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [len(codes)]])
    return [(int(a), int(b), int(codes[a])) for a, b in zip(starts, stops, strict=True)]


def tube_spans(
    pieces: list[npt.NDArray[np.int32]],
    positions: npt.NDArray[np.float32],
    codes: npt.NDArray[np.uint8] | None = None,
) -> tuple[
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.int32],
    npt.NDArray[np.float64],
]:
    """Capsules (p0, p1, owner atom, radius scale) of a backbone tube: a Catmull-Rom spline
    through each piece's trace atoms; with secondary structure (`codes` per atom), a helix of
    `HELIX_MIN` residues or more becomes a wide cylinder along its axis (the running mean of
    four consecutive CA, which lies on a helix's axis) and a strand a wider tube. Each coil or
    strand run reaches to its neighbours' first and last atoms, so the tube stays joined."""
    p0: list[npt.NDArray[np.float64]] = []
    p1: list[npt.NDArray[np.float64]] = []
    owner: list[npt.NDArray[np.int32]] = []
    scale: list[npt.NDArray[np.float64]] = []

    def spline(idx: npt.NDArray[np.int32], factor: float) -> None:
        if len(idx) < 2:
            return
        curve = catmull_rom(positions[idx].astype(np.float64), TUBE_SUBDIVISIONS)
        span = np.arange(len(curve) - 1)
        nearer = np.minimum((span + TUBE_SUBDIVISIONS // 2) // TUBE_SUBDIVISIONS, len(idx) - 1)
        p0.append(curve[:-1])
        p1.append(curve[1:])
        owner.append(idx[nearer])
        scale.append(np.full(len(span), factor))

    for piece in pieces:
        kinds = np.zeros(len(piece), np.uint8) if codes is None else codes[piece].astype(np.uint8)
        for start, stop, code in _runs(kinds):
            if code == SECONDARY["H"] and stop - start >= HELIX_MIN:
                ca = positions[piece[start:stop]].astype(np.float64)
                axis = np.stack([ca[i : i + 4].mean(axis=0) for i in range(len(ca) - 3)])
                if len(axis) == 1:  # four residues: one axis point, a short cylinder
                    direction = ca[-1] - ca[0]
                    direction /= max(float(np.linalg.norm(direction)), 1e-9)
                    axis = np.stack([axis[0] - 2.25 * direction, axis[0] + 2.25 * direction])
                p0.append(axis[:-1])
                p1.append(axis[1:])
                owner.append(piece[start + 1 : start + len(axis)].astype(np.int32))
                scale.append(np.full(len(axis) - 1, HELIX_SCALE))
            else:
                lo, hi = max(start - 1, 0), min(stop + 1, len(piece))
                spline(piece[lo:hi], STRAND_SCALE if code == SECONDARY["E"] else 1.0)
    if not p0:
        empty = np.zeros((0, 3))
        return empty, empty, np.zeros(0, np.int32), np.zeros(0)
    return (
        np.concatenate(p0),
        np.concatenate(p1),
        np.concatenate(owner).astype(np.int32),
        np.concatenate(scale),
    )


class GeometryRenderer(ImageOutputs):
    """Ray-casts one layer's atoms as licorice or as a backbone tube (see the module)."""

    def __init__(self, device: str = "auto", style: Style = "licorice") -> None:
        self.device: str = devmod.resolve(device)
        self.style: Style = style
        self.coverage = False
        self.timings: dict[str, float] = {}
        self._topology: Topology | None = None
        self._positions: npt.NDArray[np.float32] | None = None
        self._pos_dev: Any = None
        self._pieces: list[npt.NDArray[np.int32]] | None = None
        self._count = 0
        self._bvh: Any = None
        self._image: tuple[int, int] | None = None
        self._pixels = 0
        self._alloc_pixels(1)

    def _alloc_pixels(self, count: int) -> None:
        if count <= self._pixels:
            return
        self._pixels = count
        self._rgba = wp.zeros(count, dtype=wp.uint32, device=self.device)
        self._depth = wp.zeros(count, dtype=float, device=self.device)
        self._ids = wp.zeros(count, dtype=wp.int32, device=self.device)

    def set_topology(self, topology: Topology) -> None:
        self._topology = topology
        self._secondary: npt.NDArray[np.uint8] | None = None
        self._positions = None
        self._pieces = None
        self._bvh = None
        self._color_key: tuple[Any, ...] | None = None
        if self.style == "licorice":
            atom, other = licorice_capsules(topology)
            self._atom_host = atom
            self._atom = wp.array(atom, dtype=wp.int32, device=self.device)
            self._other = wp.array(other, dtype=wp.int32, device=self.device)
            self._alloc_capsules(len(atom))

    def _alloc_capsules(self, count: int) -> None:
        if count != self._count or not hasattr(self, "_p0"):
            m = max(count, 1)
            self._p0 = wp.zeros(m, dtype=wp.vec3, device=self.device)
            self._p1 = wp.zeros(m, dtype=wp.vec3, device=self.device)
            self._lowers = wp.zeros(m, dtype=wp.vec3, device=self.device)
            self._uppers = wp.zeros(m, dtype=wp.vec3, device=self.device)
            self._colors = wp.zeros(m, dtype=wp.uint32, device=self.device)
            self._scale = wp.full(m, 1.0, dtype=float, device=self.device)
            self._bvh = None
            self._color_key = None
        self._count = count

    def set_positions(self, positions: npt.ArrayLike, *, check_finite: bool = True) -> None:
        if self._topology is None:
            raise RenderError("set_topology must come before set_positions")
        arr = np.ascontiguousarray(np.asarray(positions, dtype=np.float32).reshape(-1, 3))
        if arr.shape[0] != self._topology.n_atoms:
            raise RenderError(
                f"positions have {arr.shape[0]} atoms, topology has {self._topology.n_atoms}"
            )
        if check_finite and not np.isfinite(arr).all():
            raise RenderError("positions contain NaN or Inf")
        t0 = time.perf_counter()
        self._positions = arr
        if self.style == "licorice":
            self._pos_dev = wp.array(arr, dtype=wp.vec3, device=self.device)
            if self._count:
                wp.launch(
                    half_bonds_kernel,
                    self._count,
                    (self._pos_dev, self._atom, self._other, self._p0, self._p1),
                    device=self.device,
                )
        else:
            self._tube(arr)
        self._upload_ms = (time.perf_counter() - t0) * 1e3

    def set_secondary(self, codes: npt.NDArray[np.uint8] | None) -> None:
        """Per atom of this layer: 0 coil, 1 helix, 2 strand (`SECONDARY`); None: all coil.
        The tube draws helices as wide cylinders along their axis and strands wider."""
        self._secondary = None if codes is None else np.asarray(codes, dtype=np.uint8)

    def _tube(self, positions: npt.NDArray[np.float32]) -> None:
        """Capsules along every trace piece (`tube_spans`)."""
        assert self._topology is not None
        if self._pieces is None:
            self._pieces = trace_pieces(self._topology, positions)
        p0, p1, owner, scale = tube_spans(self._pieces, positions, self._secondary)
        count = len(p0)
        self._alloc_capsules(count)
        if not count:
            self._atom_host = np.zeros(0, np.int32)
            return
        self._atom_host = owner
        self._atom = wp.array(owner, dtype=wp.int32, device=self.device)
        for dest, host, kind in ((self._p0, p0, wp.vec3), (self._p1, p1, wp.vec3)):
            wp.copy(dest, wp.array(host.astype(np.float32), dtype=kind, device=self.device))
        wp.copy(self._scale, wp.array(scale.astype(np.float32), dtype=float, device=self.device))

    def set_history(self, *args: Any, **kwargs: Any) -> None:
        """Shapes are drawn at the newest frame (time smoothing applies to densities)."""

    def _radius(self, params: RenderParams, radius: float | None) -> float:
        if radius is not None:
            return float(radius)
        return STICK_RADIUS_A if self.style == "licorice" else TUBE_RADIUS_A

    def render(
        self,
        params: RenderParams,
        camera: Camera,
        width: int,
        height: int,
        radius: float | None = None,
        tile: tuple[int, int, int, int] | None = None,
    ) -> None:
        """Draw the shapes; `tile` (x0, y0, w, h): only that rectangle of the width x height
        image, as the whole image has it (the outputs are then w x h)."""
        if self._topology is None or self._positions is None:
            raise RenderError("set_topology and set_positions come before render")
        t0 = time.perf_counter()
        w, h = int(width), int(height)
        pw, ph = (int(tile[2]), int(tile[3])) if tile is not None else (w, h)
        self._alloc_pixels(pw * ph)
        r = self._radius(params, radius)
        dev = self.device
        frame = camera_frame(camera, w, h)
        color_key = (params.color_by, tuple(params.uniform_color), self._count, id(self._atom_host))
        if self._count and color_key != self._color_key:
            per_atom = colors.atom_colors(self._topology, params.color_by, params.uniform_color)
            wp.copy(self._colors, wp.array(per_atom[self._atom_host], dtype=wp.uint32, device=dev))
            self._color_key = color_key
        t_grid = time.perf_counter()
        bvh_id = 0
        if self._count:
            args = (self._p0, self._p1, r, self._scale, self._lowers, self._uppers)
            wp.launch(bounds_kernel, self._count, args, device=dev)
            if self._bvh is None:  # the arrays hold exactly the capsules
                self._bvh = wp.Bvh(self._lowers, self._uppers)
            else:
                self._bvh.refit()
            bvh_id = self._bvh.id
        t_cast = time.perf_counter()
        sh = raycast.shading(params, frame, coverage=self.coverage)  # no occlusion on shapes
        near, far = self._fog_range(frame.eye, frame.forward, r * HELIX_SCALE)
        cam = raycast.camera_data(frame, tile)
        if self._count:
            wp.launch(
                capsule_kernel,
                raycast.launch_size(pw, ph),
                (
                    bvh_id, self._p0, self._p1, r, self._scale, self._colors, self._atom, cam,
                    sh, near, far,
                    self._rgba, self._depth, self._ids,
                ),
                device=dev,
            )  # fmt: skip
        else:
            bg = 0 if self.coverage else int(colors.pack_rgba([params.background])[0])
            self._rgba.fill_(bg)
            self._depth.fill_(math.inf)
            self._ids.fill_(-1)
        wp.synchronize_device(dev)
        t_end = time.perf_counter()
        self.timings = {
            "upload": getattr(self, "_upload_ms", 0.0),
            "grid": (t_cast - t_grid) * 1e3,
            "raycast": (t_end - t_cast) * 1e3,
            "total": (t_end - t0) * 1e3 + getattr(self, "_upload_ms", 0.0),
        }
        self._image = (pw, ph)

    def _fog_range(
        self, eye: npt.NDArray[np.float64], forward: npt.NDArray[np.float64], r: float
    ) -> tuple[float, float]:
        """The depth cue's range: the layer's atoms' bounding sphere seen along the view."""
        pos = self._positions
        if pos is None or not len(pos):
            return 0.0, 1.0
        lo, hi = pos.min(axis=0).astype(np.float64) - r, pos.max(axis=0).astype(np.float64) + r
        center, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
        dc = float((center - eye) @ forward)
        return max(dc - radius, 0.0), dc + radius

    # ------------------------------------------------------------------ outputs

    def _outputs(self) -> tuple[Any, Any, Any]:
        return self._rgba, self._depth, self._ids
