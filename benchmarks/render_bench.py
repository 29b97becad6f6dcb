"""Render benchmark: frame rate of the density ray caster from 496 to 10,000,000 atoms, with
the baselines measured in the same run.

Every timed frame uploads new positions (a small random displacement of the system, written
into the renderer's page-locked buffer beforehand), rebuilds the grid on the device and casts
all rays; the frame time is the host wall clock of `set_positions` + `render` (which
synchronises). Systems are built from the adenylate kinase structure 4AKE (3,341 atoms with
hydrogens, benchmarks/data/adk_4ake.npz): a compact subset for the thesis sizes, randomly
rotated and jittered copies on a lattice for larger systems.

Baselines (iso mode, same step and camera):
  naive      the same density, no empty-space skipping (every lattice sample evaluated)
  hashgrid   wp.HashGrid rebuilt per frame, fixed-step march, the same refinement and lighting
  resample   QuickSurf/Krone: splat the density onto a voxel grid per frame, march it with
             trilinear filtering (several voxel sizes); image error against a fine-step
             reference shows what each resolution buys

The run starts by timing a few register caps of the marching kernels (occupancy against
spills) at 100k and 1M atoms and uses the fastest for everything after it (recorded in the
JSON as `max_registers`).

    python benchmarks/render_bench.py --out benchmarks/results/render_h100.json
    python benchmarks/render_bench.py --quick --device cpu      # smoke test, tiny sizes
    python benchmarks/render_bench.py --table benchmarks/results/render_h100.json

Kept whole: one benchmark is one file that runs on its own on a GPU host (`python
benchmarks/render_bench.py`), and its `Bench` class holds the systems, cameras and renderers every
row of one run is timed against.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, no_type_check

import numpy as np
import warp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from protocol import Camera, RenderParams, Topology, WireArray
from server.render import Renderer, raycast, visibility
from server.render import device as render_device
from server.render.camera import fit_camera, orbit
from server.render.density import GaussianField, gaussian_value
from server.render.graphs import GraphCache
from server.render.raycast import (
    CameraData,
    Shading,
    camera_data,
    camera_ray,
    clip_box,
    facing,
    key_light_direction,
    launch_size,
    lit,
    pack_rgba,
    pixel_of,
)
from server.render.tuning import SPLIT_LANES, VOLUME_REGISTERS, Tuning
from server.session.steering import merge_patch

wp: Any = warp  # host API calls are dynamic

DATA = Path(__file__).parent / "data" / "adk_4ake.npz"
THESIS = {496: "villin", 1049: "dna", 2500: "1VIS", 5684: "1TII", 10_000: "1AF6"}
FULL_SIZES = [496, 1049, 2500, 5684, 10_000, 100_000, 1_000_000, 10_000_000]
FULL_RES = [(500, 500), (1920, 1080)]
REFINE = 5

# ----------------------------------------------------------------------------- systems


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def distance_bonds(pos: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """Bonds between atoms closer than 1.9 A (1.3 A with a hydrogen), in blocks of rows."""
    light = np.array([str(e).upper().startswith("H") for e in elements])
    out = []
    for a in range(0, len(pos), 1024):
        d = np.linalg.norm(pos[a : a + 1024, None] - pos[None], axis=-1)
        limit = np.where(light[a : a + 1024, None] | light[None, :], 1.3, 1.9)
        i, j = np.nonzero(d < limit)
        keep = i + a < j
        out.append(np.stack([i[keep] + a, j[keep]], axis=1))
    return np.concatenate(out).astype(np.int32)


def build_system(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, 3) float32 positions, (n,) element symbols and (m, 2) bonds of a protein-like
    system (bonds by distance in adenylate kinase, copied with every tile)."""
    base = np.load(DATA)
    pos0 = base["positions"].astype(np.float64)
    el0 = base["elements"]
    pos0 = pos0 - pos0.mean(axis=0)
    bonds0 = distance_bonds(pos0, el0)
    if n <= len(pos0):
        idx = np.sort(np.argsort(np.linalg.norm(pos0, axis=1), kind="stable")[:n])
        where = np.full(len(pos0), -1)
        where[idx] = np.arange(n)
        kept = bonds0[(where[bonds0[:, 0]] >= 0) & (where[bonds0[:, 1]] >= 0)]
        return pos0[idx].astype(np.float32), el0[idx], where[kept].astype(np.int32)
    rng = np.random.default_rng(seed)
    tiles = math.ceil(n / len(pos0))
    m = math.ceil(tiles ** (1 / 3))
    spacing = 0.85 * float(np.ptp(pos0, axis=0).max())  # neighbours just touch
    grid = np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3)
    grid = grid - (m - 1) / 2
    cells = grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")[:tiles]] * spacing
    out = np.empty((tiles * len(pos0), 3), dtype=np.float32)
    for t, c in enumerate(cells):
        block = pos0 @ random_rotation(rng).T + c + rng.normal(size=3) * 1.0
        block += rng.normal(size=block.shape) * 0.3
        out[t * len(pos0) : (t + 1) * len(pos0)] = block
    bonds = np.concatenate([bonds0 + t * len(pos0) for t in range(tiles)])
    bonds = bonds[(bonds < n).all(axis=1)]
    return out[:n], np.tile(el0, tiles)[:n], bonds.astype(np.int32)


def topology_of(elements: np.ndarray, bonds: np.ndarray | None = None) -> Topology:
    n = len(elements)
    els = [str(e) for e in elements.tolist()] if elements.dtype == object else elements.tolist()
    return Topology.model_construct(
        n_atoms=n,
        elements=els,
        names=els,
        residue_ids=WireArray.from_numpy(np.zeros(n, np.int32), "<i4"),
        residue_names=["ALA"] * n,
        chain_ids=["A"] * n,
        bonds=WireArray.from_numpy(np.zeros((0, 2), np.int32) if bonds is None else bonds, "<i4"),
        radii=None,
        charges=None,
        bfactors=None,
    )


def jittered_frames(pos: np.ndarray, count: int, seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [
        (pos + rng.normal(scale=0.05, size=pos.shape).astype(np.float32)).astype(np.float32)
        for _ in range(count)
    ]


# ----------------------------------------------------------------------------- baselines


@wp.func
@no_type_check
def hash_density(
    grid: wp.uint64, pts: wp.array[wp.vec3], p: wp.vec3, r: float, inv2s2: float
) -> wp.vec4:
    q = wp.hash_grid_query(grid, p, r)
    idx = wp.int32(0)
    s = wp.float32(0.0)
    g = wp.vec3(0.0, 0.0, 0.0)
    r2 = r * r
    while wp.hash_grid_query_next(q, idx):
        dv = pts[idx] - p
        d2 = wp.dot(dv, dv)
        if d2 < r2:
            t = wp.exp(-d2 * inv2s2)
            s += t
            g += dv * (2.0 * inv2s2 * t)
    return wp.vec4(g[0], g[1], g[2], s)


@wp.kernel(enable_backward=False)
@no_type_check
def hash_march_kernel(
    grid: wp.uint64,
    pts: wp.array[wp.vec3],
    r: float,
    inv2s2: float,
    lo: wp.vec3,
    hi: wp.vec3,
    cam: CameraData,
    iso: float,
    dt: float,
    sh: Shading,
    rgba: wp.array[wp.uint32],
    depth: wp.array[float],
):
    x, y, ok = pixel_of(cam, wp.tid())
    if ok == 0:
        return
    pix = y * cam.width + x
    o, d = camera_ray(cam, x, y)
    t0, t1 = clip_box(o, d, lo, hi)
    hit = wp.float32(wp.inf)
    if t0 < t1:
        k = int(wp.ceil(t0 / dt))
        while float(k) * dt < t1:
            t = float(k) * dt
            if hash_density(grid, pts, o + d * t, r, inv2s2)[3] >= iso:
                a = t - dt
                b = t
                for _i in range(REFINE):
                    mid = 0.5 * (a + b)
                    if hash_density(grid, pts, o + d * mid, r, inv2s2)[3] >= iso:
                        b = mid
                    else:
                        a = mid
                hit = 0.5 * (a + b)
                break
            k += 1
    if hit == wp.inf:
        rgba[pix] = pack_rgba(sh.background)
        depth[pix] = wp.inf
    else:
        vg = hash_density(grid, pts, o + d * hit, r, inv2s2)
        n = facing(wp.vec3(vg[0], vg[1], vg[2]), d)
        rgba[pix] = pack_rgba(lit(sh, sh.uniform_color, n, -d, 1.0))
        depth[pix] = hit


@wp.kernel(enable_backward=False)
@no_type_check
def splat_kernel(f: GaussianField, origin: wp.vec3, h: float, vol: wp.array3d[float]):
    i, j, k = wp.tid()
    vol[i, j, k] = gaussian_value(f, origin + wp.vec3(float(i), float(j), float(k)) * h)


@wp.func
@no_type_check
def trilinear(vol: wp.array3d[float], origin: wp.vec3, inv_h: float, p: wp.vec3) -> float:
    q = (p - origin) * inv_h
    nx = vol.shape[0]
    ny = vol.shape[1]
    nz = vol.shape[2]
    i = wp.clamp(int(wp.floor(q[0])), 0, nx - 2)
    j = wp.clamp(int(wp.floor(q[1])), 0, ny - 2)
    k = wp.clamp(int(wp.floor(q[2])), 0, nz - 2)
    fx = wp.clamp(q[0] - float(i), 0.0, 1.0)
    fy = wp.clamp(q[1] - float(j), 0.0, 1.0)
    fz = wp.clamp(q[2] - float(k), 0.0, 1.0)
    c00 = vol[i, j, k] * (1.0 - fx) + vol[i + 1, j, k] * fx
    c10 = vol[i, j + 1, k] * (1.0 - fx) + vol[i + 1, j + 1, k] * fx
    c01 = vol[i, j, k + 1] * (1.0 - fx) + vol[i + 1, j, k + 1] * fx
    c11 = vol[i, j + 1, k + 1] * (1.0 - fx) + vol[i + 1, j + 1, k + 1] * fx
    c0 = c00 * (1.0 - fy) + c10 * fy
    c1 = c01 * (1.0 - fy) + c11 * fy
    return c0 * (1.0 - fz) + c1 * fz


@wp.kernel(enable_backward=False)
@no_type_check
def grid_march_kernel(
    vol: wp.array3d[float],
    origin: wp.vec3,
    h: float,
    cam: CameraData,
    iso: float,
    dt: float,
    sh: Shading,
    rgba: wp.array[wp.uint32],
    depth: wp.array[float],
):
    x, y, ok = pixel_of(cam, wp.tid())
    if ok == 0:
        return
    pix = y * cam.width + x
    inv_h = 1.0 / h
    hi = origin + wp.vec3(
        float(vol.shape[0] - 1) * h, float(vol.shape[1] - 1) * h, float(vol.shape[2] - 1) * h
    )
    o, d = camera_ray(cam, x, y)
    t0, t1 = clip_box(o, d, origin, hi)
    hit = wp.float32(wp.inf)
    if t0 < t1:
        k = int(wp.ceil(t0 / dt))
        while float(k) * dt < t1:
            t = float(k) * dt
            if trilinear(vol, origin, inv_h, o + d * t) >= iso:
                a = t - dt
                b = t
                for _i in range(REFINE):
                    mid = 0.5 * (a + b)
                    if trilinear(vol, origin, inv_h, o + d * mid) >= iso:
                        b = mid
                    else:
                        a = mid
                hit = 0.5 * (a + b)
                break
            k += 1
    if hit == wp.inf:
        rgba[pix] = pack_rgba(sh.background)
        depth[pix] = wp.inf
    else:
        p = o + d * hit
        e = 0.5 * h
        gx = trilinear(vol, origin, inv_h, p + wp.vec3(e, 0.0, 0.0)) - trilinear(
            vol, origin, inv_h, p - wp.vec3(e, 0.0, 0.0)
        )
        gy = trilinear(vol, origin, inv_h, p + wp.vec3(0.0, e, 0.0)) - trilinear(
            vol, origin, inv_h, p - wp.vec3(0.0, e, 0.0)
        )
        gz = trilinear(vol, origin, inv_h, p + wp.vec3(0.0, 0.0, e)) - trilinear(
            vol, origin, inv_h, p - wp.vec3(0.0, 0.0, e)
        )
        n = facing(wp.vec3(gx, gy, gz), d)
        rgba[pix] = pack_rgba(lit(sh, sh.uniform_color, n, -d, 1.0))
        depth[pix] = hit


# ----------------------------------------------------------------------------- timing


def profile_frame(
    r: Renderer, positions: np.ndarray, params: RenderParams, cam: Camera, w: int, h: int
) -> dict[str, float]:
    """The device activities of one frame (upload, grid kernels, sort, cast) and their times
    in ms (`wp.timing_begin`; a frame launched one by one, not replayed as a graph)."""
    graphs = r._graphs
    r._graphs = GraphCache(r.device, 1, False, "profile")  # every launch timed on its own
    try:
        r.set_positions(positions, check_finite=False)
        wp.timing_begin()
        r.render(params, cam, w, h)
        results = wp.timing_end()
    finally:
        r._graphs = graphs
    acts: dict[str, float] = {}
    for t in results:
        acts[t.name] = acts.get(t.name, 0.0) + float(t.elapsed)
    return acts


def summarize(walls: list[float], stages: list[dict[str, float]]) -> dict[str, Any]:
    w = np.asarray(walls)
    out: dict[str, Any] = {
        "frames": len(walls),
        "median_ms": float(np.median(w)) if len(w) else None,
        "p10_ms": float(np.percentile(w, 10)) if len(w) else None,
        "p90_ms": float(np.percentile(w, 90)) if len(w) else None,
    }
    out["fps"] = 1000.0 / out["median_ms"] if out["median_ms"] else None
    if stages:
        out["stages_ms"] = {k: float(np.median([s[k] for s in stages])) for k in stages[0]}
    return out


def labelled(options: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """A set of Renderer options from the command line: its "label" (else the set itself, as
    JSON) and the options without it."""
    kw = dict(options)
    return str(kw.pop("label", json.dumps(options))), kw


class Clock:
    """Wall-clock budget of the whole run; sections stop early rather than overrun."""

    def __init__(self, budget_s: float) -> None:
        self.end = time.perf_counter() + budget_s

    def left(self) -> float:
        return self.end - time.perf_counter()


def image_error(a: np.ndarray, b: np.ndarray, da: np.ndarray, db: np.ndarray) -> dict[str, float]:
    """Mean |RGB difference| / 255, the share of pixels off by more than 16/255, disagreement
    on hit vs background, and the median depth difference where both hit."""
    diff = np.abs(a[..., :3].astype(np.int32) - b[..., :3].astype(np.int32)).max(axis=-1)
    ha, hb = np.isfinite(da), np.isfinite(db)
    both = ha & hb
    return {
        "mean_abs_rgb": float(diff.mean() / 255.0),
        "pixels_off": float((diff > 16).mean()),
        "coverage_mismatch": float((ha != hb).mean()),
        "median_depth_err": float(np.median(np.abs(da[both] - db[both]))) if both.any() else 0.0,
    }


# ----------------------------------------------------------------------------- sections


class Bench:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.device = render_device.resolve(args.device)
        self.clock = Clock(args.budget_s)
        dev = wp.get_device(self.device)
        self.gpu = str(dev.name) if dev.is_cuda else platform.processor() or "cpu"
        self.results: dict[str, Any] = {
            "benchmark": "render",
            "gpu": self.gpu,
            "device": self.device,
            "warp": wp.config.version,
            "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "quick": bool(args.quick),
            "params": RenderParams().model_dump(mode="json"),
            "frames": [],
            "grid_build": [],
            "baselines": [],
            "ablation": [],
            "graphs": [],
            "registers": [],
            "budgets": [],
            "blocks": [],
            "densities": [],
            "march_budget": args.march_budget,
            "split_lanes": args.split_lanes,
            "max_registers": args.max_registers,
            "volume_max_registers": args.volume_max_registers,
            "visible_rays": {"stride": visibility.STRIDE, "depth": visibility.DEPTH},
            "notes": [],
        }
        self.systems: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def save(self) -> None:
        out = Path(self.args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(self.results, indent=1))

    def system(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if n not in self.systems:
            self.systems = {n: build_system(n)}
        return self.systems[n]

    def renderer(self, n: int, **kw: Any) -> tuple[Renderer, list[np.ndarray]]:
        pos, el, bonds = self.system(n)
        kw.setdefault("max_registers", self.results["max_registers"])
        kw.setdefault("volume_max_registers", self.results["volume_max_registers"])
        kw.setdefault("march_budget", self.results["march_budget"])
        kw.setdefault("split_lanes", self.results["split_lanes"])
        r = Renderer(self.device, max_atoms=max(n, 1), tuning=Tuning.of(kw))
        r.set_topology(topology_of(el, bonds))
        frames = jittered_frames(pos, 3)
        return r, frames

    def frame_step(
        self,
        r: Renderer,
        frames: list[np.ndarray],
        params: RenderParams,
        cam: Camera,
        w: int,
        h: int,
        turn: float = 0.0,
        views: int = 1,
    ) -> Callable[[int], dict[str, float]]:
        """One timed frame of new positions (written into the page-locked buffer before the
        clock starts, as the server's decoder does), or with `turn` > 0 of still positions
        seen by a camera turning `turn` degrees of yaw a frame (a steerer dragging the view
        of a paused simulation). With `views` > 1 each frame is seen by that many cameras
        around the system (viewers with cameras of their own): the times are their sums."""
        buf = r.host_positions()
        if turn > 0:
            r.set_positions(frames[0])
        yaws = [360.0 * j / views for j in range(views)]

        def step(i: int) -> dict[str, float]:
            if turn <= 0:
                np.copyto(buf, frames[i % len(frames)])
            t0 = time.perf_counter()
            if turn <= 0:
                # as in the server, where the protocol decoder has already checked finiteness
                r.set_positions(buf, check_finite=False)
            st: dict[str, float] = {}
            for yaw in yaws:
                view = cam if turn <= 0 and yaw == 0.0 else orbit(cam, turn * i + yaw, 0.0)
                r.render(params, view, w, h)
                for k, v in r.timings.items():
                    st[k] = st.get(k, 0.0) + v
            st["wall"] = (time.perf_counter() - t0) * 1e3
            return st

        return step

    def timed(self, step: Callable[[int], dict[str, float]], frames: int) -> dict[str, Any]:
        """Times frames; the wall time excludes writing the next positions into the buffer."""
        walls: list[float] = []
        stages: list[dict[str, float]] = []
        stop = time.perf_counter() + min(self.args.max_config_s, max(self.clock.left(), 0.0))
        for i in range(self.args.warmup + frames):
            st = step(i)
            if i >= self.args.warmup:
                walls.append(st.pop("wall"))
                stages.append(st)
            if time.perf_counter() > stop and len(walls) >= 3:
                break
        return summarize(walls, stages)

    def log(self, text: str) -> None:
        print(f"[{self.args.budget_s - self.clock.left():7.1f}s] {text}", flush=True)

    # ---- main table
    def main_table(self, sizes: list[int], res: list[tuple[int, int]], grid: bool) -> None:
        for n in sizes:
            if self.clock.left() < 20:
                self.results["notes"].append(f"main table stopped before N={n}: time budget")
                break
            t0 = time.perf_counter()
            r, frames = self.renderer(n)
            setup_s = time.perf_counter() - t0
            mem = r.memory_bytes()
            for w, h in res:
                cam = fit_camera(frames[0], w, h)
                for mode in ("iso", "volume"):
                    params = RenderParams(mode=mode)  # type: ignore[arg-type]
                    s = self.timed(self.frame_step(r, frames, params, cam, w, h), self.args.frames)
                    beyond = mem["per_atom"] + mem["grid"] + mem["other"]
                    entry = {
                        "n_atoms": n,
                        "system": THESIS.get(n, "tiled 4AKE"),
                        "width": w,
                        "height": h,
                        "mode": mode,
                        **s,
                        "coverage": float(np.isfinite(r.read_depth()).mean()),
                        "bytes_per_atom": beyond / n,
                        "memory_bytes": mem,
                        "setup_s": setup_s,
                    }
                    self.results["frames"].append(entry)
                    self.save()
                    self.log(
                        f"N={n:>9,} {w}x{h} {mode:6s} {s['median_ms']:8.3f} ms "
                        f"{s['fps']:8.1f} fps  stages {fmt_stages(s.get('stages_ms', {}))}"
                    )
                    if self.args.images and n == self.args.image_n and w == max(res)[0]:
                        from PIL import Image

                        img = Image.fromarray(r.read_rgba()[..., :3]).resize((960, 540))
                        img.save(Path(self.args.images) / f"render_{mode}_{n}.jpg", quality=85)
            if grid and self.clock.left() > 15:
                self.grid_build(n, r, frames)

    # ---- the geodesic and carved densities next to the classical one
    def densities(self, cases: list[tuple[int, int, int]]) -> None:
        """Iso frames of the classical, geodesic and carved densities (strength 1, relative
        level) on the same renderer and frames, one after the other, grid rebuilt every frame;
        and each density's device bytes per atom (the geodesic's route tables included)."""
        for n, w, h in cases:
            if self.clock.left() < 20:
                self.results["notes"].append(f"densities section stopped before N={n}: budget")
                break
            r, frames = self.renderer(n)
            cam = fit_camera(frames[0], w, h)
            row: dict[str, Any] = {"n_atoms": n, "system": THESIS.get(n, "tiled 4AKE")}
            row.update(width=w, height=h)
            # the geodesic density as the renderer chooses (`geodesic`), read from its grid
            # wherever that fits (`geodesic_grid`), and its routes walked at every sample
            # (`geodesic_routes`, the control of the grid)
            r_grid = self.renderer(n, geodesic_volume=True)[0]
            r_routes = self.renderer(n, geodesic_volume=False)[0]
            runs = [("classical", r), ("geodesic", r), ("geodesic_grid", r_grid)]
            runs += [("geodesic_routes", r_routes), ("carved", r)]
            for label, rr in runs:
                space = label.split("_")[0]
                params = RenderParams(scale_space=space)  # type: ignore[arg-type]
                row[label] = self.timed(
                    self.frame_step(rr, frames, params, cam, w, h), self.args.frames
                )
                mem = rr.memory_bytes()
                extra = mem.get("skeleton", 0) if space == "carved" else 0
                extra += mem.get("geodesic", 0) if space == "geodesic" else 0
                row[f"{label}_bytes_per_atom"] = (
                    mem["per_atom"] + mem["grid"] + mem["other"] + extra
                ) / n
                if space == "geodesic":
                    row[f"{label}_drawn_as"] = rr.last_density
                    need = rr._gvol.last_need() if rr._gvol is not None else None
                    if need is not None:
                        row[f"{label}_grid"] = {"spacing": need[0], "points": need[1]}
                        row[f"{label}_grid"].update(bricks_walked=need[2], pixels=w * h)
            del r_grid, r_routes
            for label in ("geodesic", "geodesic_grid"):
                row[f"{label}_over_routes_fps"] = (
                    row["geodesic_routes"]["median_ms"] / row[label]["median_ms"]
                )
            for space in ("geodesic", "geodesic_grid", "geodesic_routes", "carved"):
                row[f"{space}_over_classical_fps"] = (
                    row["classical"]["median_ms"] / row[space]["median_ms"]
                )
            self.results["densities"].append(row)
            self.save()
            self.log(
                f"N={n:>9,} {w}x{h} classical {row['classical']['median_ms']:.3f} ms, geodesic "
                f"{row['geodesic']['median_ms']:.3f} ms ({row['geodesic_over_classical_fps']:.2f}x "
                f"fps, {row['geodesic_drawn_as']}; grid {row['geodesic_grid']['median_ms']:.3f} "
                f"ms as {row['geodesic_grid_drawn_as']}; routes per sample "
                f"{row['geodesic_routes']['median_ms']:.3f} ms), carved "
                f"{row['carved']['median_ms']:.3f} ms"
            )

    # ---- large systems: cell size, and the next upload overlapped with the last render
    def scale(
        self,
        sizes: list[int],
        cells_list: list[float],
        w: int,
        h: int,
        tries: list[dict[str, Any]] | None = None,
        params: RenderParams | None = None,
    ) -> None:
        """Frames of large systems (iso, or `params`) for each cell size, one by one
        (set_positions, render) and pipelined (render(wait=False), the next frame's
        set_positions, finish: the upload of frame k+1 runs on its own stream while frame k
        renders). Two frames alternate, each
        written once into one of the renderer's two page-locked buffers, so the timed loop is
        the server's: upload, grid rebuild and cast of a new frame every time. `tries` are
        sets of Renderer options, each with a "label", run one after the other for every cell
        size (default: the renderer's defaults)."""
        rp = params if params is not None else RenderParams()  # the frames' render parameters
        for n in sizes:
            if self.clock.left() < 60:
                self.results["notes"].append(f"scale section stopped before N={n}")
                return
            t0 = time.perf_counter()
            pos, el, bonds = self.system(n)
            frames = jittered_frames(pos, 2)
            top = topology_of(el, bonds if n <= 10_000_000 else None)
            setup_s = time.perf_counter() - t0
            for cells, t in itertools.product(cells_list, tries or [{"label": "default"}]):
                if self.clock.left() < 30:
                    return
                label, kw = labelled(t)
                kw.setdefault("max_registers", self.results["max_registers"])
                kw.setdefault("volume_max_registers", self.results["volume_max_registers"])
                tuning = Tuning.of({**kw, "cells_per_cutoff": cells})
                r = Renderer(self.device, max_atoms=n, tuning=tuning)
                r.set_topology(top)
                bufs = []
                for f in frames:
                    buf = r.host_positions()
                    np.copyto(buf, f)
                    r.set_positions(buf, check_finite=False)
                    bufs.append(buf)
                cam = fit_camera(frames[0], w, h)
                mem = r.memory_bytes()
                for piped in (False, True):
                    walls: list[float] = []
                    stages: list[dict[str, float]] = []
                    count = self.args.warmup + self.args.frames
                    stop = time.perf_counter() + min(self.args.max_config_s, self.clock.left())
                    r.set_positions(bufs[0], check_finite=False)
                    r.render(rp, cam, w, h, wait=not piped)
                    last = time.perf_counter()
                    for i in range(1, count + 1):
                        if piped:
                            r.set_positions(bufs[i % 2], check_finite=False)
                            r.finish()
                            stages.append(dict(r.timings))
                            r.render(rp, cam, w, h, wait=False)
                        else:
                            r.set_positions(bufs[i % 2], check_finite=False)
                            r.render(rp, cam, w, h)
                            stages.append(dict(r.timings))
                        now = time.perf_counter()
                        if i > self.args.warmup:
                            walls.append((now - last) * 1e3)
                        last = now
                        if now > stop and len(walls) >= 3:
                            break
                    r.finish()
                    summary = summarize(walls, stages[self.args.warmup :])
                    if piped and wp.get_device(self.device).is_cuda:
                        summary["activities_ms"] = profile_frame(r, bufs[0], rp, cam, w, h)
                    entry = {
                        "n_atoms": n,
                        "width": w,
                        "height": h,
                        "cells_per_cutoff": cells,
                        "label": label,
                        "options": kw,
                        "params": rp.model_dump(mode="json", exclude_defaults=True),
                        "pipelined": piped,
                        **summary,
                        "bytes_per_atom": (mem["per_atom"] + mem["grid"] + mem["other"]) / n,
                        "memory_bytes": mem,
                        "setup_s": setup_s,
                    }
                    self.results.setdefault("scale", []).append(entry)
                    self.save()
                    self.log(
                        f"scale {label} N={n:,} cells/cutoff={cells:g} piped={piped}: "
                        f"{summary['median_ms']:.2f} ms ({summary['fps']:.1f} fps) "
                        f"{fmt_stages(summary.get('stages_ms', {}))}"
                    )
                del r

    # ---- renderer options against each other
    def variants(
        self, cases: list[tuple[int, int, int]], params: RenderParams, tries: list[dict[str, Any]]
    ) -> None:
        """The same frames with each set of Renderer options (`--variants`, a JSON list of
        keyword sets, each with a "label" and optionally "params" over `params`), one after
        the other: new positions every frame, or (`--variant-turn` degrees) still positions and
        a turning camera, each frame seen by `--variant-views` cameras."""
        base = params
        for n, w, h in cases:
            for t in tries:
                if self.clock.left() < 20:
                    return
                label, kw = labelled(t)
                # merged deeply and validated: {"lighting": {"diffuse": 0}} keeps the rest
                params, _ = merge_patch(base, kw.pop("params", {}))
                matched = bool(kw.pop("matched_level", False))
                r, frames = self.renderer(n, **kw)
                cam = fit_camera(frames[0], w, h)
                if matched:  # the absolute level that draws the relative level's surface
                    r.set_positions(frames[0])
                    r.render(params, cam, w, h)
                    level = params.iso_level * r.density_scale()
                    params = params.model_copy(
                        update={"level_scale": "absolute", "iso_level": level}
                    )
                turn = float(self.args.variant_turn)
                views = int(self.args.variant_views)
                step = self.frame_step(r, frames, params, cam, w, h, turn, views)
                st = self.timed(step, self.args.frames)
                self.results.setdefault("variants", []).append(
                    {"n_atoms": n, "width": w, "height": h, "label": label, "options": kw,
                     "params": params.model_dump(mode="json", exclude_defaults=True),
                     "matched_level": matched, "turn_deg": turn, "views": views,
                     "parts": r.last_parts, **st}
                )  # fmt: skip
                self.save()
                self.log(
                    f"variant {label} N={n:,} {w}x{h}: {st['median_ms']:.3f} ms "
                    f"{fmt_stages(st.get('stages_ms', {}))}"
                )
                del r

    # ---- what a far-field split would have to beat
    def farfield(
        self, cases: list[tuple[int, int, int]], params: RenderParams, spacings: list[float]
    ) -> None:
        """The most a far-field split could save, against what building its far grid costs.

        A split keeps each Gaussian exact to 2.5 sigma and reads the rest from a coarse grid
        rebuilt every frame. Its saving is at most today's frame less the frame at a 2.5-sigma
        cutoff (no far part at all, the same frames and camera); its cost is at least the far
        grid's build: every node within the atoms' reach summing the atoms near it, which is
        `splat_kernel` over the frame's box (the far part walks the same atoms as the whole
        Gaussian, so this is its build's time), at `spacings` sigmas between nodes. The
        lookups (a tricubic read per sample) would cost more still."""
        for n, w, h in cases:
            if self.clock.left() < 30:
                return
            r, frames = self.renderer(n)
            cam = fit_camera(frames[0], w, h)
            entry: dict[str, Any] = {"n_atoms": n, "width": w, "height": h}
            for label, p in (
                ("today", params),
                (
                    "near part only (cutoff 2.5 sigma)",
                    params.model_copy(update={"cutoff_sigmas": 2.5}),
                ),
            ):
                st = self.timed(self.frame_step(r, frames, p, cam, w, h), self.args.frames)
                entry[label] = st
                self.log(f"farfield N={n:,} {w}x{h} {label}: {st['median_ms']:.3f} ms")
            saving = (
                entry["today"]["median_ms"]
                - entry["near part only (cutoff 2.5 sigma)"]["median_ms"]
            )
            entry["saving_at_most_ms"] = saving
            pos = frames[0]
            margin = r.reach(params)
            lo = pos.min(0) - margin
            hi = pos.max(0) + margin
            buf = r.host_positions()
            builds = []
            for k in spacings:
                v = k * params.sigma_A
                dims = np.ceil((hi - lo) / v).astype(int) + 1
                rec: dict[str, Any] = {
                    "spacing_sigmas": k,
                    "spacing_A": v,
                    "nodes": int(np.prod(dims)),
                }
                if rec["nodes"] > self.args.max_voxels:
                    rec["skipped"] = (
                        f"{rec['nodes']:,} nodes exceed the cap of {self.args.max_voxels:,}"
                    )
                    builds.append(rec)
                    continue
                vol = wp.zeros(tuple(int(x) for x in dims), dtype=float, device=self.device)
                origin = wp.vec3(*lo)

                def build(
                    i: int,
                    vol: Any = vol,
                    origin: Any = origin,
                    v: float = v,
                    r: Renderer = r,
                    buf: np.ndarray = buf,
                    frames: list[np.ndarray] = frames,
                ) -> dict[str, float]:
                    np.copyto(buf, frames[i % 3])
                    r.set_positions(buf, check_finite=False)
                    f = r.prepare(params)
                    wp.synchronize_device(self.device)
                    t0 = time.perf_counter()
                    wp.launch(splat_kernel, vol.shape, (f, origin, v, vol), device=self.device)
                    wp.synchronize_device(self.device)
                    return {"wall": (time.perf_counter() - t0) * 1e3}

                rec.update(self.timed(build, self.args.frames))
                rec["build_over_saving"] = rec["median_ms"] / saving if saving > 0 else None
                builds.append(rec)
                self.log(
                    f"farfield N={n:,} far grid at {k} sigma ({rec['nodes']:,} nodes): build "
                    f"{rec['median_ms']:.3f} ms against a saving of at most {saving:.3f} ms"
                )
                del vol
            entry["far_grid_builds"] = builds
            self.results.setdefault("farfield", []).append(entry)
            self.save()
            del r

    # ---- the work of a frame, whatever the device
    def passes(self, cases: list[tuple[int, int, int]], params: RenderParams) -> None:
        """The density passes (four samples each) the rays of one frame take, in iso and in
        volume mode with the same parameters otherwise (`count_passes`): counts, not times,
        the same on any device, so a CPU run tells what a GPU frame has to do (one march per
        ray: split rays would count their lanes' passes past the crossing)."""
        for n, w, h in cases:
            r, frames = self.renderer(n, count_passes=True, march_budget=0)
            r.set_positions(frames[0])
            cam = fit_camera(frames[0], w, h)
            entry: dict[str, Any] = {"n_atoms": n, "width": w, "height": h}
            for mode in ("iso", "volume"):
                r.render(params.model_copy(update={"mode": mode}), cam, w, h)
                counts = r.read_pass_counts().astype(np.float64)
                reached = np.isfinite(r.read_depth())
                entry[mode] = {
                    "per_ray": float(counts.mean()),
                    "per_ray_reaching": float(counts[reached].mean()) if reached.any() else 0.0,
                    "rays_reaching": float(reached.mean()),
                    "p99": float(np.percentile(counts, 99)),
                    "max": int(counts.max()),
                    "tile_use": tile_use(counts),
                }
            entry["volume_over_iso"] = entry["volume"]["per_ray"] / max(
                entry["iso"]["per_ray"], 1e-9
            )
            self.results.setdefault("passes", []).append(entry)
            self.save()
            self.log(
                f"passes N={n:,} {w}x{h}: iso {entry['iso']['per_ray']:.2f} per ray "
                f"({entry['iso']['per_ray_reaching']:.2f} per ray reaching a surface), "
                f"volume {entry['volume']['per_ray']:.2f}: {entry['volume_over_iso']:.2f}x"
            )
            del r

    # ---- per-kernel times of one frame
    def profile(self, cases: list[tuple[int, int, int, str, str]]) -> None:
        """The device activities of one frame (launched one by one, not as a graph) with
        their times (`wp.timing_begin`): where a frame's time goes, kernel by kernel."""
        if not wp.get_device(self.device).is_cuda:
            return
        for n, w, h, space, variant in cases:
            if self.clock.left() < 20:
                return
            mode = "volume" if variant == "volume" else "iso"
            r, frames = self.renderer(n)
            cam = fit_camera(frames[0], w, h)
            params = RenderParams(scale_space=space, mode=mode)  # type: ignore[arg-type]
            step = self.frame_step(r, frames, params, cam, w, h)
            for i in range(self.args.warmup):
                step(i)
            acts = profile_frame(r, frames[0], params, cam, w, h)
            self.results.setdefault("profile", []).append(
                {"n_atoms": n, "width": w, "height": h, "scale_space": space, "variant": variant,
                 "activities_ms": acts, "sum_ms": sum(acts.values())}
            )  # fmt: skip
            self.save()
            top = sorted(acts.items(), key=lambda kv: -kv[1])[:8]
            self.log(
                f"profile {variant} N={n:,} {w}x{h} {space}: "
                + ", ".join(f"{k.split(' ')[-1][:40]} {v:.3f}" for k, v in top)
            )
            del r

    # ---- grid build: dense grid vs wp.HashGrid
    def grid_build(self, n: int, r: Renderer, frames: list[np.ndarray]) -> None:
        """Dense grid rebuild vs wp.HashGrid.build on the same positions."""
        params = RenderParams()
        r.set_positions(frames[0])
        reach = params.cutoff_sigmas * params.sigma_A
        dev = self.device
        pts = wp.array(frames[0], dtype=wp.vec3, device=dev)
        hg = wp.HashGrid(128, 128, 128, device=dev)

        buf = r.host_positions()
        np.copyto(buf, frames[0])

        def dense(i: int) -> None:
            r.set_positions(buf, check_finite=False)  # a new frame: the grid is rebuilt
            r.prepare(params)

        def hashgrid(i: int) -> None:
            hg.build(pts, reach)

        out: dict[str, Any] = {"n_atoms": n}
        for name, fn in (("dense", dense), ("hashgrid", hashgrid)):
            ts = []
            for i in range(self.args.grid_reps + 2):
                wp.synchronize_device(dev)
                t0 = time.perf_counter()
                fn(i)
                wp.synchronize_device(dev)
                if i >= 2:
                    ts.append((time.perf_counter() - t0) * 1e3)
            out[f"{name}_ms"] = float(np.median(ts))
        out["note"] = (
            "dense = positions upload + cell sort + cell starts + sorted atoms + cell and brick"
            " bounds (host copy into the pinned buffer excluded); HashGrid = build only"
        )
        self.results["grid_build"].append(out)
        self.save()
        self.log(
            f"grid N={n:>9,} dense {out['dense_ms']:.3f} ms, HashGrid {out['hashgrid_ms']:.3f}"
        )

    # ---- baselines
    def baselines(self, sizes: list[int], w: int, h: int, voxels: list[float]) -> None:
        for n in sizes:
            if self.clock.left() < 30:
                self.results["notes"].append(f"baselines stopped before N={n}: time budget")
                break
            self._baselines_for(n, w, h, voxels)

    def _baselines_for(self, n: int, w: int, h: int, voxels: list[float]) -> None:
        dev = self.device
        r, frames = self.renderer(n)
        cam = fit_camera(frames[0], w, h)
        iso = RenderParams()
        uni = iso.model_copy(update={"color_by": "uniform"})
        fine = uni.model_copy(update={"step_sigmas": 0.05})
        nf = self.args.baseline_frames
        entry: dict[str, Any] = {"n_atoms": n, "width": w, "height": h}

        # reference: our renderer with a 5x finer step
        r.set_positions(frames[0])
        r.render(fine, cam, w, h)
        ref_rgb, ref_depth = r.read_rgba(), r.read_depth()

        def ours_image(params: RenderParams) -> tuple[np.ndarray, np.ndarray]:
            r.set_positions(frames[0])
            r.render(params, cam, w, h)
            return r.read_rgba(), r.read_depth()

        s = self.timed(self.frame_step(r, frames, iso, cam, w, h), nf)
        entry["ours"] = s
        s_uni = self.timed(self.frame_step(r, frames, uni, cam, w, h), nf)
        img, dep = ours_image(uni)
        s_uni["error_vs_fine"] = image_error(img, ref_rgb, dep, ref_depth)
        entry["ours_uniform"] = s_uni
        ours_img_color = ours_image(iso)
        self.log(f"baselines N={n:,}: ours {s['median_ms']:.2f} ms")

        # (a) naive: no empty-space skipping
        if self.clock.left() > 20:
            naive = Tuning(
                empty_space_skipping=False,
                max_registers=self.results["max_registers"],
                volume_max_registers=self.results["volume_max_registers"],
                march_budget=self.results["march_budget"],
                split_lanes=self.results["split_lanes"],
            )
            rn = Renderer(dev, max_atoms=n, tuning=naive)
            rn.set_topology(topology_of(self.system(n)[1], self.system(n)[2]))
            sn = self.timed(self.frame_step(rn, frames, iso, cam, w, h), nf)
            rn.set_positions(frames[0])
            rn.render(iso, cam, w, h)
            sn["diff_vs_ours"] = image_error(
                rn.read_rgba(), ours_img_color[0], rn.read_depth(), ours_img_color[1]
            )
            sn["speedup_of_ours"] = sn["median_ms"] / s["median_ms"]
            entry["naive"] = sn
            self.log(f"  naive {sn['median_ms']:.2f} ms ({sn['speedup_of_ours']:.1f}x)")
            del rn

        sh = self._shading(uni, cam, w, h)
        cam_d = camera_data(_frame(cam, w, h))
        threads = launch_size(w, h)
        rgba = wp.zeros(w * h, dtype=wp.uint32, device=dev)
        depth = wp.zeros(w * h, dtype=float, device=dev)
        pos = self.system(n)[0]
        reach = uni.cutoff_sigmas * uni.sigma_A
        lo = pos.min(axis=0) - reach - 1.0
        hi = pos.max(axis=0) + reach + 1.0
        dt = uni.step_sigmas * uni.sigma_A
        buf = r.host_positions()

        def read() -> tuple[np.ndarray, np.ndarray]:
            a = rgba.numpy().view(np.uint8).reshape(h, w, 4).copy()
            return a, depth.numpy().reshape(h, w).copy()

        # (a2) wp.HashGrid march
        if self.clock.left() > 20:
            pts = wp.zeros(n, dtype=wp.vec3, device=dev)
            hg = wp.HashGrid(128, 128, 128, device=dev)
            staging = wp.zeros(n, dtype=wp.vec3, device="cpu", pinned=wp.get_device(dev).is_cuda)
            sbuf = staging.numpy().view(np.float32).reshape(-1, 3)

            def hash_step(i: int) -> dict[str, float]:
                np.copyto(sbuf, frames[i % 3])
                t0 = time.perf_counter()
                wp.copy(pts, staging)
                hg.build(pts, reach)
                wp.launch(
                    hash_march_kernel,
                    threads,
                    (
                        hg.id,
                        pts,
                        reach,
                        0.5 / uni.sigma_A**2,
                        wp.vec3(*lo),
                        wp.vec3(*hi),
                        cam_d,
                        uni.iso_level,
                        dt,
                        sh,
                        rgba,
                        depth,
                    ),
                    device=dev,
                )
                wp.synchronize_device(dev)
                return {"wall": (time.perf_counter() - t0) * 1e3}

            sh_ = self.timed(hash_step, nf)
            np.copyto(sbuf, frames[0])
            hash_step(0)
            a, d = read()
            sh_["error_vs_fine"] = image_error(a, ref_rgb, d, ref_depth)
            sh_["speedup_of_ours"] = sh_["median_ms"] / s_uni["median_ms"]
            entry["hashgrid"] = sh_
            self.log(f"  hashgrid {sh_['median_ms']:.2f} ms ({sh_['speedup_of_ours']:.1f}x)")

        # (b) QuickSurf-style: splat onto a voxel grid, march it with trilinear filtering
        entry["resample"] = []
        for v in voxels:
            if self.clock.left() < 20:
                break
            dims = np.ceil((hi - lo) / v).astype(int) + 1
            count = int(np.prod(dims))
            rec: dict[str, Any] = {"voxel_A": v, "dims": dims.tolist(), "voxels": count}
            if count > self.args.max_voxels:
                rec["skipped"] = f"{count:,} voxels exceed the cap of {self.args.max_voxels:,}"
                entry["resample"].append(rec)
                continue
            vol = wp.zeros(tuple(int(x) for x in dims), dtype=float, device=dev)
            origin = wp.vec3(*lo)

            def grid_step(
                i: int, vol: Any = vol, origin: Any = origin, v: float = v
            ) -> dict[str, float]:
                np.copyto(buf, frames[i % 3])
                t0 = time.perf_counter()
                r.set_positions(buf, check_finite=False)
                f = r.prepare(uni)
                wp.launch(splat_kernel, vol.shape, (f, origin, v, vol), device=dev)
                wp.launch(
                    grid_march_kernel,
                    threads,
                    (vol, origin, v, cam_d, uni.iso_level, dt, sh, rgba, depth),
                    device=dev,
                )
                wp.synchronize_device(dev)
                return {"wall": (time.perf_counter() - t0) * 1e3}

            sr = self.timed(grid_step, nf)
            grid_step(0)
            a, d = read()
            rec.update(sr)
            rec["error_vs_fine"] = image_error(a, ref_rgb, d, ref_depth)
            rec["speedup_of_ours"] = sr["median_ms"] / s_uni["median_ms"]
            entry["resample"].append(rec)
            err = rec["error_vs_fine"]["mean_abs_rgb"]
            ours_err = s_uni["error_vs_fine"]["mean_abs_rgb"]
            self.log(
                f"  resample {v} A: {sr['median_ms']:.2f} ms, error {err:.4f} (ours {ours_err:.4f})"
            )
        self.results["baselines"].append(entry)
        self.save()

    def _shading(self, p: RenderParams, cam: Camera, w: int, h: int) -> Shading:
        light = p.lighting
        sh = Shading()
        sh.background = wp.vec3(*p.background)
        sh.uniform_color = wp.vec3(*p.uniform_color)
        sh.key_dir = wp.vec3(*key_light_direction(_frame(cam, w, h)))
        sh.ambient = light.ambient
        sh.diffuse = light.diffuse
        sh.specular = light.specular
        sh.shininess = light.shininess
        sh.head_weight = 0.6 if light.key_light else 1.0
        sh.key_weight = 0.55 if light.key_light else 0.0
        sh.ao = 0
        sh.ao_step = 1.0
        sh.iso = p.iso_level
        sh.depth_cue = 0.0
        return sh

    # ---- register cap of the marching kernels (occupancy), chosen before the main table
    def registers(self, sizes: list[int], w: int, h: int, caps: list[int]) -> None:
        """Each cap on both marching kernels; the rest of the run uses the fastest per mode."""
        score: dict[str, dict[int, float]] = {"iso": {}, "volume": {}}
        for n in sizes:
            for cap in caps:
                if self.clock.left() < 30:
                    break
                r, frames = self.renderer(n, max_registers=cap, volume_max_registers=cap)
                cam = fit_camera(frames[0], w, h)
                for mode in ("iso", "volume"):
                    params = RenderParams(mode=mode)  # type: ignore[arg-type]
                    step = self.frame_step(r, frames, params, cam, w, h)
                    s = self.timed(step, self.args.baseline_frames)
                    score[mode][cap] = score[mode].get(cap, 0.0) + s["median_ms"]
                    self.results["registers"].append(
                        {"n_atoms": n, "max_registers": cap, "mode": mode, "width": w, **s}
                    )
                    self.log(f"registers<={cap or 'auto'} N={n:,} {mode}: {s['median_ms']:.3f} ms")
        for mode, key in (("iso", "max_registers"), ("volume", "volume_max_registers")):
            if score[mode]:
                best = min(score[mode], key=lambda c: score[mode][c])
                self.results[key] = best
                self.log(f"{mode} register cap for the rest of the run: {best or 'compiler'}")
        self.save()

    # ---- pass budget of the first iso marching kernel (long rays queued for a second one)
    def budgets(
        self, cases: list[tuple[int, int, int]], budgets: list[tuple[int | None, int]]
    ) -> None:
        """Iso frames with each first-kernel pass budget (0: one kernel, no queue) and lanes
        per queued ray in the second, with the share of rays that went on to the second."""
        for n, w, h in cases:
            for budget, lanes in budgets:
                if self.clock.left() < 15:
                    return
                r, frames = self.renderer(n, march_budget=budget, split_lanes=lanes)
                cam = fit_camera(frames[0], w, h)
                params = RenderParams()
                s = self.timed(
                    self.frame_step(r, frames, params, cam, w, h), self.args.baseline_frames
                )
                used = r._budget_for(w * h)
                queued = int(r._queue_len.numpy()[0]) if used > 0 else 0
                self.results["budgets"].append(
                    {
                        "n_atoms": n,
                        "width": w,
                        "height": h,
                        "march_budget": budget,
                        "march_budget_used": used,
                        "split_lanes": lanes,
                        "queued_share": queued / (w * h),
                        **s,
                    }
                )
                self.save()
                self.log(
                    f"budget={budget}({used}) lanes={lanes} N={n:,} {w}x{h}: "
                    f"{s['median_ms']:.3f} ms, "
                    f"queued {100 * queued / (w * h):.1f}% {fmt_stages(s.get('stages_ms', {}))}"
                )
                del r

    # ---- threads per block of the marching kernels
    def blocks(self, cases: list[tuple[int, int, int]], sizes: list[int]) -> None:
        """Iso and volume frames with each block size of the marching kernels."""
        import server.render.renderer as renderer_module

        default = renderer_module.MARCH_BLOCK
        try:
            for n, w, h in cases:
                for block in sizes:
                    if self.clock.left() < 15:
                        return
                    renderer_module.MARCH_BLOCK = block
                    r, frames = self.renderer(n)
                    cam = fit_camera(frames[0], w, h)
                    for mode in ("iso", "volume"):
                        params = RenderParams(mode=mode)  # type: ignore[arg-type]
                        s = self.timed(
                            self.frame_step(r, frames, params, cam, w, h),
                            self.args.baseline_frames,
                        )
                        self.results["blocks"].append(
                            {"n_atoms": n, "width": w, "height": h, "mode": mode,
                             "block_dim": block, **s}
                        )  # fmt: skip
                        self.log(f"block={block} N={n:,} {w}x{h} {mode}: {s['median_ms']:.3f} ms")
                    self.save()
                    del r
        finally:
            renderer_module.MARCH_BLOCK = default

    # ---- graph replay vs launching kernels one by one
    def graphs(self, cases: list[tuple[int, int, int]]) -> None:
        """The same frames with the frame's launches replayed as one CUDA graph (the default)
        and launched one by one: what launch overhead costs at each size."""
        for n, w, h in cases:
            for replay in (True, False):
                if self.clock.left() < 15:
                    return
                r, frames = self.renderer(n, graphs=replay)
                cam = fit_camera(frames[0], w, h)
                params = RenderParams()
                s = self.timed(
                    self.frame_step(r, frames, params, cam, w, h), self.args.baseline_frames
                )
                self.results["graphs"].append(
                    {"n_atoms": n, "width": w, "height": h, "graphs": replay, **s}
                )
                self.save()
                self.log(
                    f"graphs={replay} N={n:,} {w}x{h}: {s['median_ms']:.3f} ms "
                    f"{fmt_stages(s.get('stages_ms', {}))}"
                )
                del r

    # ---- ablation: cell size
    def ablation(self, sizes: list[int], w: int, h: int, cells_list: list[float]) -> None:
        for n in sizes:
            for cells in cells_list:
                if self.clock.left() < 15:
                    return
                r, frames = self.renderer(n, cells_per_cutoff=cells)
                cam = fit_camera(frames[0], w, h)
                for mode in ("iso", "volume"):
                    params = RenderParams(mode=mode)  # type: ignore[arg-type]
                    s = self.timed(
                        self.frame_step(r, frames, params, cam, w, h), self.args.baseline_frames
                    )
                    mem = r.memory_bytes()
                    self.results["ablation"].append(
                        {
                            "n_atoms": n,
                            "cells_per_cutoff": cells,
                            "mode": mode,
                            "width": w,
                            "height": h,
                            **s,
                            "bytes_per_atom": (mem["per_atom"] + mem["grid"] + mem["other"]) / n,
                        }
                    )
                    self.save()
                    self.log(
                        f"ablation N={n:,} cells/cutoff={cells} {mode}: {s['median_ms']:.3f} ms "
                        f"{fmt_stages(s.get('stages_ms', {}))}"
                    )
                del r


def _frame(cam: Camera, w: int, h: int) -> Any:
    from server.render.camera import camera_frame

    return camera_frame(cam, w, h)


def tile_use(counts: np.ndarray) -> float:
    """The share of pass slots that do work in the tiles of one warp (`raycast.TILE_W` x
    `TILE_H` rays, which run in step): the passes taken over the tile's most, times its
    rays, over the tiles where any ray takes one. Edge tiles that the image cuts are left
    out."""
    tw, th = raycast.TILE_W, raycast.TILE_H
    h, w = counts.shape
    tiles = counts[: h - h % th, : w - w % tw].reshape(h // th, th, w // tw, tw)
    per_tile = tiles.transpose(0, 2, 1, 3).reshape(-1, tw * th)
    most = per_tile.max(axis=1)
    busy = most > 0
    if not busy.any():
        return 1.0
    return float(per_tile[busy].sum() / (most[busy].sum() * tw * th))


def cases_of(spec: str, default: list[tuple[int, int, int]]) -> list[tuple[int, int, int]]:
    """(atoms, width, height) of each "N@WxH" in a comma-separated `spec` (empty: `default`)."""
    if not spec:
        return default
    out = []
    for case in spec.split(","):
        n, _, size = case.partition("@")
        w, _, h = size.partition("x")
        atoms, width, height = int(n), int(w), int(h)  # ValueError when not numbers
        if atoms < 1 or width < 1 or height < 1:
            raise ValueError(case)
        out.append((atoms, width, height))
    return out


def fmt_stages(st: dict[str, float]) -> str:
    return " ".join(f"{k}={v:.2f}" for k, v in st.items())


# ----------------------------------------------------------------------------- report


def _describe(params: dict[str, Any]) -> str:
    levels = params.get("level_scale", "absolute")
    unit = "of the mean density at the atoms" if levels == "mean" else "atoms of density"
    return (
        f"sigma {params['sigma_A']} A, iso {params['iso_level']} ({unit}), step "
        f"{params['step_sigmas']} sigma, cutoff {params['cutoff_sigmas']} sigma, key light, "
        f"volume: '{params['tf_preset']}'"
    )


def table(path: Path) -> str:
    """Markdown tables of every section of a results file (printed after each run; the
    README's tables are benchmarks/tables/)."""
    res = json.loads(Path(path).read_text())
    lines = [
        f"GPU: **{res['gpu']}** (warp {res['warp']}, {res['date']}); parameters "
        f"{_describe(res['params'])}. Median of >= "
        f"{min((f['frames'] for f in res['frames']), default=0)} frames "
        "after warm-up; every frame uploads new positions and rebuilds the grid.",
        "",
        "| atoms | system | image | mode | median ms | fps | upload | grid | raycast | B/atom |",
        "| ---: | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for f in res["frames"]:
        st = f.get("stages_ms", {})
        lines.append(
            f"| {f['n_atoms']:,} | {f['system']} | {f['width']}x{f['height']} | {f['mode']} | "
            f"{f['median_ms']:.3f} | {f['fps']:.0f} | {st.get('upload', 0):.3f} | "
            f"{st.get('grid', 0):.3f} | {st.get('raycast', 0):.3f} | {f['bytes_per_atom']:.1f} |"
        )
    if res.get("densities"):
        lines += [
            "",
            "The geodesic and carved densities (strength 1) next to the classical one, iso, "
            "median ms per frame (grid and tables' distances rebuilt every frame):",
            "",
            "| atoms | image | classical ms | geodesic ms | geodesic fps / classical | carved ms | "
            "carved fps / classical | B/atom classical | geodesic | carved |",
            "| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for row in res["densities"]:
            lines.append(
                f"| {row['n_atoms']:,} | {row['width']}x{row['height']} | "
                f"{row['classical']['median_ms']:.3f} | {row['geodesic']['median_ms']:.3f} | "
                f"{row['geodesic_over_classical_fps']:.2f} | {row['carved']['median_ms']:.3f} | "
                f"{row['carved_over_classical_fps']:.2f} | "
                f"{row['classical_bytes_per_atom']:.1f} | {row['geodesic_bytes_per_atom']:.1f} | "
                f"{row['carved_bytes_per_atom']:.1f} |"
            )
    if res.get("passes"):
        lines += [
            "",
            "Density passes (four samples each) per ray of one frame, iso and volume, and the "
            "share of a warp's pass slots that do work:",
            "",
            "| atoms | image | iso per ray | iso per ray reaching a surface | iso tile use | "
            "volume per ray | volume tile use | volume / iso |",
            "| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for row in res["passes"]:
            iso, vol = row["iso"], row["volume"]
            lines.append(
                f"| {row['n_atoms']:,} | {row['width']}x{row['height']} | {iso['per_ray']:.2f} | "
                f"{iso['per_ray_reaching']:.2f} | {iso.get('tile_use', 0):.2f} | "
                f"{vol['per_ray']:.2f} | {vol.get('tile_use', 0):.2f} | "
                f"{row['volume_over_iso']:.2f} |"
            )
    if res["grid_build"]:
        lines += [
            "",
            "Grid rebuild (median ms): dense cell grid (upload from the pinned buffer, sort, cell "
            "starts, sorted atoms, cell and brick density bounds) vs `wp.HashGrid.build` alone.",
            "",
            "| atoms | dense grid | wp.HashGrid |",
            "| ---: | ---: | ---: |",
        ]
        for g in res["grid_build"]:
            lines.append(f"| {g['n_atoms']:,} | {g['dense_ms']:.3f} | {g['hashgrid_ms']:.3f} |")
    if res["baselines"]:
        lines += [
            "",
            "Baselines, iso mode (median ms per frame; error = mean |RGB difference| against "
            "our renderer at a 5x finer step, uniform colour):",
            "",
            "| atoms | image | method | median ms | ours is faster by | image error |",
            "| ---: | --- | --- | ---: | ---: | ---: |",
        ]
        for b in res["baselines"]:
            img = f"{b['width']}x{b['height']}"
            o = b["ours_uniform"]
            lines.append(
                f"| {b['n_atoms']:,} | {img} | ours | {o['median_ms']:.2f} | 1.0x | "
                f"{o['error_vs_fine']['mean_abs_rgb']:.4f} |"
            )
            if "naive" in b:
                nv = b["naive"]
                same = nv["diff_vs_ours"]["mean_abs_rgb"]
                lines.append(
                    f"| {b['n_atoms']:,} | {img} | naive march (no skipping) | "
                    f"{nv['median_ms']:.2f} | {nv['speedup_of_ours']:.1f}x | "
                    f"same image (diff {same:.4f}) |"
                )
            if "hashgrid" in b:
                hg = b["hashgrid"]
                lines.append(
                    f"| {b['n_atoms']:,} | {img} | wp.HashGrid march | {hg['median_ms']:.2f} | "
                    f"{hg['speedup_of_ours']:.1f}x | {hg['error_vs_fine']['mean_abs_rgb']:.4f} |"
                )
            for rs in b.get("resample", []):
                if "skipped" in rs:
                    lines.append(
                        f"| {b['n_atoms']:,} | {img} | resample {rs['voxel_A']} A | skipped | | "
                        f"{rs['skipped']} |"
                    )
                    continue
                lines.append(
                    f"| {b['n_atoms']:,} | {img} | resample {rs['voxel_A']} A | "
                    f"{rs['median_ms']:.2f} | {rs['speedup_of_ours']:.1f}x | "
                    f"{rs['error_vs_fine']['mean_abs_rgb']:.4f} |"
                )
    if res.get("graphs"):
        lines += [
            "",
            "Graph replay (the default on CUDA) vs launching the frame's kernels one by one "
            "(iso, median ms per frame):",
            "",
            "| atoms | image | graph replay | one by one | ratio |",
            "| ---: | --- | ---: | ---: | ---: |",
        ]
        by = {(g["n_atoms"], g["width"], g["height"], g["graphs"]): g for g in res["graphs"]}
        for (n, w, h, replay), g in by.items():
            other = by.get((n, w, h, False))
            if replay and other:
                lines.append(
                    f"| {n:,} | {w}x{h} | {g['median_ms']:.3f} | {other['median_ms']:.3f} | "
                    f"{other['median_ms'] / g['median_ms']:.2f}x |"
                )
    if res.get("registers"):
        lines += [
            "",
            "Register cap of the marching kernels (more resident warps vs spills); the run "
            f"used {res['max_registers'] or 'the compiler default'} for iso and "
            f"{res.get('volume_max_registers') or 'the compiler default'} for volume:",
            "",
            "| atoms | mode | register cap | median ms |",
            "| ---: | --- | ---: | ---: |",
        ]
        for g in res["registers"]:
            cap = g["max_registers"] or "compiler"
            lines.append(f"| {g['n_atoms']:,} | {g['mode']} | {cap} | {g['median_ms']:.3f} |")
    if res["ablation"]:
        lines += [
            "",
            "Cell size (median ms; cell = cutoff / cells-per-cutoff):",
            "",
            "| atoms | image | mode | cells per cutoff | median ms | grid | raycast | B/atom |",
            "| ---: | --- | --- | ---: | ---: | ---: | ---: | ---: |",
        ]
        for a in res["ablation"]:
            st = a.get("stages_ms", {})
            lines.append(
                f"| {a['n_atoms']:,} | {a['width']}x{a['height']} | {a['mode']} | "
                f"{a['cells_per_cutoff']:g} | {a['median_ms']:.3f} | {st.get('grid', 0):.3f} | "
                f"{st.get('raycast', 0):.3f} | {a['bytes_per_atom']:.1f} |"
            )
    if res.get("budgets"):
        lines += [
            "",
            "Split rays (iso, median ms per frame): passes in the first marching kernel before a "
            "ray is queued (0: one kernel), threads per queued ray in the second, and the share "
            "of rays queued; `auto` is the default policy.",
            "",
            "| atoms | image | budget | lanes | median ms | queued |",
            "| ---: | --- | --- | ---: | ---: | ---: |",
        ]
        for e in res["budgets"]:
            b = e["march_budget"]
            name = f"auto ({e['march_budget_used']})" if b is None else str(b)
            lanes = e["split_lanes"] if e["march_budget_used"] else "-"
            lines.append(
                f"| {e['n_atoms']:,} | {e['width']}x{e['height']} | {name} | {lanes} | "
                f"{e['median_ms']:.3f} | {100 * e['queued_share']:.1f} % |"
            )
    if res.get("blocks"):
        lines += [
            "",
            "Threads per block of the marching kernels (median ms per frame):",
            "",
            "| atoms | image | mode | block | median ms |",
            "| ---: | --- | --- | ---: | ---: |",
        ]
        for e in res["blocks"]:
            lines.append(
                f"| {e['n_atoms']:,} | {e['width']}x{e['height']} | {e['mode']} | "
                f"{e['block_dim']} | {e['median_ms']:.3f} |"
            )
    for note in res.get("notes", []):
        lines.append(f"\nNote: {note}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--device", default="auto")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test, e.g. on cpu)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "render_quick.json"))
    p.add_argument("--frames", type=int, default=60)
    # 12: past the ten frames of a CUDA renderer's part-bound trial (server/render/parttrial.py)
    p.add_argument("--warmup", type=int, default=12)
    p.add_argument("--baseline-frames", type=int, default=20)
    p.add_argument("--grid-reps", type=int, default=20)
    p.add_argument("--budget-s", type=float, default=480.0, help="wall-clock budget of the run")
    p.add_argument("--max-config-s", type=float, default=20.0, help="at most this long per config")
    p.add_argument("--max-voxels", type=int, default=1 << 28)
    p.add_argument("--sections", default="registers,main,grid,graphs,baselines,ablation")
    p.add_argument("--sizes", default="", help="comma-separated atom counts (main table)")
    p.add_argument(
        "--images", default="", help="folder for sample images (of the widest image size)"
    )
    p.add_argument("--image-n", type=int, default=1_000_000)
    p.add_argument("--ablation-sizes", default="", help="atom counts of the cell-size ablation")
    p.add_argument("--ablation-image", default="", help="image size of the ablation, WxH")
    p.add_argument("--ablation-cells", default="1,2,3", help="cells per cutoff it tries")
    p.add_argument("--table", default="", help="print the markdown tables of a results file")
    p.add_argument(
        "--max-registers",
        type=int,
        default=None,
        help="iso; 0 = compiler's choice; default: each density's own (MARCH_REGISTERS)",
    )
    p.add_argument(
        "--volume-max-registers",
        type=int,
        default=VOLUME_REGISTERS,
        help="volume kernel (0 = compiler's choice)",
    )
    p.add_argument("--register-caps", default="0,128,80,64", help="caps the first section tries")
    p.add_argument("--register-sizes", default="100000,1000000", help="atom counts it tries")
    p.add_argument(
        "--march-budget", type=int, default=None, help="iso first-kernel passes (default: auto)"
    )
    p.add_argument("--block-sizes", default="64,128,256", help="block sizes it tries")
    p.add_argument("--budget-cases", default="", help="N@WxH,... the budget section runs")
    p.add_argument("--density-cases", default="", help="N@WxH,... the densities section runs")
    p.add_argument("--profile-cases", default="", help="N@WxH@space@variant,... to profile")
    p.add_argument("--scale-sizes", default="", help="atom counts of the scale section")
    p.add_argument(
        "--variant-cases", default="", help="N@WxH,... the variants and passes sections run"
    )
    p.add_argument(
        "--variant-params", default="{}", help="render parameters (JSON) of variants and scale"
    )
    p.add_argument("--variants", default="", help='JSON list of Renderer options with "label"')
    p.add_argument(
        "--visible-rays",
        default="",
        help="STRIDE:DEPTH of the cell-marking rays (visibility.py; STRIDE at 1920x1080)",
    )
    p.add_argument(
        "--variant-turn",
        type=float,
        default=0.0,
        help="degrees the camera turns a frame over still positions (0: new positions a frame)",
    )
    p.add_argument(
        "--variant-views",
        type=int,
        default=1,
        help="cameras around the system that see each frame (times are their sums)",
    )
    p.add_argument("--scale-cells", default="2,1", help="cells per cutoff it tries")
    p.add_argument(
        "--scale-options", default="", help='JSON list of Renderer options with "label" (scale)'
    )
    p.add_argument("--split-lanes", type=int, default=SPLIT_LANES, help="lanes per queued ray")
    p.add_argument(
        "--budgets", default="0,4,8,12,16", help="budget[:lanes] pairs the budget section tries"
    )
    args = p.parse_args(argv)
    if args.visible_rays:
        # the marking rays of "visible" part bounds, for sweeps (module constants)
        try:
            stride, depth = (int(v) for v in args.visible_rays.split(":"))
        except ValueError:
            stride = depth = 0
        if stride < 1 or depth < 1:
            p.error(
                f"--visible-rays takes STRIDE:DEPTH, two integers >= 1, got {args.visible_rays!r}"
            )
        visibility.STRIDE, visibility.DEPTH = stride, depth
    given: dict[str, list[tuple[int, int, int]]] = {}
    for flag, spec in (
        ("--variant-cases", args.variant_cases),
        ("--density-cases", args.density_cases),
    ):
        try:
            given[flag] = cases_of(spec, [])
        except ValueError:
            p.error(f"{flag} takes N@WxH,... (atoms @ width x height, each >= 1), got {spec!r}")
    variant_cases = given["--variant-cases"] or [(496, 64, 48)]
    if args.variant_views < 1:
        p.error(f"--variant-views must be >= 1, got {args.variant_views}")
    if args.table:
        print(table(Path(args.table)), end="")
        return 0
    if args.quick:
        args.frames, args.warmup, args.baseline_frames, args.grid_reps = 3, 1, 2, 2
    if args.images:
        Path(args.images).mkdir(parents=True, exist_ok=True)
    b = Bench(args)
    sections = set(args.sections.split(","))
    if args.quick:
        sizes, res = [496, 3000], [(64, 48)]
        base_sizes, base_res, voxels = [496], (64, 48), [1.5, 0.75]
        abl_sizes, abl_res = [496], (64, 48)
    else:
        sizes, res = FULL_SIZES, FULL_RES
        base_sizes, base_res, voxels = (
            [10_000, 100_000, 1_000_000],
            (1920, 1080),
            [1.5, 0.75, 0.375],
        )
        abl_sizes, abl_res = [100_000, 1_000_000], (1920, 1080)
    if args.sizes:
        sizes = [int(s) for s in args.sizes.split(",")]
    b.log(f"device {b.device} ({b.gpu}), budget {args.budget_s:.0f} s")
    if "registers" in sections:
        if args.quick:
            b.registers([496], 64, 48, [0, 128])
        else:
            b.registers(
                [int(v) for v in args.register_sizes.split(",")],
                1920,
                1080,
                [int(c) for c in args.register_caps.split(",")],
            )
    if "main" in sections:
        b.main_table(sizes, res, grid="grid" in sections)
    if "densities" in sections:
        density_cases = [(496, 64, 48)] if args.quick else [
            (n, 500, 500) for n in THESIS
        ] + [(100_000, 1920, 1080), (1_000_000, 1920, 1080)]  # fmt: skip
        b.densities(given["--density-cases"] or density_cases)
    variant_params = RenderParams.model_validate(json.loads(args.variant_params))
    if "variants" in sections:
        tries = json.loads(args.variants) if args.variants else [{"label": "default"}]
        b.variants(variant_cases, variant_params, tries)
    if "farfield" in sections:
        b.farfield(variant_cases, variant_params, [0.5, 0.75])
    if "passes" in sections:
        b.passes(variant_cases, variant_params)
    if "scale" in sections:
        scale_sizes = [3000] if args.quick else [1_000_000, 10_000_000, 100_000_000]
        if args.scale_sizes:
            scale_sizes = [int(v) for v in args.scale_sizes.split(",")]
        w, h = (64, 48) if args.quick else (1920, 1080)
        scale_tries = json.loads(args.scale_options) if args.scale_options else None
        cells = [float(v) for v in args.scale_cells.split(",")]
        b.scale(scale_sizes, cells, w, h, scale_tries, variant_params)
    if "profile" in sections:
        prof = [(496, 64, 48, "classical", "iso")] if args.quick else [
            (1_000_000, 1920, 1080, "classical", "iso"),
            (1_000_000, 1920, 1080, "classical", "volume"),
            (1_000_000, 1920, 1080, "geodesic", "iso"),
            (10_000_000, 1920, 1080, "classical", "iso"),
        ]  # fmt: skip
        if args.profile_cases:
            prof = [
                (int(n), *(int(v) for v in size.split("x")), space, variant)  # type: ignore[misc]
                for n, size, space, variant in (c.split("@") for c in args.profile_cases.split(","))
            ]
        b.profile(prof)
    if "budgets" in sections:
        tries = [
            (
                None if v.split(":")[0] == "auto" else int(v.split(":")[0]),
                int(v.split(":")[1]) if ":" in v else args.split_lanes,
            )
            for v in args.budgets.split(",")
        ]
        cases = [(496, 64, 48)] if args.quick else [
            (5_684, 500, 500), (10_000, 500, 500), (100_000, 1920, 1080), (1_000_000, 1920, 1080)
        ]  # fmt: skip
        if args.budget_cases:
            cases = [
                (int(n), *(int(v) for v in size.split("x")))  # type: ignore[misc]
                for n, size in (c.split("@") for c in args.budget_cases.split(","))
            ]
        b.budgets(cases, tries)
    if "blocks" in sections:
        block_sizes = [int(v) for v in args.block_sizes.split(",")]
        cases = [(496, 64, 48)] if args.quick else [
            (5_684, 500, 500), (100_000, 1920, 1080), (1_000_000, 1920, 1080)
        ]  # fmt: skip
        b.blocks(cases, block_sizes)
    if "graphs" in sections:
        if args.quick:
            b.graphs([(496, 64, 48)])
        else:
            b.graphs([(496, 500, 500), (5_684, 500, 500), (100_000, 1920, 1080)])
    if "baselines" in sections:
        b.baselines(base_sizes, *base_res, voxels)
    if "ablation" in sections:
        if args.ablation_sizes:
            abl_sizes = [int(v) for v in args.ablation_sizes.split(",")]
        if args.ablation_image:
            abl_res = tuple(int(v) for v in args.ablation_image.split("x"))  # type: ignore[assignment]
        b.ablation(abl_sizes, *abl_res, [float(v) for v in args.ablation_cells.split(",")])
    b.save()
    print(table(Path(args.out)), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
