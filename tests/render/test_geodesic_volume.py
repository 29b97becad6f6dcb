"""The geodesic density read from its grid (`geodesic_volume`) against the same density with
its routes walked at every sample (the control): where the surface lies, what a pixel picks,
and what happens when the molecule outgrows the grid."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from protocol import RenderParams
from server.render import geodesic_field, geodesic_volume
from server.render.camera import camera_frame, fit_camera, image_rays, orbit
from server.render.device import compiled
from server.render.errors import RenderError
from server.render.renderer import Renderer
from server.render.tuning import Tuning
from tests.render.helpers import render
from tests.render.molecules import Mol, three_atoms, topology, villin

W, H = 48, 36


def _displacement(r: Renderer, direct: Renderer, cam: object, level: float) -> np.ndarray:
    """How far each hit of `r` lies from the surface of the routes per sample: |S - level| /
    |grad S| of `direct`'s density at the hit point (first order, along the normal)."""
    depth = r.read_depth()
    origins, dirs = image_rays(camera_frame(cam, W, H))  # type: ignore[arg-type]
    hit = np.isfinite(depth)
    pts = origins[hit] + depth[hit][:, None] * dirs[hit]
    val, vg, _col, _ids = direct.evaluate(pts)
    return np.abs(val.astype(np.float64) - level) / np.linalg.norm(vg[:, :3], axis=1)


@pytest.mark.parametrize(
    "sigma, smoothing, radii",
    [
        (0.6, 0.6, "uniform"),
        (1.5, 0.6, "uniform"),
        (3.0, 0.6, "uniform"),
        (1.5, 0.2, "uniform"),
        (1.5, 0.6, "vdw"),
    ],
)
def test_the_grid_keeps_the_surface_within_the_accuracy_bound(
    device: str, sigma: float, smoothing: float, radii: str
) -> None:
    """Hits drawn from the grid lie within max(0.05 A, 1 % sigma) of the routes' surface, past
    what the routes' own hits do (their march's refinement, the control)."""
    mol = villin()
    params = RenderParams(
        scale_space="geodesic", sigma_A=sigma, geodesic_smoothing=smoothing, radius_mode=radii
    )
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    grid = render(device, mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
    direct = render(device, mol.topology, mol.positions, params, cam, W, H, geodesic_volume=False)
    assert grid.last_density == "geodesic_volume" and direct.last_density == "geodesic"
    d_grid = _displacement(grid, direct, cam, params.iso_level)
    d_direct = _displacement(direct, direct, cam, params.iso_level)
    assert len(d_grid) > 200
    tol = max(0.05, 0.01 * sigma)
    assert d_grid.max() <= d_direct.max() + tol, (d_grid.max(), d_direct.max())
    hits, hits0 = np.isfinite(grid.read_depth()), np.isfinite(direct.read_depth())
    assert (hits != hits0).sum() <= 0.01 * hits0.sum()


def _three(r: Renderer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return r.read_rgba().copy(), r.read_depth().copy(), r.read_atom_ids().copy()


def test_a_molecule_that_outgrows_its_grid_is_drawn_by_its_routes_until_the_grid_grows() -> None:
    """The grid is sized from the frame before. A frame whose atoms spread past it is drawn
    with the routes walked per sample (the same image as the control's, bit for bit), and the
    next frame's grid makes room and reads it again."""
    mol = villin()
    params = RenderParams(scale_space="geodesic")
    cam = orbit(fit_camera(mol.positions * 1.6, W, H), 30.0, 20.0)
    spread = mol.positions.mean(axis=0) + (mol.positions - mol.positions.mean(axis=0)) * 1.6
    r = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
    small = r.memory_bytes()["geodesic"]
    r.set_positions(spread)
    r.render(params, cam, W, H)
    assert r.last_density == "geodesic_volume"
    outgrown = _three(r)
    # the control has the same history: route tables built at the first frame
    direct = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=False)
    direct.set_positions(spread)
    direct.render(params, cam, W, H)
    control = _three(direct)
    assert np.isfinite(control[1]).sum() > 200
    for a, b in zip(outgrown, control, strict=True):
        np.testing.assert_array_equal(a, b)
    r.render(params, cam, W, H)
    assert r.memory_bytes()["geodesic"] > small
    regrown = _three(r)
    assert not np.array_equal(regrown[0], control[0])  # read from the grid again
    hits = np.isfinite(regrown[1]) & np.isfinite(control[1])
    assert hits.sum() > 0.99 * np.isfinite(control[1]).sum()


def test_the_bricks_allocated_a_point_cover_every_grid_the_setup_can_lay() -> None:
    """`setup_kernel` lays grids at least 5 points wide on every axis; their bricks of 4 x 4 x 2
    never outnumber BRICKS_PER_POINT a point (else the grid would not be valid, and its frames
    would fall back to the routes), and the ratio only falls as the grid grows."""
    d = np.arange(5, 72)
    nx, ny, nz = np.meshgrid(d, d, d, indexing="ij")
    bricks = (
        -(-nx // geodesic_volume.BRICK_X)
        * -(-ny // geodesic_volume.BRICK_Y)
        * -(-nz // geodesic_volume.BRICK_Z)
    )
    ratio = bricks / (nx * ny * nz)
    assert ratio.max() <= geodesic_volume.BRICKS_PER_POINT
    assert ratio.max() == ratio[0, 0, 0]  # 5 x 5 x 5: 12 bricks for 125 points


def _walked(r: Renderer) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points the last grid walked: positions, values, colours (RGBA bytes) and largest
    contributors (original atom indices); checks that the listed bricks are exactly those
    that hold a walked point."""
    vol = r._gvol
    assert vol is not None
    v = vol.vol.numpy()[0]
    nx, ny, nz = (int(x) for x in v["dims"])
    idx = np.nonzero(vol.flags.numpy()[: nx * ny * nz])[0]
    xyz = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1)
    bx, by = -(-nx // geodesic_volume.BRICK_X), -(-ny // geodesic_volume.BRICK_Y)
    brick = xyz // [geodesic_volume.BRICK_X, geodesic_volume.BRICK_Y, geodesic_volume.BRICK_Z]
    bricks = np.unique((brick[:, 2] * by + brick[:, 1]) * bx + brick[:, 0])
    listed = vol.listed.numpy()[: int(vol.count.numpy()[0])]
    np.testing.assert_array_equal(listed, bricks)
    pts = np.asarray(v["origin"], np.float32) + xyz.astype(np.float32) * np.float32(v["h"])
    tint = vol.tint.numpy()[idx]
    rgba = np.stack([(tint >> s) & 255 for s in (0, 8, 16, 24)], axis=1)
    order = r._grid.order.numpy()
    sorted_ids = vol.atoms.numpy()[idx]
    ids = np.where(sorted_ids >= 0, order[np.maximum(sorted_ids, 0)], -1)
    return pts, vol.coef.numpy()[idx], rgba, ids


def test_each_walked_point_keeps_the_routes_colour_and_largest_contributor() -> None:
    """The fill keeps, at every walked point, the routes' contribution-weighted colour (to
    the byte) and their largest contributor: what a shaded point reads instead of walking the
    routes."""
    mol = villin()
    params = RenderParams(scale_space="geodesic")
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    r = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
    direct = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=False)
    pts, _coef, rgba, ids = _walked(r)
    assert len(pts) > 1000
    _val, _vg, col, ids0 = direct.evaluate(pts)
    held = col[:, 3] > 0.0
    assert held.mean() > 0.5
    assert (rgba[held, 3] == 255).all() and (rgba[~held, 3] == 0).all()
    expect = np.clip(np.floor(col[held, :3].astype(np.float64) * 255.0 + 0.5), 0, 255)
    assert np.abs(rgba[held, :3] - expect).max() <= 1
    np.testing.assert_array_equal(ids[held], ids0[held])
    assert (ids[~held] == -1).all()


@pytest.mark.parametrize("sigma, radii", [(1.5, "uniform"), (0.8, "vdw")])
def test_a_brick_walked_together_fills_the_grid_of_each_point_alone(
    device: str, sigma: float, radii: str
) -> None:
    """A brick's 32 points walk the atoms within reach of the whole brick (on CUDA one warp
    reads the same routes together); the atoms beyond a point's own reach add exact zeros, so
    the grid and the image are those of each point walking its own, bit for bit."""
    mol = villin()
    params = RenderParams(scale_space="geodesic", sigma_A=sigma, radius_mode=radii)
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    runs = []
    for together in (True, False):
        r = render(
            device, mol.topology, mol.positions, params, cam, W, H,
            geodesic_volume=True, geodesic_bricks=together,
        )  # fmt: skip
        assert r._gvol is not None and r._gvol.together is together
        assert r.last_density == "geodesic_volume"
        runs.append((*_walked(r), *_three(r)))
    assert len(runs[0][0]) > 1000
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_cpu_fill_split_across_host_threads_is_the_fill_of_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The CPU device runs a launch on the thread that makes it, and the fill is most of a
    geodesic frame there: once its kernel is loaded (by one thread), the fill runs as runs of
    the listed bricks on several host threads. A brick's points are its own, so the grid and
    the image are those of one thread, bit for bit."""
    mol = villin()
    params = RenderParams(scale_space="geodesic")
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    moved = mol.positions + np.float32(0.3)
    split: list[int] = []
    fill_on_threads = geodesic_volume.GeodesicVolume._fill_on_threads

    def counted(self: geodesic_volume.GeodesicVolume, *args: object) -> None:
        split.append(self.threads)
        fill_on_threads(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(geodesic_volume.GeodesicVolume, "_fill_on_threads", counted)
    runs = []
    for threads in (1, 3):
        options = {"geodesic_volume": True, "cpu_threads": threads}
        r = Renderer("cpu", tuning=Tuning.of(options))
        r.set_topology(mol.topology)
        for positions in (mol.positions, moved):
            r.set_positions(positions)
            r.render(params, cam, W, H)
        assert r.last_density == "geodesic_volume"
        runs.append((*_walked(r), *_three(r)))
    assert split == [3, 3]  # both frames of three threads, and no frame of one
    assert len(runs[0][0]) > 1000
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(RenderError, match="cpu_threads"):
        Tuning.of({"cpu_threads": 0})


def _brick_points(r: Renderer) -> list[np.ndarray]:
    """The walked grid points of each listed brick, in listed order."""
    vol = r._gvol
    assert vol is not None
    v = vol.vol.numpy()[0]
    nx, ny, nz = (int(x) for x in v["dims"])
    bx, by = -(-nx // geodesic_volume.BRICK_X), -(-ny // geodesic_volume.BRICK_Y)
    flags = vol.flags.numpy()
    out = []
    for b in vol.listed.numpy()[: int(vol.count.numpy()[0])]:
        x0 = (b % bx) * geodesic_volume.BRICK_X
        y0 = ((b // bx) % by) * geodesic_volume.BRICK_Y
        z0 = (b // (bx * by)) * geodesic_volume.BRICK_Z
        xs, ys, zs = np.meshgrid(
            np.arange(x0, x0 + geodesic_volume.BRICK_X),
            np.arange(y0, y0 + geodesic_volume.BRICK_Y),
            np.arange(z0, z0 + geodesic_volume.BRICK_Z),
            indexing="ij",
        )
        inside = (xs < nx) & (ys < ny) & (zs < nz)
        idx = ((zs * ny + ys) * nx + xs)[inside]
        out.append(idx[flags[idx] != 0])
    return out


def _kept(r: Renderer, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vol = r._gvol
    assert vol is not None
    return vol.coef.numpy()[idx], vol.tint.numpy()[idx], vol.atoms.numpy()[idx]


@wp.kernel
def _no_prefilter(
    coef: wp.array(dtype=float),  # type: ignore[valid-type]
    vol: wp.array(dtype=geodesic_volume.VolumeInfo),  # type: ignore[valid-type]
    axis: int,
) -> None:
    pass


def test_bricks_taken_by_several_groups_add_their_shares_and_the_rest_one_group_each(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Several groups a brick (a small molecule's few bricks fill the device) each walk a share
    of every row's atoms and their sums are added in lane order: the values of one group to
    rounding, the same colours and contributors. Bricks past the plan's room for those shares
    are walked one group each: exactly what one group a brick gives them. (The grids hold the
    values themselves here: the prefilter, which mixes neighbouring points, is left out.)"""
    monkeypatch.setattr(geodesic_volume, "prefilter_kernel", _no_prefilter)
    mol = villin()
    params = RenderParams(scale_space="geodesic")
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    args = (mol.topology, mol.positions, params, cam, W, H)
    one = render("cpu", *args, geodesic_volume=True, geodesic_fill_lanes=1)
    four = render("cpu", *args, geodesic_volume=True, geodesic_fill_lanes=4)
    assert four._gvol is not None and four._gvol.lanes == 4
    bricks = _brick_points(one)
    assert len(bricks) > 200 and four._gvol.planned >= len(bricks)
    walked = np.concatenate(bricks)
    c1, t1, a1 = _kept(one, walked)
    c4, t4, a4 = _kept(four, walked)
    np.testing.assert_allclose(c4, c1, rtol=1e-5, atol=1e-7)
    assert not np.array_equal(c4, c1)  # the shares really were added apart
    assert np.abs(t4.view(np.uint8).astype(int) - t1.view(np.uint8).astype(int)).max() <= 1
    assert (a4 == a1).mean() > 0.999
    monkeypatch.setattr(geodesic_volume, "LISTED_BRICKS", 0.0)
    short = render("cpu", *args, geodesic_volume=True, geodesic_fill_lanes=4)
    vol = short._gvol
    assert vol is not None and vol.lanes == 4 and vol.planned == 64 < len(bricks)
    planned, rest = np.concatenate(bricks[:64]), np.concatenate(bricks[64:])
    for got, want in zip(_kept(short, planned), _kept(four, planned), strict=True):
        np.testing.assert_array_equal(got, want)
    for got, want in zip(_kept(short, rest), _kept(one, rest), strict=True):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_the_gate_reads_the_cell_bounds_first_and_lists_the_same_points(
    monkeypatch: pytest.MonkeyPatch, mode: str
) -> None:
    """The grid's gate skips the points whose atom-grid cell bound is below the cut (their own
    bound is too): the same points are walked, so the same grid and image bit for bit as a
    gate that evaluates every point, over two frames whose atoms move."""
    mol = villin()
    params = RenderParams(scale_space="geodesic", mode=mode)
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    moved = mol.positions + np.random.default_rng(3).normal(0.0, 0.3, mol.positions.shape)
    runs = []
    for cells in (1, 0):
        monkeypatch.setattr(geodesic_volume, "CELL_GATE", cells)
        r = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
        first = (*_walked(r), *_three(r))
        r.set_positions(moved)
        r.render(params, cam, W, H)
        assert r.last_density == "geodesic_volume"
        runs.append((*first, *_walked(r), *_three(r)))
    assert len(runs[0][0]) > 1000
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_pixel_picks_what_the_routes_pick(device: str) -> None:
    """Colour and the picked atom come from the grid's points around the hit the grid's rays
    found (trilinear colour; the largest of their largest contributors' terms there): the
    same atom as the routes per sample at nearly every pixel (the hits differ by the grid's
    error), and a colour within a few levels."""
    mol = villin()
    params = RenderParams(scale_space="geodesic", sigma_A=3.0)
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    grid = render(device, mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
    direct = render(device, mol.topology, mol.positions, params, cam, W, H, geodesic_volume=False)
    ids, ids0 = grid.read_atom_ids(), direct.read_atom_ids()
    hit = (ids >= 0) & (ids0 >= 0)
    assert hit.sum() > 300
    assert float((ids[hit] == ids0[hit]).mean()) > 0.98
    diff = np.abs(grid.read_rgba()[hit].astype(int) - direct.read_rgba()[hit].astype(int))
    assert np.quantile(diff, 0.99) <= 8


def test_volume_mode_reads_the_grid_too() -> None:
    """Volume mode integrates the spline along the rays: the image of the routes per sample
    within a few levels (the grid's error, and the values below a fifth of the transfer
    function's clear level that the grid holds at 0)."""
    mol = villin()
    params = RenderParams(scale_space="geodesic", mode="volume")
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    grid = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
    direct = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=False)
    assert grid.last_density == "geodesic_volume"
    a, b = grid.read_rgba().astype(int), direct.read_rgba().astype(int)
    diff = np.abs(a - b)
    lit = (b[..., :3].sum(axis=-1) > 3 * 40).sum()
    assert lit > 200
    assert diff.mean() < 0.5 and np.quantile(diff, 0.999) <= 6 and diff.max() <= 16


@pytest.mark.parametrize("sigma", [0.6, 3.0])
def test_the_first_frame_of_a_tiny_molecule_reads_its_grid(sigma: float) -> None:
    """Before any grid, the plan sizes the first from the positions and the whole cell the
    atom grid may round its box up by: one atom, and three, are read from the grid at once."""
    cam = fit_camera(np.array([[-4.0, -4.0, -4.0], [4.0, 4.0, 4.0]], np.float32), W, H)
    for mol in (Mol(topology(["C"], []), np.zeros((1, 3), np.float32)), three_atoms()):
        params = RenderParams(scale_space="geodesic", sigma_A=sigma)
        r = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
        assert r.last_density == "geodesic_volume" and r._gvol is not None
        assert int(r._gvol.vol.numpy()[0]["valid"]) == 1  # not the routes' fallback


def test_a_smoothing_past_the_grids_range_walks_the_routes() -> None:
    """Past MAX_SMOOTHING the level falls to the Gaussians' tails, where the spline rings: the
    routes are walked per sample, even when the grid is asked for."""
    mol = villin()
    cam = orbit(fit_camera(mol.positions, W, H), 30.0, 20.0)
    drawn = []
    for smoothing in (1.0, 2.0):
        params = RenderParams(scale_space="geodesic", geodesic_smoothing=smoothing)
        r = render("cpu", mol.topology, mol.positions, params, cam, W, H, geodesic_volume=True)
        drawn.append(r.last_density)
    assert drawn == ["geodesic_volume", "geodesic"]


def test_the_rays_read_the_grid_up_to_the_devices_points_a_pixel() -> None:
    """Unforced, the grid is read while it has at most `points_per_pixel` points a pixel: on the
    CPU device villin's grid (some 140,000 points) for 320x240 (1.8 a pixel), its routes for
    96x72 (20), where the CPU's grid takes 2.5 times the routes' time. A CUDA device's rule
    reaches further (its fill takes a brick a warp)."""
    mol = villin()
    params = RenderParams(scale_space="geodesic")
    drawn = []
    for w, h in ((320, 240), (96, 72)):
        cam = orbit(fit_camera(mol.positions, w, h), 30.0, 20.0)
        drawn.append(render("cpu", mol.topology, mol.positions, params, cam, w, h).last_density)
    assert drawn == ["geodesic_volume", "geodesic"]
    cpu, cuda = geodesic_volume.points_per_pixel(False), geodesic_volume.points_per_pixel(True)
    assert 1.8 < cpu < 20 < cuda


def test_the_grids_kernels_follow_fast_math_and_compile_once_per_choice() -> None:
    """The fill and the gate take CUDA's approximate transcendentals with the rest of the
    renderer (`Tuning.fast_math`), the fill its register cap (`geodesic_fill_registers`); a
    second renderer with the same choices reuses the compiled kernels."""
    fast = Renderer("cpu", tuning=Tuning())._geodesic_volume()
    precise = Renderer(
        "cpu", tuning=Tuning(fast_math=False, geodesic_fill_registers=0)
    )._geodesic_volume()
    for vol, want in ((fast, True), (precise, False)):
        assert vol.fill.module.options["fast_math"] is want
        assert vol.gate.module.options["fast_math"] is want
    assert fast.fill.options["cuda_max_registers"] == geodesic_volume.FILL_REGISTERS > 0
    assert precise.fill.options.get("cuda_max_registers") is None
    uncapped = Renderer("cpu", tuning=Tuning(geodesic_fill_registers=0))._geodesic_volume()
    assert uncapped.fill is not fast.fill and uncapped.gate is fast.gate
    mean = compiled(geodesic_field.sampled_values, True)
    assert mean.module.options["fast_math"] is True
    assert compiled(geodesic_field.sampled_values, False).module.options["fast_math"] is False
    again = Renderer("cpu", tuning=Tuning())._geodesic_volume()
    assert again.fill is fast.fill and again.gate is fast.gate
    assert fast.fill is not precise.fill
    for bad in (-1, 256, True):
        with pytest.raises(RenderError, match="geodesic_fill_registers"):
            Tuning(geodesic_fill_registers=bad)
