"""The carved density (a narrower Gaussian density carved away from the bond skeleton; not the
thesis's warped density, which is the geodesic one): the kernels against the float64
reference, and what its design promises (docs/rendering.md): smooth, the 1-D along-graph scale
space on a chain, the classical density at strength 0, structure that only simplifies as sigma
grows, invariance and symmetry; and the name it had before, "warped", still drawing it."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

import timewarp
from protocol import RenderParams
from server.render import colors, raycast
from server.render.camera import camera_frame, fit_camera, image_rays, orbit
from server.render.reach import reach_sigmas
from server.render.renderer import Renderer
from server.render.skeleton import (
    GAIN,
    GRAPH_CUTOFF_SIGMAS,
    Skeleton,
    WarpScales,
    carved_density,
    smoothed_densities,
)
from tests.render import oracle
from tests.render.helpers import carved_reference, render
from tests.render.molecules import Mol, benzene, chain, hairpin, three_atoms, villin, villin_phe

CARVED = RenderParams(scale_space="carved", sigma_A=1.5)


def _render(
    device: str, mol: Mol, params: RenderParams, w: int = 48, h: int = 36, **kw: object
) -> Renderer:
    cam = orbit(fit_camera(mol.positions, w, h, margin=1.0), 30.0, 20.0)
    return render(device, mol.topology, mol.positions, params, cam, w, h, **kw)


def _points_around(mol: Mol, m: int, seed: int, spread: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = mol.positions[rng.integers(0, len(mol.positions), m)]
    return (base + rng.normal(size=(m, 3)) * spread).astype(np.float32)


# ---------------------------------------------------------------- kernels vs the reference


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("villin", CARVED),
        ("villin", RenderParams(scale_space="carved", sigma_A=0.9, density_weights="electrons")),
        ("hairpin", RenderParams(scale_space="carved", sigma_A=2.5, warp_strength=0.6)),
        ("benzene", RenderParams(scale_space="carved", sigma_A=1.0)),
    ],
)
def test_value_and_gradient_match_the_reference(
    device: str, name: str, params: RenderParams
) -> None:
    mol = {"villin": villin, "hairpin": hairpin, "benzene": benzene}[name]()
    r = _render(device, mol, params, 8, 6)
    pts = _points_around(mol, 500, seed=3, spread=1.8)
    vals, vgs, cols, _ids = r.evaluate(pts)
    ref, ref_grad = carved_reference(mol.topology, mol.positions, params)(pts.astype(np.float64))
    scale = float(ref.max())
    np.testing.assert_allclose(vals, ref, rtol=1e-5, atol=1e-6 * scale)
    np.testing.assert_allclose(vgs[:, 3], ref, rtol=1e-5, atol=1e-6 * scale)
    np.testing.assert_allclose(cols[:, 3], ref, rtol=1e-5, atol=1e-6 * scale)
    gscale = float(np.abs(ref_grad).max())
    np.testing.assert_allclose(vgs[:, :3], ref_grad, rtol=1e-4, atol=1e-5 * gscale)
    assert (ref > 1e-3 * scale).sum() > 100
    # relative levels: the density is divided by its mean at the atoms
    absolute = params.model_copy(update={"level_scale": "absolute"})
    at_atoms = carved_reference(mol.topology, mol.positions, absolute)(mol.positions)[0]
    assert r.density_scale() == pytest.approx(float(at_atoms.mean()), rel=1e-5)


def test_smoothing_along_the_graph_matches_the_reference(device: str) -> None:
    mol = villin()
    params = RenderParams(scale_space="carved", sigma_A=3.0, density_weights="electrons")
    r = _render(device, mol, params, 4, 4)
    sc = WarpScales.of(params.sigma_A, params.warp_strength)
    dens = colors.atom_weights(mol.topology, "electrons").astype(np.float64)
    ref = smoothed_densities(Skeleton.of(mol.topology), mol.positions, dens, sc.graph)
    got = r._weights.numpy()[: mol.topology.n_atoms]
    np.testing.assert_allclose(got, ref, rtol=2e-5)
    assert np.abs(ref - dens).max() > 0.5  # the smoothing did something


def test_iso_depth_matches_a_root_finder_on_the_reference(device: str) -> None:
    mol = villin_phe()
    params = RenderParams(scale_space="carved", sigma_A=1.2, step_sigmas=0.3)
    w, h = 40, 30
    cam = orbit(fit_camera(mol.positions, w, h, margin=-0.5), 25.0, 35.0)
    r = render(device, mol.topology, mol.positions, params, cam, w, h)
    depth = r.read_depth()
    frame = camera_frame(cam, w, h)
    origins, dirs = image_rays(frame)
    ref_fn = carved_reference(mol.topology, mol.positions, params)
    dt = params.step_sigmas * WarpScales.of(params.sigma_A, params.warp_strength).space
    t_far = float(np.linalg.norm(origins[0, 0] - mol.positions.mean(0))) + 20.0
    ref = oracle.first_crossings(
        lambda p: ref_fn(p)[0], origins, dirs, (0.0, t_far), dt, params.iso_level
    )
    t_ref = ref.t.reshape(h, w)
    amb = ref.ambiguous.reshape(h, w)
    hit, hit_ref = np.isfinite(depth), np.isfinite(t_ref)
    assert 0.1 < hit_ref.mean() < 0.9
    assert np.all(amb[hit != hit_ref])
    both = hit & hit_ref & ~amb
    err = np.abs(depth[both] - t_ref[both])
    assert err.max() <= dt / raycast.REFINE_SHRINK + 2e-4


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_strength_zero_is_the_classical_renderer(device: str, mode: str) -> None:
    mol = villin()
    classical = RenderParams(mode=mode, sigma_A=1.4)  # type: ignore[arg-type]
    zero = classical.model_copy(update={"scale_space": "carved", "warp_strength": 0.0})
    a = _render(device, mol, classical).read_rgba()
    b = _render(device, mol, zero).read_rgba()
    np.testing.assert_array_equal(a, b)
    # the carved density keeps cutoff_sigmas as its reach (reach.py measured the Gaussian's)
    full = _render(device, mol, classical, fixed_cutoff=True).read_rgba()
    weak = classical.model_copy(update={"scale_space": "carved", "warp_strength": 1e-4})
    c = _render(device, mol, weak).read_rgba()
    assert np.abs(c.astype(int) - full.astype(int)).max() <= 2


def test_rigid_motion_leaves_the_density_unchanged(device: str) -> None:
    mol = villin_phe()
    rng = np.random.default_rng(7)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    shift = np.array([40.0, -15.0, 7.0])
    moved = Mol(mol.topology, (mol.positions @ q.T + shift).astype(np.float32))
    params = RenderParams(scale_space="carved", sigma_A=1.1)
    pts = _points_around(mol, 300, seed=2, spread=1.5).astype(np.float64)
    a = _render(device, mol, params, 4, 4).evaluate(pts)[0]
    b = _render(device, moved, params, 4, 4).evaluate(pts @ q.T + shift)[0]
    np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-6 * a.max())


# ---------------------------------------------------------------- the design's promises


def _density(mol: Mol, sigma: float, strength: float) -> object:
    skeleton = Skeleton.of(mol.topology)
    d = np.ones(mol.topology.n_atoms)
    pos = mol.positions.astype(np.float64)
    return lambda p: carved_density(p, pos, d, skeleton, sigma, strength)[0]


def crease_ratio(density: object, mol: Mol, h: float, seed: int) -> float:
    """The smallest ratio, over lines through the molecule (its centre, atoms, bond midpoints),
    of the largest second difference of S at step h to that at h / 2."""
    rng = np.random.default_rng(seed)
    pos = mol.positions.astype(np.float64)
    bonds = mol.topology.bonds.to_numpy()
    origins = [pos.mean(axis=0), *pos[:4], *[(pos[i] + pos[j]) / 2 for i, j in bonds[:4]]]
    worst = math.inf
    for o in origins:
        for _ in range(3):
            v = rng.normal(size=3)
            v /= np.linalg.norm(v)
            o2 = o + rng.normal(scale=0.05, size=3)
            seconds = []
            for step in (h, h / 2):
                t = np.arange(-4.0, 4.0 + step / 2, step)
                s = np.asarray(density(o2 + t[:, None] * v))  # type: ignore[operator]
                seconds.append(np.abs(s[2:] - 2 * s[1:-1] + s[:-2]).max())
            worst = min(worst, seconds[0] / seconds[1])
    return worst


@pytest.mark.parametrize("maker", [three_atoms, benzene, villin_phe])
def test_no_creases(maker: object) -> None:
    mol = maker()  # type: ignore[operator]
    carved = crease_ratio(_density(mol, 1.0, 1.0), mol, 0.02, seed=1)
    classical = crease_ratio(_density(mol, 1.0, 0.0), mol, 0.02, seed=1)
    assert classical == pytest.approx(4.0, abs=0.1)
    assert carved >= 3.5, carved


def test_no_creases_on_the_device(device: str) -> None:
    mol = villin_phe()
    r = _render(device, mol, RenderParams(scale_space="carved", sigma_A=1.0), 4, 4)
    ratio = crease_ratio(lambda p: r.evaluate(p)[0].astype(np.float64), mol, 0.04, seed=4)
    assert ratio >= 3.5, ratio


def _fill_sigma(mol: Mol, center: np.ndarray, mid: np.ndarray) -> float:
    """The smallest sigma at which the classical density fills the ring: S(centre) >= S(mid)."""
    lo, hi = 0.3, 3.0
    for _ in range(40):
        s = 0.5 * (lo + hi)
        f = _density(mol, s, 0.0)
        if f(center[None])[0] >= f(mid[None])[0]:  # type: ignore[operator]
            hi = s
        else:
            lo = s
    return hi


@pytest.mark.parametrize("hydrogens", [False, True])
def test_rings_are_carved_with_their_symmetry(hydrogens: bool) -> None:
    mol = benzene(hydrogens)
    pos = mol.positions.astype(np.float64)
    center, mid = np.zeros(3), (pos[0] + pos[1]) / 2
    sigma = _fill_sigma(mol, center, mid)
    classical = _density(mol, sigma, 0.0)
    carved = _density(mol, sigma, 1.0)
    assert classical(center[None])[0] >= classical(mid[None])[0]  # type: ignore[operator]
    ratio = carved(center[None])[0] / carved(mid[None])[0]  # type: ignore[operator]
    assert ratio <= 0.5, ratio
    # six-fold symmetry of the iso-contours: S on circles is 60-degree periodic and mirror
    # symmetric (to the float32 rounding of the atom positions)
    theta = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    for radius in (0.7, 1.2, 2.0, 3.0):
        ring_pts = np.stack([radius * np.cos(theta), radius * np.sin(theta), 0 * theta], axis=1)
        s = carved(ring_pts)  # type: ignore[operator]
        np.testing.assert_allclose(s, np.roll(s, 20), rtol=2e-6, atol=1e-12)
        np.testing.assert_allclose(s, s[::-1][np.r_[119, 0:119]], rtol=2e-6, atol=1e-12)
        assert np.ptp(s) > 1e-3 * s.max() or radius < 1.0  # the contours are not circles


@pytest.mark.parametrize("strength", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("sigma", [0.8, 1.5, 3.0])
def test_a_straight_chain_is_the_1d_along_graph_scale_space(strength: float, sigma: float) -> None:
    """On the axis of a straight chain (between its end atoms) S equals the classical scale
    space, at the spatial scale s3, of the atom densities after the warped convolution (eq. 3.3)
    at the graph scale sg with the arclength warp of the densities: `timewarp` computes both."""
    elements = ["H", "C", "C", "N", "H", "O", "C", "C", "S", "C"]
    mol = chain(elements, spacing=1.4)
    t = mol.positions[:, 0].astype(np.float64)
    d = colors.atom_weights(mol.topology, "electrons").astype(np.float64)
    x = np.linspace(t[0], t[-1], 401)
    axis = np.stack([x, 0 * x, 0 * x], axis=1)
    s, _ = carved_density(axis, mol.positions, d, Skeleton.of(mol.topology), sigma, strength)
    sc = WarpScales.of(sigma, strength)
    if sc.graph > 0:
        warp = timewarp.arclength_warp(t, d, gain=GAIN)
        dt = timewarp.warped_convolve(
            t, d, sc.graph, warp, x=t, normalise=True, truncate=GRAPH_CUTOFF_SIGMAS
        )
    else:
        dt = d
    # convolve() without normalisation is sum_j w_j f_j G / (sqrt(2 pi) s3), w_j = 1.4 here
    ref = timewarp.convolve(t, dt, sc.space, x=x, normalise=False) * (
        math.sqrt(2 * math.pi) * sc.space / 1.4
    )
    np.testing.assert_allclose(s, ref, rtol=1e-6, atol=1e-9)
    if strength == 0:
        classical = (d[None] * np.exp(-((x[:, None] - t[None]) ** 2) / (2 * sigma**2))).sum(1)
        np.testing.assert_allclose(s, classical, rtol=1e-12)


def test_a_straight_chain_on_the_device(device: str) -> None:
    mol = chain(["H", "C", "C", "N", "H", "O", "C", "C", "S", "C"])
    params = RenderParams(
        scale_space="carved", sigma_A=1.5, density_weights="electrons", level_scale="absolute"
    )
    r = _render(device, mol, params, 4, 4)
    x = np.linspace(0.0, 9 * 1.4, 200)
    axis = np.stack([x, 0 * x, 0 * x], axis=1)
    ref = carved_reference(mol.topology, mol.positions, params)(axis)[0]
    np.testing.assert_allclose(r.evaluate(axis)[0], ref, rtol=1e-5)


def _components(mol: Mol, sigma: float, strength: float, level: float) -> int:
    """Connected components of {S >= level x the mean of S at the atoms} on a lattice of a
    fifth of the spatial scale (0.08 A at least), over the molecule and 2.5 sigma around it."""
    ndimage = pytest.importorskip("scipy.ndimage")
    f = _density(mol, sigma, strength)
    pos = mol.positions.astype(np.float64)
    h = max(0.2 * WarpScales.of(sigma, strength).space, 0.08)
    lo, hi = pos.min(0) - 2.5 * sigma, pos.max(0) + 2.5 * sigma
    axes = [np.arange(lo[k], hi[k] + h, h) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = f(grid).reshape([len(a) for a in axes])  # type: ignore[operator]
    scale = float(np.mean(f(pos)))  # type: ignore[operator]
    _labels, count = ndimage.label(values >= level * scale)
    return int(count)


@pytest.mark.parametrize("maker", [three_atoms, benzene, hairpin])
def test_structure_only_simplifies_as_sigma_grows(maker: object) -> None:
    """Connected components inside the iso-surface (at the default relative level) never
    increase with sigma, for the classical and the carved density; the carved keeps the two
    strands of the hairpin apart longer."""
    mol = maker()  # type: ignore[operator]
    sigmas = (0.4, 0.7, 1.0, 1.4, 2.0, 2.8)
    level = RenderParams().iso_level
    counts = {s: [_components(mol, x, s, level) for x in sigmas] for s in (0.0, 1.0)}
    for strength, seq in counts.items():
        assert all(b <= a for a, b in itertools.pairwise(seq)), (strength, seq)
    if maker is hairpin:
        assert sum(counts[1.0]) > sum(counts[0.0]), counts


def test_the_default_cutoff_keeps_the_surface_in_place() -> None:
    """Tapering each Gaussian to zero at the reach the renderer takes by default (reach.py:
    the least the accuracy bound needs at each sigma) moves villin's iso-surface by at most
    max(0.05 A, 1 % of sigma) against the untruncated float64 density, from sigma 0.3 to 12 A
    (relative levels: the level follows the truncated density too). Crossings are taken along
    rays from the molecule's centre."""
    mol = villin()
    pos = mol.positions.astype(np.float64)
    center = pos.mean(axis=0)
    level = RenderParams().iso_level
    rng = np.random.default_rng(11)
    dirs = rng.normal(size=(32, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]

    def molecule(sigma: float, cut: float) -> oracle.Molecule:
        n = len(pos)
        return oracle.Molecule(pos, np.ones(n), np.full(n, sigma), cut, np.zeros((n, 3)))

    for sigma in (0.3, 0.6, 1.0, 1.5, 3.0, 6.0, 12.0):
        radii = np.linspace(0.0, 30.0 + 4 * sigma, 900)
        shift = 0.0
        k = reach_sigmas(sigma, RenderParams().cutoff_sigmas)
        mols = {cut: molecule(sigma, cut) for cut in (1e3, k)}  # 1e3 sigmas: untruncated
        levels = {cut: level * oracle.density_of(m, pos).mean() for cut, m in mols.items()}
        for v in dirs:
            pts = center + radii[:, None] * v
            crossing = {}
            for cut, m in mols.items():
                s = oracle.density_of(m, pts) - levels[cut]
                above = np.nonzero(s >= 0)[0]
                if len(above) == 0:
                    crossing[cut] = None
                    continue
                i = above[-1]
                crossing[cut] = radii[i] + s[i] / (s[i] - s[i + 1]) * (radii[i + 1] - radii[i])
            a, b = crossing[1e3], crossing[k]
            assert (a is None) == (b is None), (sigma, a, b)
            if a is not None and b is not None:
                shift = max(shift, abs(a - b))
        assert shift <= max(0.05, 0.01 * sigma), (sigma, shift)


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_empty_space_skipping_changes_nothing(device: str, mode: str) -> None:
    """The carved cell bounds (the Gaussian bound times the largest carving factor in the cell)
    only skip what cannot matter: the image equals the one marched without skipping."""
    mol = villin()
    params = RenderParams(mode=mode, scale_space="carved", sigma_A=1.3)  # type: ignore[arg-type]
    cam = orbit(fit_camera(mol.positions, 40, 30, margin=0.5), 20.0, 10.0)
    a = render(device, mol.topology, mol.positions, params, cam, 40, 30)
    b = render(device, mol.topology, mol.positions, params, cam, 40, 30, empty_space_skipping=False)
    np.testing.assert_array_equal(a.read_rgba(), b.read_rgba())


def test_the_name_warped_still_draws_the_carved_density(device: str) -> None:
    """Protocol 1.1-1.7 called the carved density "warped": saved views and recordings that say
    so draw the same image."""
    mol = villin()
    old = _render(device, mol, CARVED.model_copy(update={"scale_space": "warped"}))
    new = _render(device, mol, CARVED)
    assert np.array_equal(old.read_rgba(), new.read_rgba())
