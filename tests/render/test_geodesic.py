"""The geodesic density (the thesis's warped molecular density, made smooth): its float64
reference against eqs. 5.2-5.6 as printed, the properties its design promises (the thesis's
field as the smoothing goes to 0, never above the classical density, no crease, not a
narrower Gaussian), and the device kernels against the reference."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import warp as wp

from protocol import RenderParams
from server.render import geodesic, geodesic_field, raycast
from server.render.camera import fit_camera, orbit
from server.render.errors import CapacityError
from server.render.geodesic import (
    BondGraph,
    Geodesic,
    GeodesicScales,
    best_classical_sigma,
    classical_density,
)
from server.render.reach import reach_sigmas
from server.render.renderer import Renderer
from tests.render.helpers import render
from tests.render.molecules import Mol, benzene, hairpin, three_atoms, villin
from thesis import molecular

GEODESIC = RenderParams(scale_space="geodesic", sigma_A=1.5)


def geodesic_of(mol: Mol, reach: float, densities: np.ndarray | None = None) -> Geodesic:
    pos = mol.positions.astype(np.float64)
    d = np.ones(len(pos)) if densities is None else densities
    return Geodesic.build(pos, d, BondGraph.of(mol.topology), reach)


def thesis_graph(g: molecular.BondGraph) -> Geodesic:
    """A thesis molecule (figs. 5.5-5.8) with route tables reaching every atom."""
    graph = BondGraph.from_bonds(len(g.positions), g.bonds)
    return Geodesic.build(g.positions, g.densities, graph, 50.0, gain=g.gain)


def plane_points(n: int, seed: int, extent: float = 3.0) -> np.ndarray:
    pts = np.random.default_rng(seed).uniform(-extent, extent, size=(n, 3))
    pts[:, 2] = 0.0
    return pts


THESIS = {
    "three atoms": molecular.three_atoms(),
    "dense centre": molecular.three_atoms(2.5),
    "ring": molecular.ring(),
}


def second_difference_ratios(f: object, o: np.ndarray, v: np.ndarray, h: float) -> list[float]:
    """max |second difference| at steps h, h/2, h/4 along a line, as the ratios of
    successive ones: 4 for a field with a bounded second derivative, 2 across a crease."""
    worst = []
    for step in (h, h / 2, h / 4):
        t = np.arange(-0.1, 0.1 + step / 2, step)
        s = np.asarray(f(o + t[:, None] * v))  # type: ignore[operator]
        worst.append(float(np.abs(s[2:] - 2.0 * s[1:-1] + s[:-2]).max()))
    return [worst[0] / worst[1], worst[1] / worst[2]]


# ---------------------------------------------------------------- the reference


@pytest.mark.parametrize("name", list(THESIS))
def test_smoothing_zero_is_eqs_5_2_to_5_5_as_printed(name: str) -> None:
    g = THESIS[name]
    geo = thesis_graph(g)
    pts = plane_points(300, 1)
    for sigma in (0.6, 1.2):
        ref = molecular.thesis_density(g, pts, sigma)
        got = geo.density(pts, sigma, smoothing=0.0, cutoff_sigmas=None)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(THESIS))
def test_the_field_tends_to_the_thesiss_as_the_smoothing_goes_to_zero(name: str) -> None:
    """(a): the distance to eq. 5.5 shrinks with the smoothing, at every point (ties
    included: their routes are equal, and a mean of equal routes is that route)."""
    g = THESIS[name]
    geo = thesis_graph(g)
    pts = plane_points(300, 2)
    ref = molecular.thesis_density(g, pts, 1.0)
    errors = [
        float(np.abs(geo.density(pts, 1.0, smoothing=t, cutoff_sigmas=None) - ref).max())
        for t in (0.1, 0.01, 0.001)
    ]
    assert errors[1] < 0.2 * errors[0] and errors[2] < 0.2 * errors[1], errors
    assert errors[2] < 2e-3


@pytest.mark.parametrize("name", [*THESIS, "villin"])
def test_never_above_the_classical_density(name: str) -> None:
    """(b): every route is a path through the molecule, never shorter than the straight
    line, so at equal sigma and weights the field never exceeds the classical one."""
    if name == "villin":
        mol = villin()
        pos = mol.positions.astype(np.float64)
        rng = np.random.default_rng(3)
        pts = pos[rng.integers(0, len(pos), 300)] + rng.normal(scale=1.5, size=(300, 3))
        d = np.ones(len(pos))
        geo = geodesic_of(mol, 8.0)
    else:
        g = THESIS[name]
        pos, d, pts, geo = g.positions, g.densities, plane_points(300, 4), thesis_graph(g)
    for sigma in (0.7, 1.5, 2.0):
        classical = classical_density(pts, pos, d, sigma)
        for strength in (1.0, 0.4):
            got = geo.density(pts, sigma, strength=strength)
            assert (got <= classical + 1e-12).all()
            # and by the renderer's gate: a route is at least sqrt(r^2 + tau^2) long
            for smoothing in (0.6, 2.0):
                gate = math.exp(-strength * smoothing**2 / 2.0)
                got = geo.density(pts, sigma, strength=strength, smoothing=smoothing)
                assert (got <= classical * gate + 1e-12).all()
    zero = geo.density(pts, 1.5, strength=0.0)
    np.testing.assert_allclose(zero, classical_density(pts, pos, d, 1.5), rtol=1e-12)


@pytest.mark.parametrize("name", list(THESIS))
def test_no_crease_on_the_thesiss_molecules(name: str) -> None:
    """(c): second differences converge as the step halves (ratios near 4) along random lines
    through the molecule; the thesis's own field, the control, is creased (near 2 or below)."""
    geo = thesis_graph(THESIS[name])
    rng = np.random.default_rng(5)
    smooth, creased = [], []
    for _ in range(30):
        o = rng.uniform(-2.0, 2.0, 3)
        o[2] = 0.0
        v = rng.normal(size=3)
        v[2] = 0.0
        v /= np.linalg.norm(v)
        smooth += second_difference_ratios(lambda p: geo.density(p, 1.0), o, v, 0.02)
        exact = lambda p: geo.density(p, 1.0, smoothing=0.0)  # noqa: E731
        creased += second_difference_ratios(exact, o, v, 0.02)
    assert min(smooth) > 3.3, sorted(smooth)[:3]
    assert min(creased) < 2.5


def surface_points(geo: Geodesic, sigma: float, level: float, count: int, seed: int) -> np.ndarray:
    """Points of the iso-surface S = level: from random atoms outwards along random directions
    to the first crossing, refined by bisection."""
    rng = np.random.default_rng(seed)
    pos = geo.positions
    out: list[np.ndarray] = []
    ts = np.arange(0.1, 10.0, 0.2)
    for i in rng.permutation(len(pos)):
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        values = geo.density(pos[i] + ts[:, None] * v, sigma)
        below = np.nonzero(values < level)[0]
        if not len(below) or below[0] == 0:
            continue
        lo, hi = ts[below[0] - 1], ts[below[0]]
        for _ in range(22):
            mid = 0.5 * (lo + hi)
            if geo.density(pos[i] + mid * v[None], sigma)[0] < level:
                hi = mid
            else:
                lo = mid
        out.append(pos[i] + lo * v)
        if len(out) == count:
            break
    return np.asarray(out)


def test_no_crease_at_200_points_of_a_proteins_surface() -> None:
    """(c) on a real protein (villin headpiece, 582 atoms): at 200 points of its iso-surface
    (sigma 1.5 A, a quarter of the mean density at the atoms), along random directions."""
    mol = villin()
    geo = geodesic_of(mol, 6.0)
    sigma = 1.5
    level = 0.25 * float(geo.density(geo.positions[::5], sigma).mean())
    pts = surface_points(geo, sigma, level, 200, 6)
    assert len(pts) == 200
    rng = np.random.default_rng(7)
    ratios = []
    for p in pts:
        v = rng.normal(size=3)
        ratios += second_difference_ratios(
            lambda q: geo.density(q, sigma), p, v / np.linalg.norm(v), 0.02
        )
    assert np.percentile(ratios, 1) > 3.4 and min(ratios) > 3.0, sorted(ratios)[:5]


def test_not_a_narrower_gaussian_where_the_graph_matters() -> None:
    """(d): the classical density closest to the field (over its width and an amplitude)
    leaves a residual in the plane of a ring and of a hairpin, where routes go round the ring
    and along the strands; on one atom, with nothing to route through, it explains the field
    (the control)."""
    rng = np.random.default_rng(8)
    ring = geodesic_of(benzene(hydrogens=False), 8.0)
    pts = np.c_[rng.uniform(-2.5, 2.5, (400, 2)), np.zeros(400)]
    fit = best_classical_sigma(
        ring.density(pts, 1.0), pts, ring.positions, ring.densities, 0.2, 3.0
    )
    assert fit[2] > 0.08, fit
    pin = geodesic_of(hairpin(), 12.0)
    pts = np.c_[rng.uniform(-2, 13, 600), rng.uniform(-5, 5, 600), np.zeros(600)]
    fit = best_classical_sigma(pin.density(pts, 1.0), pts, pin.positions, pin.densities, 0.2, 5.0)
    assert fit[2] > 0.04, fit
    lone = Geodesic.build(np.zeros((1, 3)), np.ones(1), BondGraph.from_bonds(1, []), 6.0)
    near = rng.normal(scale=1.0, size=(200, 3))
    fit = best_classical_sigma(
        lone.density(near, 1.0), near, lone.positions, lone.densities, 0.2, 3.0
    )
    assert fit[2] < 1e-4 and fit[0] == pytest.approx(1.0, rel=1e-3), fit


# ---------------------------------------------------------------- the device kernels


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("villin", GEODESIC),
        ("villin", RenderParams(scale_space="geodesic", sigma_A=0.9, density_weights="electrons")),
        ("hairpin", RenderParams(scale_space="geodesic", sigma_A=2.0, warp_strength=0.6)),
        ("three atoms", RenderParams(scale_space="geodesic", sigma_A=1.0, level_scale="absolute")),
        ("hairpin", RenderParams(scale_space="geodesic", sigma_A=1.5, geodesic_smoothing=0.05)),
    ],
)
def test_value_and_gradient_match_the_reference(
    device: str, name: str, params: RenderParams
) -> None:
    mol = {"villin": villin, "hairpin": hairpin, "three atoms": three_atoms}[name]()
    cam = fit_camera(mol.positions, 32, 24)
    # the routes per sample (the grid's interpolant has tests of its own)
    r = render(device, mol.topology, mol.positions, params, cam, 32, 24, geodesic_volume=False)
    assert r.last_density == "geodesic"
    sigma = params.sigma_A
    k = reach_sigmas(sigma, params.cutoff_sigmas)
    lam = params.warp_strength
    tau = params.geodesic_smoothing
    scales = GeodesicScales.of(sigma, lam, k * sigma, tau)
    from server.render import colors

    d = colors.atom_weights(mol.topology, params.density_weights).astype(np.float64)
    geo = geodesic_of(mol, scales.table_reach, d)
    rng = np.random.default_rng(11)
    pts = mol.positions[rng.integers(0, len(mol.positions), 40)] + rng.normal(size=(40, 3))
    ref = geo.density(pts, sigma, strength=lam, smoothing=tau, cutoff_sigmas=k)
    ref = ref / r.density_scale()
    val, vg, _col, ids = r.evaluate(pts)
    np.testing.assert_allclose(val, ref, rtol=2e-5, atol=2e-6 * float(ref.max()))
    h = 1e-4
    grad = (
        np.stack(
            [
                (
                    geo.density(pts + h * e, sigma, strength=lam, smoothing=tau, cutoff_sigmas=k)
                    - geo.density(pts - h * e, sigma, strength=lam, smoothing=tau, cutoff_sigmas=k)
                )
                / (2 * h)
                for e in np.eye(3)
            ],
            axis=1,
        )
        / r.density_scale()
    )
    np.testing.assert_allclose(vg[:, :3], grad, rtol=1e-3, atol=2e-4 * float(np.abs(grad).max()))
    assert (ids[val > 0] >= 0).all()


def test_the_batched_walks_match_one_point_walks(device: str) -> None:
    """The marching kernels' four-point walks (every point, or only where the classical density
    reaches a level) give what one walk per point gives."""
    mol = villin()
    r = Renderer(device)
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    f = r.prepare(GEODESIC)
    rng = np.random.default_rng(12)
    m = 64
    o = mol.positions[rng.integers(0, len(mol.positions), m)] + rng.normal(size=(m, 3))
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    arrays = [wp.array(a.astype(np.float32), dtype=wp.vec3, device=device) for a in (o, d)]
    out = wp.zeros((m, 4), dtype=wp.vec4, device=device)
    wp.launch(_batched_kernel, m, (f, *arrays, 0.5, out), device=device)
    single, batched, level, side = (out.numpy()[:, k] for k in range(4))
    np.testing.assert_allclose(batched, single, rtol=1e-5, atol=1e-6)
    reached = single >= 0.5  # the classical density is higher still there
    np.testing.assert_allclose(level[reached], single[reached], rtol=1e-5, atol=1e-6)
    assert (level[~reached] < 0.5).all()
    # the side walk: the value where it walked every atom, else only which side it is on
    above, below = side == np.inf, side == -1.0
    walked = ~above & ~below
    np.testing.assert_allclose(side[walked], single[walked], rtol=1e-5, atol=1e-6)
    assert (single[above] >= 0.5 * (1 - 1e-5)).all() and (single[below] < 0.5 * (1 + 1e-5)).all()
    # and it did stop early, both ways, at points where the classical density reaches the level
    gated = level >= 0.0
    assert (above & gated).sum() > 10 and (below & gated).sum() > 10


def test_a_route_mean_whose_weights_underflow_is_taken_by_the_running_least(device: str) -> None:
    """`atom_distance_near` weighs each route against the straight line: where every route
    is many tau longer than it (tau 0.01 A here, points up to 40 A from the atom) those
    weights underflow, and the running least (exact whatever the spread) takes the atom;
    everywhere both give the same mean."""
    mol = villin()
    r = Renderer(device)
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    f = r.prepare(GEODESIC.model_copy(update={"sigma_A": 0.2, "geodesic_smoothing": 0.05}))
    rng = np.random.default_rng(5)
    m = 256
    atoms = rng.integers(0, len(mol.positions), m).astype(np.int32)
    d = rng.normal(size=(m, 3))
    d *= rng.uniform(0.5, 40.0, (m, 1)) / np.linalg.norm(d, axis=1, keepdims=True)
    pts = mol.positions[atoms] + d
    r2 = (d**2).sum(axis=1)
    args = (
        wp.array(atoms, dtype=wp.int32, device=device),
        wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(r2.astype(np.float32), dtype=float, device=device),
    )
    out = wp.zeros(m, dtype=wp.vec3, device=device)
    wp.launch(_means_kernel, m, (f, *args, out), device=device)
    near, least, weights = out.numpy().T
    assert np.isfinite(near).all()
    np.testing.assert_allclose(near, least, rtol=1e-5)
    under = weights <= geodesic_field.FLOOR
    assert under.sum() > 10 and (~under).sum() > 10


@wp.kernel
def _means_kernel(  # type: ignore[no-untyped-def]
    f: geodesic_field.GeodesicField,
    atoms: wp.array(dtype=wp.int32),
    pts: wp.array(dtype=wp.vec3),
    r2: wp.array(dtype=float),
    out: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    a = atoms[i]
    p = pts[i]
    rt = f.routes
    ref = wp.sqrt(r2[i] + rt.tau2)
    acc = wp.vec2(0.0, 0.0)
    for k in range(rt.start[a], rt.start[a + 1]):
        acc = geodesic_field.weigh(acc, geodesic_field.route_pair(rt, k, p), ref, rt.inv_tau)
    near = geodesic_field.atom_distance_near(rt, a, p, r2[i])
    out[i] = wp.vec3(near, geodesic_field.atom_distance(rt, a, p), acc[0])


@wp.kernel
def _batched_kernel(  # type: ignore[no-untyped-def]
    f: geodesic_field.GeodesicField,
    o: wp.array(dtype=wp.vec3),
    d: wp.array(dtype=wp.vec3),
    level: float,
    out: wp.array2d(dtype=wp.vec4),
):
    i = wp.tid()
    ts = wp.vec4(0.0, 0.3, 0.6, 0.9)
    one = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for q in range(4):
        one[q] = geodesic_field.geodesic_value(f, o[i] + d[i] * ts[q])
    out[i, 0] = one
    out[i, 1] = geodesic_field.geodesic_value4(f, o[i], d[i], ts)
    out[i, 2] = geodesic_field.geodesic_value4_level(f, o[i], d[i], ts, level)
    out[i, 3] = geodesic_field.geodesic_side4(f, o[i], d[i], ts, level)


@pytest.mark.parametrize("case", ["outside", "inside", "vdw radii, strength 0.4"])
def test_a_march_told_only_the_sides_draws_the_same_image(device: str, case: str) -> None:
    """The marching kernels' side walk (`decided_sides`) against every gated sample walked
    whole: the same image, from outside, from a camera inside the surface (rays start above
    the level and cross it downwards) and with per-atom widths and a blended distance."""
    mol = villin()
    cam = orbit(fit_camera(mol.positions, 48, 36), 30.0, 20.0)
    params = GEODESIC
    if case == "inside":
        centre = mol.positions.mean(axis=0)
        atom = mol.positions[np.argmin(np.linalg.norm(mol.positions - centre, axis=1))]
        cam = cam.model_copy(update={"target": tuple(float(x) for x in atom), "distance": 0.3})
    elif case != "outside":
        params = GEODESIC.model_copy(update={"radius_mode": "vdw", "warp_strength": 0.4})
    images = []
    for sides in (True, False):
        r = render(device, mol.topology, mol.positions, params, cam, 48, 36, decided_sides=sides)
        images.append((r.read_rgba(), r.read_depth(), r.read_atom_ids()))
    (rgba, depth, ids), (rgba0, depth0, ids0) = images
    assert np.isfinite(depth).sum() > 100
    assert np.array_equal(ids, ids0)
    # the side walk adds the near atoms first, the whole walk row by row: the same terms in
    # another order, so a sample within rounding of the level may fall on the other side and
    # its hit move by an ulp
    assert np.abs(rgba.astype(int) - rgba0.astype(int)).max() <= 1
    np.testing.assert_allclose(depth, depth0, rtol=1e-6, atol=0.0)


def test_strength_zero_draws_the_classical_image(device: str) -> None:
    mol = villin()
    cam = orbit(fit_camera(mol.positions, 48, 36), 30.0, 20.0)
    zero = render(
        device,
        mol.topology,
        mol.positions,
        GEODESIC.model_copy(update={"warp_strength": 0.0}),
        cam,
        48,
        36,
    )
    classical = render(device, mol.topology, mol.positions, RenderParams(), cam, 48, 36)
    assert np.array_equal(zero.read_rgba(), classical.read_rgba())


def test_a_geodesic_surface_lies_inside_the_classical_one(device: str) -> None:
    """Drawn at the same absolute level, every ray that hits the geodesic surface hits the
    classical one no farther away (the field is lower everywhere)."""
    mol = villin()
    cam = orbit(fit_camera(mol.positions, 48, 36), 30.0, 20.0)
    level = {"level_scale": "absolute", "iso_level": 0.5}
    geo = render(
        device, mol.topology, mol.positions, GEODESIC.model_copy(update=level), cam, 48, 36
    )
    classical = render(device, mol.topology, mol.positions, RenderParams(**level), cam, 48, 36)
    dg, dc = geo.read_depth(), classical.read_depth()
    hit = np.isfinite(dg)
    assert hit.sum() > 100 and np.isfinite(dc[hit]).all()
    assert (dc[hit] <= dg[hit] + 1e-3).all() and (dc[hit] < dg[hit] - 0.05).any()


def test_the_relative_level_is_taken_by_several_lanes_a_sample(device: str) -> None:
    """The geodesic density's own scale (the mean at the sampled atoms: every atom of villin)
    summed by 4 or 32 threads a sample, each holding up to QUEUE atoms before it walks their
    routes, equals one thread's (which holds and walks many times a sample) up to the order of
    its float sums, and draws the same image; the density it scales averages 1 at the atoms."""
    mol = villin()
    cam = fit_camera(mol.positions, 40, 30)
    out = {}
    for lanes in (1, 4, 32):
        r = render(
            device, mol.topology, mol.positions, GEODESIC, cam, 40, 30,
            mean_lanes=lanes, geodesic_volume=False,
        )  # fmt: skip
        out[lanes] = (r.density_scale(), r.read_rgba())
        at_atoms = r.evaluate(mol.positions)[0].astype(np.float64)
        assert at_atoms.mean() == pytest.approx(1.0, rel=1e-5)
    for lanes in (4, 32):
        assert out[lanes][0] == pytest.approx(out[1][0], rel=1e-5)
        differ = np.any(out[lanes][1] != out[1][1], axis=-1).mean()
        assert differ < 0.005  # a pixel whose ray grazes the level may flip
    assert out[1][0] > 0.0


def test_route_tables_follow_the_reach_and_report_their_bytes(device: str) -> None:
    mol = villin()
    cam = fit_camera(mol.positions, 16, 12)
    r = render(device, mol.topology, mol.positions, GEODESIC, cam, 16, 12)
    tables = r._geo
    assert tables is not None and tables.key == (
        "uniform",
        GeodesicScales.of(1.5, 1, 1.5 * reach_sigmas(1.5, 4.0)).table_reach,
    )
    small = r.memory_bytes()["geodesic"]
    assert small > 0
    r.render(GEODESIC.model_copy(update={"sigma_A": 1.55}), cam, 16, 12)  # the same step
    assert r.memory_bytes()["geodesic"] == small
    r.render(GEODESIC.model_copy(update={"sigma_A": 2.5}), cam, 16, 12)
    assert r.memory_bytes()["geodesic"] > small and tables.lost == 0


def test_an_atom_without_bonds_keeps_its_own_gaussian() -> None:
    geo = Geodesic.build(np.zeros((1, 3)), np.ones(1), BondGraph.from_bonds(1, []), 6.0)
    pts = np.random.default_rng(13).normal(size=(50, 3))
    tau = geodesic.SMOOTHING * 1.5
    r2 = (pts * pts).sum(axis=1)
    want = geodesic.taper((r2 + tau * tau) / (2 * 1.5**2), 4.0)
    np.testing.assert_allclose(geo.density(pts, 1.5), want, rtol=1e-12)


def test_a_sigma_whose_samples_walk_too_many_routes_is_refused_before_the_tables() -> None:
    """One REST render at sigma 50 A held the device's thread for over 20 minutes (every atom's
    routes through every bond near it, at every sample), with every other render waiting. Such
    a density is refused at once, with its numbers and the limit; smaller sigmas still draw,
    and the refusal holds for the reach it was made for, not for the renderer."""
    m = villin()
    r = Renderer("cpu")
    r.set_topology(m.topology)
    r.set_positions(m.positions)
    for sigma in (5.0, 50.0):
        with pytest.raises(CapacityError, match=r"routes a sample .* limit of 50,000") as err:
            r.prepare(RenderParams(scale_space="geodesic", sigma_A=sigma))
        assert f"sigma {sigma:g} A" in str(err.value)
    assert r._geo is None or r._geo.key is None  # no tables were built for them
    r.prepare(RenderParams(scale_space="geodesic", sigma_A=1.5))
    near, per_atom = r._geo_work[1], r._geo_work[2]  # type: ignore[index]
    assert 20 < near < 120 and 10 < per_atom < 40  # villin at 1.5 A: about 50 atoms, 22 routes
    r.geodesic_max_routes = int(near * per_atom) // 2
    r._geo.key = None  # type: ignore[union-attr]  # the tables built again, now over the limit
    with pytest.raises(CapacityError, match="limit of"):
        r.prepare(RenderParams(scale_space="geodesic", sigma_A=1.5))
    r.prepare(RenderParams(sigma_A=50.0))  # the classical density is not limited so


def test_route_work_counts_what_the_tables_hold() -> None:
    """The estimate before the build against the tables the device builds: atoms within the
    cutoff and routes an atom, within sampling error."""
    m = villin()
    r = Renderer("cpu")
    r.set_topology(m.topology)
    r.set_positions(m.positions)
    r.prepare(RenderParams(scale_space="geodesic", sigma_A=3.0))
    tables = r._geo
    assert tables is not None
    built = np.diff(tables.route_start.numpy()).mean()
    _, near, per_atom = r._geo_work  # type: ignore[misc]
    assert 0.7 * built < per_atom < 1.3 * built
    pos = m.positions.astype(np.float64)
    reach = r.reach(RenderParams(scale_space="geodesic", sigma_A=3.0))
    d2 = ((pos[:, None] - pos[None]) ** 2).sum(-1)
    assert 0.7 < near / (d2 <= reach * reach).sum(1).mean() < 1.4


def test_the_whole_walks_kernels_are_made_once_a_process(
    device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The marching kernels without the side walk (CUDA's default) are generated once, not
    again for every renderer (a session, a layer, a device each hold one)."""
    made: list[str] = []
    real = raycast._make

    def counted(model, *args):  # type: ignore[no-untyped-def]
        made.append(model.name)
        return real(model, *args)

    monkeypatch.setattr(raycast, "_make", counted)
    mol = three_atoms()
    cam = fit_camera(mol.positions, 16, 12)
    for _ in range(3):
        render(device, mol.topology, mol.positions, GEODESIC, cam, 16, 12, decided_sides=False)
    assert made.count("geodesic_whole_samples") <= 1


def test_route_tables_a_device_cannot_hold_are_refused_with_their_size(
    device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Route tables larger than the device's free memory are refused before they are
    allocated, naming their size. The tables they would have replaced stay whole: the last
    frame's densities and histogram are what they were, the sigma drawn before draws again
    as a fresh renderer draws it, and the refused one once there is room."""
    mol = villin()
    cam = fit_camera(mol.positions, 24, 18)
    wide = GEODESIC.model_copy(update={"sigma_A": 2.5})
    r = Renderer(device)
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    r.render(GEODESIC, cam, 24, 18)
    pts = mol.positions[::7] + 0.7
    values, hist = r.evaluate(pts)[0], r.density_histogram()[0]
    monkeypatch.setattr(geodesic_field, "free_bytes", lambda _device: 1000)
    with pytest.raises(
        CapacityError,
        match=(
            r"tables of 584 atoms, each reaching \d+\.\d A .* need \d\.\d MB; "
            rf"{re.escape(device)} has \d+\.\d kB"
        ),
    ):
        r.render(wide, cam, 24, 18)
    np.testing.assert_array_equal(r.evaluate(pts)[0], values)
    np.testing.assert_array_equal(r.density_histogram()[0], hist)
    monkeypatch.undo()
    for params in (GEODESIC, wide):
        r.render(params, cam, 24, 18)
        ref = render(device, mol.topology, mol.positions, params, cam, 24, 18)
        np.testing.assert_array_equal(r.read_rgba(), ref.read_rgba())
        np.testing.assert_array_equal(r.read_depth(), ref.read_depth())


def test_every_route_carries_its_bonds_geometry_of_this_frame(device: str) -> None:
    """Each route's copy of its bond's geometry and its ends' graph distances follows the
    atoms every frame (`geometry_kernel`), not only the frame after its tables are built."""
    mol = villin()
    cam = fit_camera(mol.positions, 16, 12)
    r = Renderer(device)
    r.set_topology(mol.topology)
    rng = np.random.default_rng(3)
    for step in range(3):
        moved = mol.positions + rng.normal(scale=0.2 * step, size=mol.positions.shape)
        r.set_positions(moved.astype(np.float32))
        r.render(GEODESIC, cam, 16, 12)
        t = r._geodesic_tables()
        bond = t.route_bond.numpy()[: t.route_total]
        seg = t.seg_a.numpy()[bond]
        ra = t.route_a.numpy()[: t.route_total]
        rv = t.route_v.numpy()[: t.route_total]
        g = t.route_g.numpy()[: t.route_total]
        ends = t.ends.numpy()[bond]
        np.testing.assert_array_equal(ra[:, :3], seg[:, :3])
        np.testing.assert_allclose(ra[:, :3], moved[ends[:, 0]], atol=1e-5)
        np.testing.assert_array_equal(rv[:, :3], t.seg_v.numpy()[bond][:, :3])
        np.testing.assert_array_equal(np.stack([ra[:, 3], rv[:, 3]], axis=1), g)
        # each route's length and 1 / length^2 of its bond, made once this frame
        sv = t.seg_v.numpy()[bond]
        rl = t.route_l.numpy()[: t.route_total]
        np.testing.assert_array_equal(rl, np.stack([seg[:, 3], sv[:, 3] * sv[:, 3]], axis=1))
        length = np.linalg.norm(moved[ends[:, 1]] - moved[ends[:, 0]], axis=1)
        np.testing.assert_allclose(rl[:, 0], length, rtol=1e-5)
    # the sizes the memory check counts are those of the tables
    nodes = int(t.node_start.numpy()[-1])
    need = nodes * geodesic_field.NODE_BYTES + t.route_total * geodesic_field.ROUTE_BYTES
    assert sum(int(a.capacity) for a in t._tables()) == need


@wp.kernel
def _route_pairs(
    ai: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    v: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    p: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    tau2: float,
    out: wp.array(dtype=wp.vec2),  # type: ignore[valid-type]
) -> None:
    i = wp.tid()
    b = geodesic_field.RouteBond()
    b.ai = ai[i]
    b.v = v[i]
    b.length = wp.length(v[i])
    b.inv_l2 = 1.0 / (b.length * b.length)
    b.w2 = tau2 * b.inv_l2
    b.g = wp.vec2(0.0, 0.0)
    out[i] = geodesic_field.pair_at(b, p[i], tau2)


def test_a_routes_distance_across_keeps_its_precision_near_a_bonds_ends() -> None:
    """At a small smoothing the distance across a bond is a few hundredths of an angstrom near
    its ends and its middle, where |p - a_i|^2 and the projection's terms are of the bond's
    length squared: the kernel's two routes stay within 1e-6 A of float64 there (a form that
    subtracts those terms lost 6e-5 A at tau = 0.01 A), and within float32's rounding of the
    route's length away from the bond."""
    rng = np.random.default_rng(11)
    n = 4000
    tau2 = 1.0e-4
    ai = rng.uniform(-30.0, 30.0, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    v = d * rng.uniform(0.9, 2.2, (n, 1))
    # near the far end, the near end and the middle, within a few tau, and some far away
    where = rng.choice([1.0, 0.0, 0.5], n)[:, None]
    near = ai + v * where + rng.normal(scale=0.03, size=(n, 3))
    far = ai + rng.normal(scale=8.0, size=(n, 3))
    p = np.where(rng.random((n, 1)) < 0.8, near, far)
    ai32, v32, p32 = (x.astype(np.float32) for x in (ai, v, p))
    out = wp.zeros(n, dtype=wp.vec2, device="cpu")
    args = [wp.array(x, dtype=wp.vec3, device="cpu") for x in (ai32, v32, p32)]
    wp.launch(_route_pairs, n, [*args, tau2, out], device="cpu")
    a, b, q = (x.astype(np.float64) for x in (ai32, v32, p32))
    length = np.linalg.norm(b, axis=1)
    t = np.einsum("ij,ij->i", q - a, b) / length**2
    u = geodesic.smooth_clamp(t, np.sqrt(tau2) / length)
    across = np.sqrt(np.sum((q - (a + b * u[:, None])) ** 2, axis=1) + tau2)
    want = np.stack([across + u * length, across + (1.0 - u) * length], axis=1)
    got = out.numpy().astype(np.float64)
    over = np.abs(got - want) / (1.0e-6 + 2.0e-7 * want)
    assert over.max() <= 1.0, over.max()
