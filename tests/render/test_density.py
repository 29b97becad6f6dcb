"""Density, gradient, colour blend and top atom on the device vs the brute-force oracle, and
the cell grid's neighbour completeness."""

from __future__ import annotations

import dataclasses
import math
from typing import no_type_check

import numpy as np
import pytest
import warp as wp

from protocol import RenderParams
from server.render import colors, density, visibility
from server.render import grid as grid_module
from server.render import renderer as renderer_module
from server.render.camera import fit_camera, orbit, quat_to_matrix
from server.render.cells import PART_BITS, WALKED, cell_box
from server.render.density import GaussianField, UnsortedAtoms
from server.render.errors import RenderError
from server.render.grid import SORTED_IN_CELL, CellGrid, order_cells_kernel
from server.render.raycast import PART_MARGIN, kernels_for
from server.render.reach import reach_sigmas
from server.render.renderer import Renderer
from server.render.tuning import Tuning
from tests.render import oracle
from tests.render.conftest import blob, make_topology
from tests.render.helpers import oracle_molecule, render


def _points_near(pos: np.ndarray, m: int, seed: int, spread: float = 3.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = pos[rng.integers(0, len(pos), m)]
    return (base + rng.normal(size=(m, 3)) * spread).astype(np.float32)


@pytest.mark.parametrize(
    ("radius_mode", "sigma", "offset", "cells"),
    [
        ("uniform", 1.5, (0.0, 0.0, 0.0), 2.0),
        ("uniform", 0.8, (-350.0, 1200.0, -75.0), 1.0),
        ("vdw", 1.2, (-20.0, -30.0, -40.0), 2.0),
    ],
)
def test_density_and_gradient_match_oracle(
    device: str, radius_mode: str, sigma: float, offset: tuple[float, float, float], cells: float
) -> None:
    n = 60
    top = make_topology(n, radii=None)
    pos = blob(n, seed=3, offset=offset)
    params = RenderParams(sigma_A=sigma, radius_mode=radius_mode)  # type: ignore[arg-type]
    r = render(device, top, pos, params, fit_camera(pos, 8, 6), 8, 6, cells_per_cutoff=cells)
    pts = _points_near(pos, 400, seed=5)
    vals, vgs, cols, ids = r.evaluate(pts)
    mol = oracle_molecule(top, pos, params)
    # the oracle in float64 at the float32 points the device saw
    ref, ref_grad = oracle.density(mol, pts.astype(np.float64))
    scale = max(float(ref.max()), 1e-12)
    np.testing.assert_allclose(vals, ref, rtol=1e-5, atol=1e-5 * scale)
    np.testing.assert_allclose(vgs[:, 3], ref, rtol=1e-5, atol=1e-5 * scale)
    np.testing.assert_allclose(cols[:, 3], ref, rtol=1e-5, atol=1e-5 * scale)
    gscale = float(np.abs(ref_grad).max())
    np.testing.assert_allclose(vgs[:, :3], ref_grad, rtol=1e-4, atol=2e-5 * gscale)
    hit = ref > 1e-3 * scale
    assert hit.sum() > 100
    np.testing.assert_allclose(cols[hit, :3], oracle.blended_color(mol, pts)[hit], atol=2e-5)
    best, margin = oracle.top_atom(mol, pts)
    clear = hit & (margin > 1e-4)
    assert clear.sum() > 100
    np.testing.assert_array_equal(ids[clear], best[clear])
    assert np.all(ids[ref == 0] == -1)


@pytest.mark.parametrize(("k", "c_k", "missing"), [(3.0, 1.023, 0.0432), (4.0, 1.086, 0.00248)])
def test_truncation_bound_is_documented(device: str, k: float, c_k: float, missing: float) -> None:
    """The tapered kernel of an isolated atom differs from its Gaussian by at most
    c_k w exp(-k^2 / 2), and by that much just inside the cutoff; it reaches zero without a step
    at the cutoff; and it misses the share of the Gaussian's mass density.py states (the tail
    beyond the cutoff plus what the taper takes inside it)."""
    top = make_topology(1)
    pos = np.zeros((1, 3), np.float32)
    params = RenderParams(sigma_A=1.0, cutoff_sigmas=k)
    r = render(device, top, pos, params, fit_camera(pos, 4, 4), 4, 4)
    d = np.concatenate([np.linspace(0.0, k + 1.0, 4001), np.linspace(0.97 * k, k, 2001)])
    d = np.sort(d).astype(np.float32).astype(np.float64)
    pts = np.stack([d, np.zeros_like(d), np.zeros_like(d)], axis=1)
    vals = r.evaluate(pts)[0].astype(np.float64)
    exact = np.exp(-(d**2) / 2)
    worst = np.abs(vals - exact).max() / np.exp(-k * k / 2)
    assert c_k - 1e-3 <= worst <= c_k + 1e-3
    assert vals[d >= k + 1e-6].max() == 0.0
    # no step where the atom leaves reach: the last samples inside fall to zero
    inside = vals[(d > k - 0.2) & (d < k)]
    assert np.all(np.diff(inside) <= 0) and inside[-1] < 1e-3 * np.exp(-k * k / 2)
    # the share of the Gaussian's mass, (2 pi)^(3/2), that the kernel leaves out
    mass = np.trapezoid(4 * np.pi * d**2 * vals, d)
    assert abs(1.0 - mass / (2 * np.pi) ** 1.5 - missing) < 0.01 * missing


def _probe_field(grid: CellGrid, device: str, n: int, radius: float) -> GaussianField:
    """A field whose 'density' counts atoms within `radius` (weights = 1 + index), built
    from the grid alone: exp(-1e-12 d^2) == 1 in float32, cutoff d < radius."""
    f = GaussianField()
    f.atoms = wp.zeros(n, dtype=wp.vec4, device=device)
    f.inv2s2 = wp.zeros(1, dtype=float, device=device)
    f.order = grid.order
    f.colors = wp.zeros(n, dtype=wp.uint32, device=device)
    f.cell_start = grid.cell_start
    f.bound = grid.cell_values
    f.brick_bound = grid.brick_values
    f.info = grid.info
    f.inv2s2_uniform = 1e-12
    f.half_k2 = 1e-12 * radius * radius
    f.per_atom = 0
    return f


@wp.kernel
@no_type_check
def _weights_in_order(
    pos: wp.array[wp.vec3],
    order: wp.array[wp.int32],
    out: wp.array[wp.vec4],
):
    i = wp.tid()
    j = order[i]
    p = pos[j]
    out[i] = wp.vec4(p[0], p[1], p[2], float(j + 1))


@pytest.mark.parametrize(
    ("offset", "spread", "cells_per_reach"),
    [
        ((0.0, 0.0, 0.0), 6.0, 1.0),
        ((-2500.0, -40.0, 910.0), 6.0, 2.0),
        ((30.0, -60.0, 5.0), 300.0, 2.0),  # wide box: the cell cap forces larger cells
    ],
)
def test_grid_finds_every_atom_within_cutoff(
    device: str, offset: tuple[float, float, float], spread: float, cells_per_reach: float
) -> None:
    n = 300
    radius = 2.5
    rng = np.random.default_rng(11)
    centers = rng.normal(size=(12, 3)) * spread + np.asarray(offset)
    pos = (centers[rng.integers(0, 12, n)] + rng.normal(size=(n, 3)) * 2.0).astype(np.float32)
    grid = CellGrid(device, n)
    wp_pos = wp.array(pos, dtype=wp.vec3, device=device)
    grid.build(wp_pos, n, radius, cells_per_reach)
    info = grid.read_info()
    assert int(info["valid"]) == 1
    assert int(info["ncells"]) <= grid.capacity
    f = _probe_field(grid, device, n, radius)
    wp.launch(_weights_in_order, n, (wp_pos, grid.order, f.atoms), device=device)
    probes = np.concatenate([pos[:100] + rng.normal(size=(100, 3)) * 1.5, pos[100:150]])
    probes = probes.astype(np.float32)
    k = kernels_for()
    m = len(probes)
    vals = wp.zeros(m, dtype=float, device=device)
    out = [wp.zeros(m, dtype=t, device=device) for t in (wp.vec4, wp.vec4, wp.int32)]
    wp.launch(
        k.evaluate,
        m,
        (f, wp.array(probes, dtype=wp.vec3, device=device), vals, *out),
        device=device,
    )
    got = vals.numpy().astype(np.float64)
    d = np.linalg.norm(probes[:, None, :].astype(np.float64) - pos[None, :, :], axis=-1)
    within = d < radius
    # float32 rounding may move an atom sitting exactly on the cutoff sphere either way
    edge = np.abs(d - radius) < 1e-3 + 2e-7 * float(np.abs(pos).max())
    lo = ((within & ~edge) * (np.arange(n) + 1)).sum(axis=1)
    hi = ((within | edge) * (np.arange(n) + 1)).sum(axis=1)
    assert within.sum() > 500
    assert np.all(got >= lo - 0.5) and np.all(got <= hi + 0.5), np.nonzero(
        (got < lo - 0.5) | (got > hi + 0.5)
    )


@pytest.mark.parametrize(("cells_per_reach", "most"), [(2.0, 41), (0.25, 3313)])
def test_counting_sort_orders_atoms_as_the_radix_sort(
    device: str, cells_per_reach: float, most: int
) -> None:
    """Atom for atom the stable sort's order (each cell's atoms by index), on CUDA too, where
    the ranks come in whatever order the device ran the atoms. Cells of a dense lump at two
    cells per reach hold up to 41 atoms; cells four times the reach could hold far more than
    SORTED_IN_CELL (3,313 here), so such a grid is sorted by the radix sort."""
    n = 5000
    pos = np.concatenate([blob(4000, seed=3), blob(1000, seed=5, spread=1.0)]).astype(np.float32)
    orders = {}
    for sort in ("radix", "counting"):
        grid = CellGrid(device, n, sort)
        grid.build(wp.array(pos, dtype=wp.vec3, device=device), n, 3.0, cells_per_reach)
        cells = int(grid.read_info()["ncells"])
        orders[sort] = (grid.order.numpy()[:n], grid.cell_start.numpy()[: cells + 1])
    (counted, starts), (radix, radix_starts) = orders["counting"], orders["radix"]
    np.testing.assert_array_equal(starts, radix_starts)
    assert np.diff(starts).max() == most
    np.testing.assert_array_equal(counted, radix)


@pytest.mark.parametrize("sort", ["counting", "radix"])
def test_a_frame_with_a_non_finite_position_keeps_every_index_in_bounds(
    device: str, sort: str
) -> None:
    """A NaN position invalidates the grid (the frame draws background); its one cell then
    holds every atom, so the sort writes only where it may, frame after frame."""
    n = 20_000
    pos = blob(n, seed=4)
    pos[123, 2] = np.nan
    grid = CellGrid(device, n, sort)
    for _ in range(3):
        grid.build(wp.array(pos, dtype=wp.vec3, device=device), n, 3.0, 2.0)
    info = grid.read_info()
    assert int(info["valid"]) == 0 and int(info["ncells"]) == 1
    np.testing.assert_array_equal(grid.cell_start.numpy()[:2], [0, n])
    np.testing.assert_array_equal(np.sort(grid.order.numpy()[:n]), np.arange(n))


def test_cells_are_put_in_index_order_up_to_their_limit(device: str) -> None:
    """The counting sort's last step on scrambled cells: each cell of up to SORTED_IN_CELL
    atoms comes out in index order, a larger one as it was."""
    rng = np.random.default_rng(8)
    sizes = [0, 1, 2, 7, 40, SORTED_IN_CELL, SORTED_IN_CELL + 1, 3]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)
    n = int(starts[-1])
    placed = rng.permutation(n).astype(np.int32)
    keys = np.empty(n, np.int32)
    keys[placed] = np.repeat(np.arange(len(sizes)), sizes)  # atom -> its cell
    order = wp.zeros(n, dtype=wp.int32, device=device)
    args = [wp.array(a, dtype=wp.int32, device=device) for a in (keys, starts, placed)]
    wp.launch(order_cells_kernel, n, (*args, len(sizes), order), device=device)
    got = order.numpy()
    for c, size in enumerate(sizes):
        a, b = starts[c], starts[c + 1]
        want = placed[a:b] if size > SORTED_IN_CELL else np.sort(placed[a:b])
        np.testing.assert_array_equal(got[a:b], want)


def test_an_unknown_grid_sort_is_refused() -> None:
    with pytest.raises(RenderError, match="grid_sort must be one of counting, radix, got 'bucket'"):
        Renderer("cpu", tuning=Tuning(grid_sort="bucket"))


def test_grid_is_sorted_by_cell(device: str) -> None:
    n = 200
    pos = blob(n, seed=9, offset=(-40.0, 10.0, -5.0))
    grid = CellGrid(device, n)
    grid.build(wp.array(pos, dtype=wp.vec3, device=device), n, 3.0, 2.0)
    info = grid.read_info()
    dims = np.asarray(info["dims"])
    origin = np.asarray(info["origin"], dtype=np.float64)
    h = float(info["h"])
    order = grid.order.numpy()[:n]
    start = grid.cell_start.numpy()[: int(info["ncells"]) + 1]
    assert sorted(order.tolist()) == list(range(n))
    cell = np.floor((pos[order] - origin) / h).astype(int)
    key = (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
    assert np.all(np.diff(key) >= 0)
    assert start[0] == 0 and start[-1] == n
    for c in np.unique(key):
        assert np.all(key[start[c] : start[c + 1]] == c)


def test_brick_bounds_are_cell_maxima(device: str) -> None:
    n = 400
    rng = np.random.default_rng(4)
    pos = (rng.uniform(-60, 60, size=(n, 3))).astype(np.float32)
    grid = CellGrid(device, n)
    grid.build(wp.array(pos, dtype=wp.vec3, device=device), n, 2.0, 2.0)
    info = grid.read_info()
    assert int(info["bricks"]) == 1
    dims = np.asarray(info["dims"])
    cells = int(np.prod(dims))
    values = rng.uniform(0, 1, size=grid.capacity + 1).astype(np.float32)
    grid.cell_values.assign(values)
    grid.build_bricks()
    vol = values[:cells].reshape(dims[2], dims[1], dims[0])
    b = np.asarray(info["bdims"])
    pad = np.full((b[2] * 4, b[1] * 4, b[0] * 4), -1.0, np.float32)
    pad[: dims[2], : dims[1], : dims[0]] = vol
    want = pad.reshape(b[2], 4, b[1], 4, b[0], 4).max(axis=(1, 3, 5)).reshape(-1)
    got = grid.brick_values.numpy()[: len(want)]
    np.testing.assert_array_equal(got, want)


def test_vdw_mode_widens_big_atoms(device: str) -> None:
    top = make_topology(2, elements=["H", "S"])
    pos = np.array([[-10.0, 0.0, 0.0], [10.0, 0.0, 0.0]], np.float32)
    params = RenderParams(sigma_A=1.0, radius_mode="vdw")
    r = render(device, top, pos, params, fit_camera(pos, 4, 4), 4, 4)
    pts = np.array([[-8.5, 0.0, 0.0], [11.5, 0.0, 0.0]], np.float32)
    vals = r.evaluate(pts)[0]
    s_h = 1.0 * colors.VDW_RADII["H"] / colors.R_REF
    s_s = 1.0 * colors.VDW_RADII["S"] / colors.R_REF
    np.testing.assert_allclose(vals, np.exp(-(1.5**2) / (2 * np.array([s_h, s_s]) ** 2)), rtol=1e-5)


@wp.func
@no_type_check
def _row_one_at_a_time(f: UnsortedAtoms, p: wp.vec3, j0: int, j1: int, total: float) -> float:
    """The mean density's row sum one atom at a time (the form before two atoms a step)."""
    s = total
    for j in range(j0, j1):
        i = f.order[j]
        q = f.positions[i]
        a = wp.vec4(q[0], q[1], q[2], f.weights[i])
        c = f.inv2s2_uniform
        if f.per_atom != 0:
            c = density.inv2s2_of(f.sigma_per_radius, f.radii[i])
        e = density.dist2(a, p) * c
        if e < f.half_k2:
            s += a[3] * density.kernel(e, f.inv_half_k2)
    return s


_walk_one_at_a_time = density.cell_rows(
    "one_at_a_time", _row_one_at_a_time, wp.vec3, float, field=UnsortedAtoms
)


@wp.kernel
@no_type_check
def _one_at_a_time_kernel(f: UnsortedAtoms, stride: int, values: wp.array[float]):
    k = wp.tid()
    p = f.positions[k * stride]
    values[k] = _walk_one_at_a_time(f, p, p, p, wp.float32(0.0))


@pytest.mark.parametrize("radius_mode", ["uniform", "vdw"])
def test_the_mean_density_two_atoms_a_step_keeps_the_bits(device: str, radius_mode: str) -> None:
    """The mean density at the sampled atoms reads two atoms a step; each sample is the sum
    one atom at a time would give, bit for bit (rows of odd and even lengths; one thread a
    sample, as on the CPU: several lanes add their shares in another order)."""
    top, pos = _two_lumps()
    params = RenderParams(radius_mode=radius_mode)  # type: ignore[arg-type]
    r = render(device, top, pos, params, fit_camera(pos, 8, 6), 8, 6, mean_lanes=1)
    assert r._last is not None
    n = len(pos)
    samples = min(n, 4096)
    out = wp.zeros(samples, dtype=float, device=r.device)
    args = (r._unsorted(r._last[1]), n // samples, out)
    wp.launch(_one_at_a_time_kernel, samples, args, device=r.device)
    got = r._density_samples.numpy()[:samples].copy()
    assert (got > 0.0).all()
    np.testing.assert_array_equal(got, out.numpy())


@pytest.mark.parametrize("radius_mode", ["uniform", "vdw"])
def test_the_scale_of_relative_levels_is_the_mean_density_at_the_sampled_atoms(
    device: str, radius_mode: str
) -> None:
    """Relative levels divide by the mean density at every (n // 4096)-th atom, each summed
    through the grid over the unsorted atoms by the renderer's lanes (several on CUDA, each
    a share of every row): every sample's shares add up to the reference density."""
    top, pos = _two_lumps()
    params = RenderParams(radius_mode=radius_mode)  # type: ignore[arg-type]
    r = render(device, top, pos, params, fit_camera(pos, 16, 12), 16, 12)
    absolute = params.model_copy(update={"level_scale": "absolute"})
    mol = oracle_molecule(top, pos, absolute)
    n = len(pos)
    samples = min(n, 4096)
    ref = oracle.density(mol, pos[np.arange(samples) * (n // samples)].astype(np.float64))[0]
    lanes = r._mean_lanes
    assert lanes == (1 if device == "cpu" else density.LANES_PER_SAMPLE)
    shares = r._density_samples.numpy()[: samples * lanes].reshape(samples, lanes)
    np.testing.assert_allclose(shares.astype(np.float64).sum(axis=1), ref, rtol=1e-5)
    assert r.density_scale() == pytest.approx(float(ref.mean()), rel=1e-5)


@wp.kernel
@no_type_check
def _batched_kernel(
    f: GaussianField,
    o: wp.array[wp.vec3],
    d: wp.array[wp.vec3],
    ts: wp.array[wp.vec4],
    single: wp.array2d[float],
    single_grad: wp.array2d[wp.vec4],
    four: wp.array[wp.vec4],
    grads: wp.array2d[wp.vec4],
):
    i = wp.tid()
    t = ts[i]
    for q in range(4):
        p = o[i] + d[i] * t[q]
        single[i, q] = density.gaussian_value(f, p)
        single_grad[i, q] = density.gaussian_value_grad(f, p)
    four[i] = density.gaussian_value4(f, o[i], d[i], t)
    g0, g1, g2, g3 = density.gaussian_value_grad4(f, o[i], d[i], t)
    grads[i, 0] = g0
    grads[i, 1] = g1
    grads[i, 2] = g2
    grads[i, 3] = g3


@pytest.mark.parametrize(
    ("radius_mode", "offset", "spacing"),
    [
        ("uniform", (0.0, 0.0, 0.0), 0.4),
        ("uniform", (-350.0, 1200.0, -75.0), 1.3),
        ("vdw", (-20.0, -30.0, -40.0), 0.6),
    ],
)
def test_batched_samples_equal_single_samples(
    device: str, radius_mode: str, offset: tuple[float, float, float], spacing: float
) -> None:
    """`value4` / `value_grad4` (four points along a line in one pass over the neighbours)
    give what `value` / `value_grad` give point by point, also for segments longer than a cell
    and lines in every direction."""
    n = 80
    top = make_topology(n, radii=None)
    pos = blob(n, seed=13, offset=offset)
    params = RenderParams(sigma_A=1.3, radius_mode=radius_mode)  # type: ignore[arg-type]
    r = render(device, top, pos, params, fit_camera(pos, 8, 6), 8, 6)
    f = r.prepare(params)
    rng = np.random.default_rng(17)
    m = 300
    origins = _points_near(pos, m, seed=19, spread=4.0)
    dirs = rng.normal(size=(m, 3))
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    t0 = rng.uniform(-2.0, 2.0, size=(m, 1))
    ts = (t0 + spacing * np.arange(4)[None, :]).astype(np.float32)
    arr = [wp.array(a, dtype=wp.vec3, device=device) for a in (origins, dirs)]
    wts = wp.array(ts, dtype=wp.vec4, device=device)
    single = wp.zeros((m, 4), dtype=float, device=device)
    single_grad = wp.zeros((m, 4), dtype=wp.vec4, device=device)
    four = wp.zeros(m, dtype=wp.vec4, device=device)
    grads = wp.zeros((m, 4), dtype=wp.vec4, device=device)
    wp.launch(_batched_kernel, m, (f, *arr, wts, single, single_grad, four, grads), device=device)
    ref = single.numpy()
    assert (ref > 1e-3).sum() > 300
    scale = float(ref.max())
    np.testing.assert_allclose(four.numpy(), ref, rtol=2e-6, atol=1e-6 * scale)
    g = single_grad.numpy()
    gscale = float(np.abs(g).max())
    np.testing.assert_allclose(grads.numpy(), g, rtol=2e-6, atol=1e-6 * gscale)


def test_a_model_without_batched_forms_draws_the_same_image(device: str) -> None:
    """The caster's per-point fallbacks for `value4` / `value_grad4` (what a new density
    model gets when it provides only the four required functions)."""
    plain = dataclasses.replace(
        density.GAUSSIAN, name="gaussian-per-point", value4=None, value_grad4=None
    )
    n = 40
    top = make_topology(n)
    pos = blob(n, seed=6)
    cam = fit_camera(pos, 40, 30)
    for mode in ("iso", "volume"):
        params = RenderParams(mode=mode, sigma_A=1.2)  # type: ignore[arg-type]
        a = render(device, top, pos, params, cam, 40, 30)
        b = render(device, top, pos, params, cam, 40, 30, density=plain)
        diff = np.abs(a.read_rgba().astype(int) - b.read_rgba().astype(int))
        assert diff.max() <= 1, mode
        hit = np.isfinite(a.read_depth())
        assert hit.mean() > (0.05 if mode == "iso" else 0.02), mode
        np.testing.assert_array_equal(hit, np.isfinite(b.read_depth()))
        np.testing.assert_allclose(a.read_depth()[hit], b.read_depth()[hit], atol=1e-4)


def _grid_layout(r: Renderer) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """The grid's cells per axis, cell edge, origin and per-cell bounds after a render."""
    info = r.grid_info()
    dims = np.asarray(info["dims"])
    cells = int(np.prod(dims))
    origin = np.asarray(info["origin"], dtype=np.float64)
    return dims, float(info["h"]), origin, r._grid.cell_values.numpy()[:cells]


@pytest.mark.parametrize("scale_space", ["classical", "warped"])
def test_cell_bounds_hold_the_density(device: str, scale_space: str) -> None:
    """Every cell's bound is at least the density anywhere in the cell (checked at points
    spread through each cell), or above the level it is compared with (the walk stops there),
    and a cell that holds an atom is unbounded without a walk."""
    mol = make_topology(60), blob(60, 7)
    top, pos = mol
    params = RenderParams(scale_space=scale_space)  # type: ignore[arg-type]
    r = render(device, top, pos, params, fit_camera(pos, 32, 24), 32, 24)
    dims, h, origin, bound = _grid_layout(r)
    cells = len(bound)
    starts = r._grid.cell_start.numpy()[: cells + 1]
    occupied = starts[1:] > starts[:-1]
    assert occupied.any() and np.isinf(bound[occupied]).all()
    rng = np.random.default_rng(3)
    idx = np.arange(cells)
    cell_xyz = np.stack(
        [idx % dims[0], (idx // dims[0]) % dims[1], idx // (dims[0] * dims[1])], axis=1
    )
    points = (origin + (cell_xyz[:, None, :] + rng.uniform(0, 1, (cells, 6, 3))) * h).reshape(-1, 3)
    values = r.evaluate(points)[0].reshape(cells, 6).max(axis=1)
    assert (values > 0).sum() > 50, "the points must reach into the density"
    assert ((bound >= values * (1 - 1e-5)) | (bound > params.iso_level)).all()
    assert (bound < params.iso_level).sum() > 10, "some cells must be skippable"


def test_unwalked_cells_only_loosen_bounds_and_keep_the_image(device: str) -> None:
    """Leaving the empty cells with the largest coarse bounds unwalked gives them the coarse
    bound: never below their walked one, and the same image (a ray samples where it could
    have skipped, and finds the level where it did). Two lumps a few cells apart give open
    cells of every kind."""
    top = make_topology(1200)
    pos = np.concatenate([blob(600, 7), blob(600, 9, offset=(9.0, 0.0, 0.0))]).astype(np.float32)
    cam = fit_camera(pos, 64, 48)
    for space in ("classical", "warped"):
        params = RenderParams(scale_space=space)  # type: ignore[arg-type]
        runs = {}
        for keep in (math.inf, 3.0):
            r = render(device, top, pos, params, cam, 64, 48, bound_keep_from=keep)
            cells = int(np.prod(r.grid_info()["dims"]))
            walked = int(r._grid.work_count.numpy()[0])
            runs[keep] = (
                r._grid.cell_values.numpy()[:cells],
                r.read_rgba(),
                r.read_depth(),
                walked,
            )
        every, fewer = runs[math.inf], runs[3.0]
        assert every[3] > fewer[3] > 50, space
        assert (fewer[0] >= every[0]).all() and (fewer[0] > every[0]).sum() > 50, space
        np.testing.assert_array_equal(fewer[1], every[1])
        np.testing.assert_array_equal(fewer[2], every[2])


def _two_lumps() -> tuple[object, np.ndarray]:
    pos = np.concatenate([blob(600, 7), blob(600, 9, offset=(9.0, 0.0, 0.0))]).astype(np.float32)
    return make_topology(1200), pos


def test_parts_below_the_level_hold_no_density_above_it(device: str) -> None:
    """The parts of a walked cell (27, x fastest) marked below the level are: at points
    spread through every marked part of a cell that is itself above the level, the density
    is below it."""
    top, pos = _two_lumps()
    params = RenderParams()
    r = render(device, top, pos, params, fit_camera(pos, 32, 24), 32, 24)
    dims, h, origin, bound = _grid_layout(r)
    cells = len(bound)
    parts = r._grid.parts.numpy()[:cells]
    cell, part = np.nonzero((parts[:, None] >> np.arange(27)) & 1)
    keep = bound[cell] >= params.iso_level
    cell, part = cell[keep], part[keep]
    assert len(cell) > 200, "open cells must have parts below the level"
    xyz = np.stack([cell % dims[0], (cell // dims[0]) % dims[1], cell // (dims[0] * dims[1])], 1)
    sub = np.stack([part % 3, (part // 3) % 3, part // 9], axis=1)
    rng = np.random.default_rng(5)
    at = (xyz[:, None, :] + (sub[:, None, :] + rng.uniform(0, 1, (len(cell), 4, 3))) / 3.0) * h
    values = r.evaluate((origin + at).reshape(-1, 3))[0]
    assert values.max() < params.iso_level
    assert values.max() > 0.3 * params.iso_level, "the parts must reach near the surface"


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_part_bounds_skip_samples_and_keep_the_image(device: str, mode: str) -> None:
    """Samples in parts below the level are skipped (iso: they cannot hold a crossing;
    volume: they are transparent): the image is the one of whole-cell skipping, bit for bit,
    with every open cell walked for its parts or only those the view marks, with the
    classical density and with the warped one (which has no part bounds). A small molecule
    gets part bounds in every open cell by default."""
    top, pos = _two_lumps()
    cam = fit_camera(pos, 64, 48)
    for space in ("classical", "warped"):
        params = RenderParams(mode=mode, scale_space=space)  # type: ignore[arg-type]
        runs = {}
        for split in ("all", "visible", "none", None):
            r = render(device, top, pos, params, cam, 64, 48, part_bounds=split)
            cells = int(np.prod(r.grid_info()["dims"]))
            marked = int(((r._grid.parts.numpy()[:cells] & PART_BITS) != 0).sum())
            runs[split] = (marked, r.read_rgba(), r.read_depth(), r.read_atom_ids())
        assert runs["none"][0] == 0
        assert runs["all"][0] > (50 if space == "classical" else -1), space
        assert runs[None][0] == runs["all"][0], space
        if space == "classical":
            # the view reaches only the cells in front of the surface
            assert 0 < runs["visible"][0] < runs["all"][0], runs["visible"][0]
        for split in ("all", "visible"):
            for a, b in zip(runs[split][1:], runs["none"][1:], strict=True):
                np.testing.assert_array_equal(a, b)


@wp.kernel
@no_type_check
def _lane_shares_kernel(
    f: GaussianField,
    cells: wp.array[wp.int32],
    lanes: int,
    shares: wp.array[density.PartBounds],
    whole: wp.array[density.PartBounds],
):
    t = wp.tid()
    i = t // lanes
    lo, hi = cell_box(f.info[0], cells[i])
    shares[t] = density.gaussian_part_bounds_lane(f, lo, hi, t - i * lanes, lanes)
    if t - i * lanes == 0:
        whole[i] = density.gaussian_part_bounds(f, lo, hi, wp.inf)


def test_the_lanes_shares_of_a_cells_part_bounds_add_up_to_them(device: str) -> None:
    """Each lane of a cell's part walk counts every lanes-th atom of each row: the shares of
    1, 3 and 8 lanes add up to the bounds one walk gives, and to those the frame's own walk
    wrote for the cells it listed (the largest, raised by PART_MARGIN; where every part
    passed the level, the walk stopped there, short of the whole sum)."""
    top, pos = _two_lumps()
    params = RenderParams()
    r = render(device, top, pos, params, fit_camera(pos, 32, 24), 32, 24, part_bounds="all")
    f = r._gaussian_field(r._last[1])
    stop = r._stop_level(params, r._last[1])
    n = int(r._grid.work_count.numpy()[0])
    assert n > 100, "the grid must list cells to walk"
    cells = wp.array(r._grid.work.numpy()[:n], dtype=wp.int32, device=device)
    written = r._grid.cell_values.numpy()[cells.numpy()]
    for lanes in (1, 3, 8):
        shares = wp.zeros(n * lanes, dtype=density.PartBounds, device=device)
        whole = wp.zeros(n, dtype=density.PartBounds, device=device)
        args = (f, cells, lanes, shares, whole)
        wp.launch(_lane_shares_kernel, n * lanes, args, device=device)
        total = shares.numpy().astype(np.float64).reshape(n, lanes, 27).sum(axis=1)
        np.testing.assert_allclose(total, whole.numpy(), rtol=1e-5, atol=1e-30)
        raised = total.max(axis=1) * PART_MARGIN
        whole_sum = total.min(axis=1) * PART_MARGIN <= stop
        assert whole_sum.sum() > 100
        np.testing.assert_allclose(raised[whole_sum], written[whole_sum], rtol=1e-5)
        short = written[~whole_sum]
        assert (short > stop).all() and (short <= raised[~whole_sum] * (1 + 1e-5)).all()
    assert (total > 0).sum() > 1000, "the parts must hold density"
    assert (~whole_sum).sum() >= 5, "some cells must pass the level in every part"
    if r._bound_lanes(r._kernels_of(r._last[1], "iso")) > 1:
        # the frame's lanes never stop early: every listed cell holds its whole sum
        np.testing.assert_allclose(raised, written, rtol=1e-5)


def test_a_small_molecules_listed_cells_walked_by_lanes_keep_every_bound_and_the_image(
    device: str,
) -> None:
    """On CUDA a small molecule's listed cells are walked by BOUND_LANES threads each: the
    same cells walked, the same parts below the level, bounds equal up to the order of their
    sums, and the same image as one thread a cell. On the CPU, whose tiles are one thread
    wide, any number asked for walks with one."""
    top, pos = _two_lumps()
    cam = fit_camera(pos, 64, 48)
    params = RenderParams()
    runs = {}
    stop = 0.0
    for lanes in (1, None, 8):
        r = render(device, top, pos, params, cam, 64, 48, part_bounds="all", bound_lanes=lanes)
        kernels = r._kernels_of(r._last[1], "iso")
        stop = r._stop_level(params, r._last[1])
        expect = 1 if device == "cpu" or lanes == 1 else renderer_module.BOUND_LANES
        assert r._bound_lanes(kernels) == (expect if lanes is None else min(lanes, expect))
        cells = int(np.prod(r.grid_info()["dims"]))
        runs[lanes] = (  # copies: on the CPU `numpy()` views memory the next renderer reuses
            r._grid.cell_values.numpy()[:cells].copy(),
            r._grid.parts.numpy()[:cells].copy(),
            r.read_rgba(),
            r.read_depth(),
            r.read_atom_ids(),
        )
    one = runs[1]
    assert ((one[1] & WALKED) != 0).sum() > 100
    # one thread stops its walk once every part passes the level; the lanes sum them all
    stopped = one[0] > stop
    assert (~stopped).sum() > 1000
    for lanes in (None, 8):
        np.testing.assert_allclose(runs[lanes][0][~stopped], one[0][~stopped], rtol=1e-5)
        assert (runs[lanes][0][stopped] > stop).all()
        # the lanes' whole sums pass where one thread stopped (the lanes' kernel ran)
        grew = (runs[lanes][0] > one[0] * (1 + 1e-4)).sum()
        assert grew > 0 if device != "cpu" else grew == 0
        for a, b in zip(runs[lanes][1:], one[1:], strict=True):
            np.testing.assert_array_equal(a, b)


def _walked_parts(r: Renderer) -> set[tuple[int, int, int]]:
    """Cells (x, y, z) of the last grid that walked for their part bounds."""
    dims = np.asarray(r.grid_info()["dims"])
    words = r._grid.parts.numpy()[: int(np.prod(dims))]
    cell = np.nonzero(words & WALKED)[0]
    xyz = np.stack([cell % dims[0], (cell // dims[0]) % dims[1], cell // (dims[0] * dims[1])], 1)
    return {(int(x), int(y), int(z)) for x, y, z in xyz}


def test_visible_part_bounds_follow_the_view(device: str) -> None:
    """With part bounds for the view, the cells that walk for their parts are those in front
    of the surface the camera sees: a camera on +z walks cells on the lumps' +z side; turned
    to -z over the same atoms, it adds cells on their -z side; new positions start over.
    Each image is that of whole cells, bit for bit."""
    top, pos = _two_lumps()
    params = RenderParams()
    cam = fit_camera(pos, 64, 48)
    back = orbit(cam, 180.0, 0.0)
    axis = quat_to_matrix(cam.orientation)[:, 2]  # from the target towards the first camera
    r = Renderer(device, tuning=Tuning(part_bounds="visible"))
    r.set_topology(top)

    def side(cells: set[tuple[int, int, int]]) -> float:
        """Median height along `axis` of the cells' centres above the atoms' centre."""
        info = r.grid_info()
        xyz = np.asarray(sorted(cells), dtype=np.float64)
        at = np.asarray(info["origin"]) + (xyz + 0.5) * float(info["h"]) - pos.mean(axis=0)
        return float(np.median(at @ axis))

    walked = []
    for view, fresh in ((cam, True), (back, False), (back, True)):
        if fresh:
            r.set_positions(pos)
        r.render(params, view, 64, 48)
        ref = render(device, top, pos, params, view, 64, 48, part_bounds="none")
        np.testing.assert_array_equal(r.read_rgba(), ref.read_rgba())
        np.testing.assert_array_equal(r.read_depth(), ref.read_depth())
        walked.append(_walked_parts(r))
    front, both, rear = walked
    assert len(front) > 20 and side(front) > 0
    assert front < both and side(both - front) < 0
    assert len(rear) > 20 and side(rear) < 0


def test_positions_seen_by_many_views_walk_every_open_cell(
    device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """By default a large system's grid walks the parts of the cells its views reach. Once
    STILL_VIEWS cameras have seen one set of positions (a turning camera), the grid is built
    again walking every open cell, as "all" does; positions after two or more cameras (need
    is 2 here: viewers with cameras of their own) start so too, positions after one camera go
    back to the view's cells. The bands of one camera's image are one view, and a new level
    on the same positions goes by the views of the level before it. Every image is that of
    whole cells, bit for bit."""
    monkeypatch.setattr(renderer_module, "VISIBLE_ATOMS", 1)
    monkeypatch.setattr(renderer_module, "STILL_VIEWS", 3)
    top, pos = _two_lumps()
    params = RenderParams()
    other = RenderParams(iso_level=0.3)
    cam = fit_camera(pos, 64, 48)
    every = {
        p.iso_level: _walked_parts(render(device, top, pos, p, cam, 64, 48, part_bounds="all"))
        for p in (params, other)
    }
    r = Renderer(device, tuning=Tuning(part_trial=False))  # the rule of sizes, untimed
    r.set_topology(top)
    top_band, low_band = (0, 0, 64, 24), (0, 24, 64, 24)
    steps: list[tuple[bool, float, RenderParams, tuple[int, int, int, int] | None, str]] = [
        (True, 0.0, params, None, "view"),  # one camera ...
        (False, 30.0, params, None, "view"),
        (False, 60.0, params, None, "all"),  # ... the third on still positions: all
        (True, 0.0, params, None, "all"),  # new positions after three cameras
        (True, 0.0, params, None, "view"),  # after one
        (False, 30.0, params, None, "view"),
        (True, 0.0, params, top_band, "all"),  # after two
        (False, 0.0, params, low_band, "all"),
        (True, 0.0, params, top_band, "view"),  # after one camera's two bands
        (False, 0.0, other, None, "view"),  # a new level after one view
        (False, 30.0, other, None, "view"),
        (False, 60.0, other, None, "all"),
        (False, 60.0, params, None, "all"),  # the level before, after three views
        (False, 60.0, other, None, "view"),  # after one
    ]
    ref = Renderer(device, tuning=Tuning(part_bounds="none"))
    ref.set_topology(top)
    ref.set_positions(pos)
    for fresh, yaw, p, tile, expect in steps:
        if fresh:
            r.set_positions(pos)
        view = orbit(cam, yaw, 0.0)
        r.render(p, view, 64, 48, tile)
        ref.render(p, view, 64, 48, tile)
        np.testing.assert_array_equal(r.read_rgba(), ref.read_rgba())
        np.testing.assert_array_equal(r.read_depth(), ref.read_depth())
        walked = _walked_parts(r)
        if expect == "all":
            assert walked == every[p.iso_level], (yaw, tile, p.iso_level)
        else:
            assert 0 < len(walked) < len(every[p.iso_level]), (yaw, tile, p.iso_level)


def test_volume_frames_of_large_systems_walk_the_cells_of_the_view(
    device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From VISIBLE_ATOMS atoms a volume frame walks for part bounds the cells its view
    reaches, as "visible" does, and from LARGE_ATOMS whole cells only; the image is that of
    whole cells, bit for bit."""
    monkeypatch.setattr(renderer_module, "VISIBLE_ATOMS", 1)
    top, pos = _two_lumps()
    params = RenderParams(mode="volume")
    cam = fit_camera(pos, 64, 48)
    forced = render(device, top, pos, params, cam, 64, 48, part_bounds="visible")
    every = render(device, top, pos, params, cam, 64, 48, part_bounds="all")
    ref = render(device, top, pos, params, cam, 64, 48, part_bounds="none")
    seen = _walked_parts(render(device, top, pos, params, cam, 64, 48, part_trial=False))
    assert 0 < len(seen) < len(_walked_parts(every)) and seen == _walked_parts(forced)
    monkeypatch.setattr(renderer_module, "LARGE_ATOMS", 1)
    r = render(device, top, pos, params, cam, 64, 48, cells_per_cutoff=2.0, part_trial=False)
    assert _walked_parts(r) == set()
    np.testing.assert_array_equal(r.read_rgba(), ref.read_rgba())
    np.testing.assert_array_equal(forced.read_rgba(), ref.read_rgba())


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_rays_count_their_density_passes(device: str, mode: str) -> None:
    """`count_passes` draws the same image and reports each ray's density passes: none for
    rays that miss the atoms' box, some for those that reach a surface; skipping empty space
    never adds a pass and saves many; an iso ray queued after a budget of passes and resumed
    adds up to the passes of one uninterrupted march."""
    top, pos = _two_lumps()
    cam = fit_camera(pos, 64, 48)
    params = RenderParams(mode=mode)  # type: ignore[arg-type]
    plain = render(device, top, pos, params, cam, 64, 48)
    counted = render(device, top, pos, params, cam, 64, 48, count_passes=True)
    np.testing.assert_array_equal(counted.read_rgba(), plain.read_rgba())
    np.testing.assert_array_equal(counted.read_depth(), plain.read_depth())
    passes = counted.read_pass_counts()
    hit = np.isfinite(counted.read_depth())
    assert hit.mean() > 0.1 and (passes[hit] > 0).all()
    assert (passes[0] == 0).all(), "the top row misses the atoms' box"
    full = render(
        device, top, pos, params, cam, 64, 48, count_passes=True, empty_space_skipping=False
    )
    every = full.read_pass_counts()
    assert (every >= passes).all() and every.sum() > 2 * passes.sum()
    if mode == "iso":
        queued = render(
            device, top, pos, params, cam, 64, 48, count_passes=True, march_budget=2, split_lanes=1
        )
        np.testing.assert_array_equal(queued.read_pass_counts(), passes)
        assert (passes > 2).any(), "some rays must have been queued"
        # queued rays finished by four lanes each: the rays done within the budget keep
        # their count, the queued ones add the lanes' passes to the two they took
        lanes = render(
            device, top, pos, params, cam, 64, 48, count_passes=True, march_budget=2, split_lanes=4
        ).read_pass_counts()
        np.testing.assert_array_equal(lanes[passes <= 2], passes[passes <= 2])
        assert (lanes[passes > 2] > 2).all()
    with pytest.raises(RenderError, match="count_passes=True"):
        plain.read_pass_counts()


def test_marking_rays_keep_their_count_on_larger_images() -> None:
    """The marking rays' stride is STRIDE up to 1920x1080 and grows with the image's linear
    size above it, so a 4K image casts as many marking rays as a 1080p one."""
    assert visibility.stride_for(64, 48) == visibility.STRIDE == 2
    assert visibility.stride_for(1920, 1080) == 2
    assert visibility.stride_for(2560, 1440) == 3
    assert visibility.stride_for(3840, 2160) == 4
    assert visibility.rays(3840, 2160, 4) == visibility.rays(1920, 1080, 2)


def test_part_bounds_mode_is_checked() -> None:
    with pytest.raises(RenderError, match=r"part_bounds must be one of all, visible, none"):
        Renderer("cpu", tuning=Tuning(part_bounds="some"))  # type: ignore[arg-type]


def test_bound_keep_from_below_one_is_refused() -> None:
    with pytest.raises(RenderError, match=r"bound_keep_from must be >= 1, got 0\.5"):
        Renderer("cpu", tuning=Tuning(bound_keep_from=0.5))


@pytest.mark.parametrize("parts", ["all", "visible", "none"])
def test_cell_kernels_that_stride_over_the_cells_give_the_same_bounds(
    device: str, parts: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The per-cell kernels (weights, spread, settle, walks) launch at most CELL_THREADS
    threads, each striding over the cells beyond: with a few threads, every cell's bound,
    its parts and the image are those of a thread per cell."""
    top, pos = _two_lumps()
    params = RenderParams()
    cam = fit_camera(pos, 48, 32)
    runs = []
    for threads in (grid_module.CELL_THREADS, 37):
        monkeypatch.setattr(grid_module, "CELL_THREADS", threads)
        r = render(device, top, pos, params, cam, 48, 32, part_bounds=parts)
        cells = int(np.prod(r.grid_info()["dims"]))
        assert cells > 37 * 10
        # copies: on the CPU an array's numpy() views memory freed with the renderer
        bounds = r._grid.cell_values.numpy()[:cells].copy()
        words = r._grid.parts.numpy()[:cells].copy()
        runs.append((bounds, words, r.read_rgba(), r.read_depth()))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_untapered_gaussians_are_cut_at_the_cutoff(device: str) -> None:
    """`Tuning(taper=False)`, the baseline the taper's cost is measured against: each atom's
    Gaussian whole inside the cutoff and zero beyond."""
    rng = np.random.default_rng(21)
    pos = rng.normal(scale=3.0, size=(60, 3)).astype(np.float32)
    top = make_topology(60)
    params = RenderParams(sigma_A=1.2, level_scale="absolute", iso_level=0.3)
    r = render(device, top, pos, params, fit_camera(pos, 8, 6), 8, 6, taper=False)
    pts = pos[:20] + rng.normal(scale=1.5, size=(20, 3)).astype(np.float32)
    got = r.evaluate(pts)[0]
    d2 = ((pts[:, None, :].astype(np.float64) - pos[None]) ** 2).sum(-1)
    e = d2 / (2 * 1.2**2)
    k = reach_sigmas(1.2, params.cutoff_sigmas)
    want = np.where(e < 0.5 * k**2, np.exp(-e), 0.0).sum(axis=1)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-7)
    tapered = render(device, top, pos, params, fit_camera(pos, 8, 6), 8, 6).evaluate(pts)[0]
    assert not np.allclose(tapered, want, rtol=1e-6)  # the default does taper
    with pytest.raises(RenderError, match="unknown tuning tapering"):
        Tuning.of({"tapering": False})
