"""Ray casting vs brute-force references: iso hit depth per pixel (per-ray root finder on the
same sample lattice), volume compositing (numpy front-to-back), picking, and the claim that
empty-space skipping never changes an image."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import Camera, Lighting, RenderParams, TFPoint
from server.render import raycast
from server.render.camera import camera_frame, fit_camera, image_rays, look_at, orbit
from server.render.errors import RenderError
from server.render.renderer import Renderer
from server.render.transfer import build_table
from server.render.tuning import VOLUME_STEPS, Tuning
from tests.render import oracle
from tests.render.conftest import blob, make_topology
from tests.render.helpers import oracle_light, oracle_molecule, render

W, H = 64, 48


def _t_range(r: Renderer, origins: np.ndarray) -> tuple[float, float]:
    """A lattice range covering the grid box for every ray (outside it S == 0)."""
    info = r.grid_info()
    lo = np.asarray(info["origin"], dtype=np.float64)
    hi = np.asarray(info["box_hi"], dtype=np.float64)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    o = origins.reshape(-1, 3)
    dist = np.linalg.norm(corners[None, :, :] - o[:, None, :], axis=-1)
    return 0.0, float(dist.max()) + 1.0


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_iso_depth_matches_root_finder(device: str, projection: str) -> None:
    n = 45
    top = make_topology(n)
    pos = blob(n, seed=21, spread=2.5)
    params = RenderParams(sigma_A=1.4, iso_level=0.6, step_sigmas=0.3)
    cam = orbit(fit_camera(pos, W, H, projection, margin=-2.0), 25.0, -15.0)  # type: ignore[arg-type]
    r = render(device, top, pos, params, cam, W, H)
    depth = r.read_depth()
    ids = r.read_atom_ids()
    frame = camera_frame(cam, W, H)
    origins, dirs = image_rays(frame)
    dt = params.step_sigmas * params.sigma_A
    mol = oracle_molecule(top, pos, params)
    ref = oracle.first_crossings(mol, origins, dirs, _t_range(r, origins), dt, params.iso_level)
    t_ref = ref.t.reshape(H, W)
    amb = ref.ambiguous.reshape(H, W)
    hit_ref = np.isfinite(t_ref)
    hit = np.isfinite(depth)
    assert 0.2 < hit_ref.mean() < 0.9
    mismatch = hit != hit_ref
    assert np.all(amb[mismatch]), f"{mismatch.sum()} unexplained hit/miss differences"
    both = hit & hit_ref & ~amb
    tol = dt / raycast.REFINE_SHRINK + 2e-4
    err = np.abs(depth[both] - t_ref[both])
    assert err.max() <= tol, err.max()
    # the secant point is refined by one Newton step from the shading sample: half the
    # crossings come within a hundred-thousandth of a step (float32 depth, ~1e-6 A)
    assert np.median(err) <= 1e-5 * dt + 2e-6, "the Newton step should land on the surface"
    assert np.all(ids[~hit] == -1) and np.all(ids[hit] >= 0)
    pts = origins[both] + depth[both][:, None] * dirs[both]
    best, margin = oracle.top_atom(mol, pts)
    clear = margin > 1e-3
    np.testing.assert_array_equal(ids[both][clear], best[clear])
    y, x = np.argwhere(both)[0]
    atom, d = r.pick(int(x), int(y))
    assert atom == ids[y, x] and d == pytest.approx(float(depth[y, x]))
    by, bx = np.argwhere(~hit)[0]
    assert r.pick(int(bx), int(by)) == (None, None)


@pytest.mark.parametrize(
    ("tf", "preset", "light"),
    [
        ((), "cloud", Lighting()),
        ((), "shells", Lighting(key_light=False, depth_cue=0.6)),
        (
            (
                TFPoint(x=0.0, alpha=0.0),
                TFPoint(x=0.3, color=(1, 0.5, 0), alpha=0.3),
                TFPoint(x=1.5, alpha=0.9),
            ),
            "cloud",
            Lighting(diffuse=0.0, specular=0.0),
        ),
        (  # a step: two points at one x
            (
                TFPoint(x=0.0, alpha=0.0),
                TFPoint(x=0.6, alpha=0.0),
                TFPoint(x=0.6, color=(1, 0, 0), alpha=0.5),
                TFPoint(x=1.5, color=(0, 1, 0), alpha=0.5),
            ),
            "cloud",
            Lighting(),
        ),
        (  # x_max far below the densities: most ramps run past the table's end
            (
                TFPoint(x=0.0, alpha=0.0),
                TFPoint(x=0.01, alpha=0.0),
                TFPoint(x=0.02, color=(0, 1, 0), alpha=0.4),
            ),
            "cloud",
            Lighting(diffuse=0.0, specular=0.0),
        ),
    ],
)
def test_volume_matches_numpy_compositor(
    device: str, tf: tuple[TFPoint, ...], preset: str, light: Lighting
) -> None:
    n = 30
    w, h = 20, 14
    top = make_topology(n)
    pos = blob(n, seed=4)
    params = RenderParams(
        mode="volume",
        sigma_A=1.3,
        iso_level=0.5,
        step_sigmas=0.35,
        transfer_function=list(tf),
        tf_preset=preset,  # type: ignore[arg-type]
        lighting=light,
        background=(0.1, 0.2, 0.3),
    )
    cam = fit_camera(pos, w, h, margin=1.0)
    r = render(device, top, pos, params, cam, w, h)
    img = r.read_rgba().astype(np.float64) / 255.0
    depth = r.read_depth()
    frame = camera_frame(cam, w, h)
    origins, dirs = image_rays(frame)
    lt = oracle_light(params, frame, r)
    table = build_table(params.transfer_function, params.tf_preset)
    mol = oracle_molecule(top, pos, params)
    dt = params.step_sigmas * params.sigma_A * VOLUME_STEPS  # volume's lattice
    t_range = _t_range(r, origins)
    shade = light.diffuse > 0 or light.specular > 0
    ref = np.zeros((h, w, 3))
    ref_depth = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            ref[y, x], ref_depth[y, x] = oracle.composite(
                mol,
                origins[y, x],
                dirs[y, x],
                t_range,
                dt,
                params.iso_level,
                table,
                lt,
                shade,
                jitter=oracle.pixel_jitter(x, y),
            )
    diff = np.abs(img[..., :3] - ref)
    assert diff.max() <= 3.0 / 255.0, diff.max()
    assert np.all(img[..., 3] == 1.0)
    covered = np.isfinite(ref_depth)
    assert covered.any()
    agree = np.isfinite(depth) == covered
    assert agree.mean() > 0.97
    both = np.isfinite(depth) & covered
    assert np.allclose(depth[both], ref_depth[both], atol=dt * 1.01)


def test_a_transfer_function_clear_everywhere_draws_the_background(device: str) -> None:
    """Alpha 0 at every x: the clear level is infinite, every region is skipped, and the image
    is the background, as the numpy compositor draws it."""
    n = 30
    top = make_topology(n)
    pos = blob(n, seed=4)
    tf = [TFPoint(x=0.0, alpha=0.0), TFPoint(x=2.0, color=(1, 0, 0), alpha=0.0)]
    params = RenderParams(mode="volume", sigma_A=1.3, transfer_function=tf)
    cam = fit_camera(pos, 12, 10)
    r = render(device, top, pos, params, cam, 12, 10)
    frame = camera_frame(cam, 12, 10)
    origins, dirs = image_rays(frame)
    lt = oracle_light(params, frame, r)
    table = build_table(params.transfer_function, params.tf_preset)
    mol = oracle_molecule(top, pos, params)
    dt = params.step_sigmas * params.sigma_A * VOLUME_STEPS
    for y, x in ((0, 0), (5, 6), (9, 11)):
        want, depth = oracle.composite(
            mol, origins[y, x], dirs[y, x], _t_range(r, origins), dt, params.iso_level, table,
            lt, True,
        )  # fmt: skip
        assert depth == np.inf
        np.testing.assert_allclose(want, params.background)
    bg = np.round(np.asarray(params.background) * 255.0)
    assert np.all(r.read_rgba()[..., :3] == bg)
    assert np.all(np.isinf(r.read_depth())) and np.all(r.read_atom_ids() == -1)


@pytest.mark.parametrize("sparse", [False, True])
@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_empty_space_skipping_changes_nothing(device: str, mode: str, sparse: bool) -> None:
    n = 50
    top = make_topology(n)
    pos = blob(n, seed=8, spread=7.0)
    if sparse:  # far-apart lumps: rays jump whole empty bricks between them
        pos[::3] += np.float32(45.0)
        pos[1::3] -= np.float32([30.0, -20.0, 40.0])
    params = RenderParams(mode=mode, sigma_A=1.1)  # type: ignore[arg-type]
    cam = fit_camera(pos, W, H)
    fast = render(device, top, pos, params, cam, W, H)
    naive = render(device, top, pos, params, cam, W, H, empty_space_skipping=False)
    np.testing.assert_array_equal(fast.read_rgba(), naive.read_rgba())
    np.testing.assert_array_equal(fast.read_depth(), naive.read_depth())
    np.testing.assert_array_equal(fast.read_atom_ids(), naive.read_atom_ids())


_ENDS_TFS = {
    "step": [
        TFPoint(x=0.0, alpha=0.0),
        TFPoint(x=0.6, alpha=0.0),
        TFPoint(x=0.6, color=(1, 0, 0), alpha=0.5),
        TFPoint(x=1.5, color=(0, 1, 0), alpha=0.5),
    ],
    "clear-at-nothing": [TFPoint(x=0.0, alpha=0.05), TFPoint(x=1.0, alpha=0.3)],
    "shells": [],
}


@pytest.mark.parametrize("tf", list(_ENDS_TFS))
@pytest.mark.parametrize("scale_space", ["classical", "geodesic", "carved"])
def test_empty_space_skipping_changes_nothing_at_the_ray_ends(
    device: str, scale_space: str, tf: str
) -> None:
    """Volume rays that start inside the molecule and end at a depth limit, through a step,
    a transfer function clear nowhere and the shells: skipping (cells and their parts) and
    a march that samples everything draw the same image, on each density (the geodesic and
    carved ones answer any value below the level there)."""
    import warp as wp

    n, w, h = 120, 24, 18
    rng = np.random.default_rng(0)
    pos = rng.uniform(-8, 8, size=(n, 3)).astype(np.float32)
    top = make_topology(n, bonds=np.array([[i, i + 1] for i in range(n - 1)]))
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -5.0), fov_deg=70.0)
    limit = rng.uniform(2.0, 20.0, w * h).astype(np.float32)
    params = RenderParams(
        mode="volume",
        sigma_A=1.1,
        iso_level=0.3,
        transfer_function=_ENDS_TFS[tf],
        tf_preset="shells",
        scale_space=scale_space,  # type: ignore[arg-type]
    )
    images = []
    naive: dict[str, object] = {"empty_space_skipping": False}
    for tuning in (naive, {"part_bounds": "all"}, {"part_bounds": "none"}):
        r = Renderer(device, tuning=Tuning.of(tuning))
        r.set_topology(top)
        r.set_positions(pos)
        r.depth_limit = wp.array(limit, dtype=float, device=device)
        r.render(params, cam, w, h)
        images.append((r.read_rgba(), r.read_depth(), r.read_atom_ids()))
    assert len(np.unique(images[0][0].reshape(-1, 4), axis=0)) > 20  # something is drawn
    for other in images[1:]:
        for a, b in zip(images[0], other, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("scene", ["blob", "sparse", "inside"])
@pytest.mark.parametrize(("budget", "lanes"), [(1, 1), (1, 8), (2, 32), (3, 4)])
def test_split_rays_draw_the_same_image(device: str, scene: str, budget: int, lanes: int) -> None:
    """Queuing rays after `budget` passes and finishing them with `lanes` threads each
    (forced here; automatic only for small images on CUDA) draws the one-kernel image."""
    n = 120
    top = make_topology(n)
    pos = blob(n, seed=5, spread=8.0)
    cam = fit_camera(pos, W, H)
    if scene == "sparse":
        pos[::3] += np.float32(45.0)
        cam = fit_camera(pos, W, H)
    elif scene == "inside":
        cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -5.0), fov_deg=70.0)
    params = RenderParams(sigma_A=1.2, iso_level=0.4)
    one = render(device, top, pos, params, cam, W, H, march_budget=0)
    split = render(device, top, pos, params, cam, W, H, march_budget=budget, split_lanes=lanes)
    assert int(split._queue_len.numpy()[0]) > 0
    np.testing.assert_array_equal(split.read_depth(), one.read_depth())
    np.testing.assert_array_equal(split.read_rgba(), one.read_rgba())
    np.testing.assert_array_equal(split.read_atom_ids(), one.read_atom_ids())


@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_the_cpu_devices_rays_split_across_host_threads_draw_the_same_image(
    mode: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """warp's CPU device runs a launch on the thread that makes it; once a kernel is loaded the
    march, the shading and the volume cast run as runs of whole 8x4 tiles on several host
    threads. Each pixel is its run's alone, so the image, its depths, atoms and pass counts are
    one launch's bit for bit, whole or a band of it."""
    from server.render import device

    spread: list[int] = []
    split_launch = device.split_launch

    def counted(kernel: object, runs: list, dev: str, threads: int, *rest: object) -> None:  # type: ignore[type-arg]
        if threads > 1:
            spread.append(len(runs))
        split_launch(kernel, runs, dev, threads, *rest)  # type: ignore[arg-type]

    monkeypatch.setattr(device, "split_launch", counted)
    n = 120
    top = make_topology(n)
    pos = blob(n, seed=5, spread=8.0)
    cam = fit_camera(pos, W, H)
    params = RenderParams(sigma_A=1.2, iso_level=0.4, mode=mode)  # type: ignore[arg-type]
    outs = []
    for threads in (1, 3):
        r = Renderer("cpu", tuning=Tuning(cpu_threads=threads, count_passes=True))
        r.set_topology(top)
        r.set_positions(pos)
        for tile in (None, None, (5, 3, W - 9, H - 7)):  # the first whole frame compiles
            r.render(params, cam, W, H, tile)
            got = (r.read_rgba(), r.read_depth(), r.read_atom_ids(), r.read_pass_counts())
            outs.append(tuple(np.array(x, copy=True) for x in got))
    assert all(runs > 3 for runs in spread)  # the threads' runs
    assert len(spread) == (2 if mode == "iso" else 1) * 3  # each kernel of each frame
    for a, b in zip(outs[:3], outs[3:], strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_split_policy_and_its_arguments() -> None:
    auto = Renderer("cpu")
    assert auto._budget_for(W * H) == 0  # never automatic on the CPU
    assert Renderer("cpu", tuning=Tuning(march_budget=5))._budget_for(W * H) == 5
    with pytest.raises(RenderError, match="march_budget"):
        Renderer("cpu", tuning=Tuning(march_budget=-1))
    with pytest.raises(RenderError, match="split_lanes"):
        Renderer("cpu", tuning=Tuning(split_lanes=0))


def test_cell_size_does_not_change_the_image(device: str) -> None:
    top = make_topology(40)
    pos = blob(40, seed=2)
    params = RenderParams(sigma_A=1.5)
    cam = fit_camera(pos, W, H)
    a = render(device, top, pos, params, cam, W, H, cells_per_cutoff=1.0)
    b = render(device, top, pos, params, cam, W, H, cells_per_cutoff=2.0)
    diff = np.abs(a.read_rgba().astype(int) - b.read_rgba().astype(int))
    assert (diff > 2).mean() < 0.002
    both = np.isfinite(a.read_depth()) & np.isfinite(b.read_depth())
    assert np.allclose(a.read_depth()[both], b.read_depth()[both], atol=1e-3)


def test_camera_inside_molecule_sees_the_wall(device: str) -> None:
    n = 200
    top = make_topology(n)
    rng = np.random.default_rng(0)
    pos = (rng.uniform(-9, 9, size=(n, 3))).astype(np.float32)
    params = RenderParams(sigma_A=1.6, iso_level=0.3)
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -5.0), fov_deg=70.0)
    r = render(device, top, pos, params, cam, 40, 30)
    mol = oracle_molecule(top, pos, params)
    assert oracle.density(mol, np.zeros((1, 3)))[0][0] >= params.iso_level
    depth = r.read_depth()
    assert np.isfinite(depth).mean() > 0.5
    assert np.nanmin(np.where(np.isfinite(depth), depth, np.nan)) > 0.0
    frame = camera_frame(cam, 40, 30)
    origins, dirs = image_rays(frame)
    ys, xs = np.nonzero(np.isfinite(depth))
    pts = origins[ys, xs] + depth[ys, xs, None] * dirs[ys, xs]
    vals = oracle.density(mol, pts)[0]
    assert np.median(np.abs(vals - params.iso_level)) < 0.02


def test_orthographic_depth_is_distance_from_the_camera_plane(device: str) -> None:
    top = make_topology(1)
    pos = np.array([[1.0, -2.0, 3.0]], np.float32)
    params = RenderParams(sigma_A=1.0, iso_level=0.5)
    cam = Camera(
        target=(1.0, -2.0, 3.0), distance=20.0, projection="orthographic", ortho_height=8.0
    )
    r = render(device, top, pos, params, cam, 33, 33)
    radius = np.sqrt(2 * np.log(1 / 0.5))
    assert r.read_depth()[16, 16] == pytest.approx(20.0 - radius, abs=2e-3)
    assert r.read_depth()[0, 0] == np.inf
