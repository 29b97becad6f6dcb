"""Layers: each layer's density is that of its own atoms only, layers composite by depth
(nearest opaque hit, translucent blending front to back) and picking answers in the whole
system's atom indices with the layer; golden images of two and three layers."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import Camera, Layer, RenderParams, TFPoint, Topology
from server.render.camera import fit_camera, orbit
from server.render.layerplan import LayerPlan, plan_layers, subset_topology, visible_atoms
from server.render.layers import LayeredRenderer
from server.render.renderer import Renderer
from server.render.tuning import VOLUME_STEPS
from tests.render import oracle
from tests.render.conftest import blob, make_topology
from tests.render.golden_images import H, W, check_golden, gramicidin
from tests.render.helpers import oracle_light, oracle_molecule


def _plans(params: RenderParams, n: int, sets: dict[str, np.ndarray]) -> tuple[LayerPlan, ...]:
    plans = plan_layers(params, n, lambda text: (sets[text], text))
    assert plans is not None
    return plans


def _layered(
    device: str,
    top: Topology,
    pos: np.ndarray,
    plans: tuple[LayerPlan, ...],
    cam: Camera,
    w: int,
    h: int,
) -> LayeredRenderer:
    lr = LayeredRenderer(lambda: Renderer(device))
    lr.render(plans, top, 1, pos, 1, cam, w, h)
    return lr


def _alone(
    device: str,
    top: Topology,
    pos: np.ndarray,
    atoms: np.ndarray,
    params: RenderParams,
    cam: Camera,
    size: tuple[int, int] = (48, 36),
) -> Renderer:
    """A renderer that holds only `atoms` (the reference a layer must match)."""
    r = Renderer(device)
    r.set_topology(subset_topology(top, atoms))
    r.set_positions(pos[atoms])
    r.render(params, cam, *size)
    return r


@pytest.fixture
def two_lumps() -> tuple[Topology, np.ndarray, np.ndarray, np.ndarray]:
    """Two overlapping lumps of atoms: the first 40 and the last 30."""
    n = 70
    top = make_topology(n)
    pos = blob(n, seed=11, spread=2.0)
    pos[40:] = blob(30, seed=12, spread=2.0, offset=(3.0, 0.5, -1.0))
    return top, pos, np.arange(40, dtype=np.int32), np.arange(40, 70, dtype=np.int32)


def test_a_layer_draws_the_density_of_its_atoms_only(
    device: str, two_lumps: tuple[Topology, np.ndarray, np.ndarray, np.ndarray]
) -> None:
    top, pos, a, _b = two_lumps
    params = RenderParams(sigma_A=1.2, layers=[Layer(name="a", selection="A")])
    plans = _plans(params, top.n_atoms, {"A": a})
    cam = fit_camera(pos, 48, 36)
    lr = _layered(device, top, pos, plans, cam, 48, 36)
    # the layer's renderer evaluates the brute-force density of the selected atoms only
    child = lr._children[0].renderer
    rng = np.random.default_rng(5)
    pts = pos[rng.integers(0, len(pos), 64)] + rng.normal(size=(64, 3)).astype(np.float32)
    got = child.evaluate(pts)[0]
    want = oracle.density(oracle_molecule(subset_topology(top, a), pos[a], plans[0].params), pts)
    assert np.allclose(got, want[0], rtol=1e-4, atol=1e-6)
    # hidden atoms contribute nothing: moving them leaves the image as it was
    before = lr.read_rgba()
    moved = pos.copy()
    moved[40:] += 0.7
    lr.render(plans, top, 1, moved, 2, cam, 48, 36)
    assert np.array_equal(lr.read_rgba(), before)
    # ... and the image is the one a renderer of those atoms alone draws (over the background)
    alone = _alone(device, top, pos, a, plans[0].params, cam)
    assert np.array_equal(lr.read_depth(), alone.read_depth())
    assert np.abs(before.astype(int) - alone.read_rgba().astype(int)).max() <= 1
    ids = lr.read_atom_ids()
    local = alone.read_atom_ids()
    assert np.array_equal(ids, np.where(local >= 0, a[np.maximum(local, 0)], -1))


def test_overlapping_iso_layers_show_the_nearest_hit(
    device: str, two_lumps: tuple[Topology, np.ndarray, np.ndarray, np.ndarray]
) -> None:
    top, pos, a, b = two_lumps
    params = RenderParams(
        sigma_A=1.2,
        layers=[Layer(name="a", selection="A"), Layer(name="b", selection="B", sigma_A=0.8)],
    )
    plans = _plans(params, top.n_atoms, {"A": a, "B": b})
    cam = orbit(fit_camera(pos, 48, 36), 60.0, 10.0)
    lr = _layered(device, top, pos, plans, cam, 48, 36)
    ra = _alone(device, top, pos, a, plans[0].params, cam)
    rb = _alone(device, top, pos, b, plans[1].params, cam)
    da, db = ra.read_depth(), rb.read_depth()
    front_a = da <= db
    near = np.where(front_a, da, db)
    assert np.isfinite(da).any() and np.isfinite(db).any()
    assert (np.isfinite(da) & np.isfinite(db) & ~front_a).any(), "b must cover a somewhere"
    assert np.array_equal(lr.read_depth(), near)
    rgb_a, rgb_b = ra.read_rgba()[..., :3], rb.read_rgba()[..., :3]
    want = np.where(front_a[..., None], rgb_a, rgb_b)
    hit = np.isfinite(near)
    diff = np.abs(lr.read_rgba()[..., :3].astype(int) - want.astype(int))
    assert diff[hit].max() <= 1
    layer = lr.read_layers()
    assert np.array_equal(layer[hit], np.where(front_a, 0, 1)[hit])
    assert (layer[~hit] == -1).all()
    ids_b = rb.read_atom_ids()
    y, x = np.argwhere(hit & ~front_a)[0]
    atom, depth, name = lr.pick_layer(int(x), int(y))
    assert (atom, name) == (int(b[ids_b[y, x]]), "b")
    assert depth == pytest.approx(float(db[y, x]))


def test_translucent_layers_blend_front_to_back(
    device: str, two_lumps: tuple[Topology, np.ndarray, np.ndarray, np.ndarray]
) -> None:
    top, pos, a, b = two_lumps
    bg = (0.2, 0.1, 0.05)
    params = RenderParams(
        sigma_A=1.2,
        background=bg,
        layers=[
            Layer(name="a", selection="A", opacity=0.5),
            Layer(name="cloud", selection="B", mode="volume", opacity=0.8),
        ],
    )
    plans = _plans(params, top.n_atoms, {"A": a, "B": b})
    cam = fit_camera(pos, 48, 36)
    lr = _layered(device, top, pos, plans, cam, 48, 36)
    # the numpy oracle: each layer's premultiplied colour and coverage, blended in depth order
    layers = []
    for k, plan in enumerate(plans):
        child = lr._children[k].renderer
        rgba = child.read_rgba().astype(np.float64) / 255.0
        layers.append(
            (rgba[..., :3] * plan.opacity, rgba[..., 3] * plan.opacity, child.read_depth())
        )
    acc = np.zeros((36, 48, 3))
    alpha = np.zeros((36, 48))
    order = np.argsort(np.stack([d for _c, _a, d in layers]), axis=0, kind="stable")
    for rank in range(len(layers)):
        for k, (c, a_k, _d) in enumerate(layers):
            pick = order[rank] == k
            acc[pick] += c[pick] * (1.0 - alpha[pick])[:, None]
            alpha[pick] += a_k[pick] * (1.0 - alpha[pick])
    want = acc + np.asarray(bg) * (1.0 - alpha)[..., None]
    got = lr.read_rgba()[..., :3].astype(np.float64) / 255.0
    assert np.abs(got - want).max() <= 1.5 / 255.0
    assert (alpha > 0.3).any() and (alpha < 0.99).any()  # translucent where covered


def test_plans_follow_visibility_and_whole_selections() -> None:
    n = 10
    sets = {"all": np.arange(n, dtype=np.int32), "few": np.array([1, 3], np.int32)}
    params = RenderParams(
        sigma_A=2.0,
        iso_level=0.3,
        layers=[
            Layer(name="whole", selection="all", iso_level=0.5),
            Layer(name="hidden", selection="few", visible=False),
            Layer(name="clear", selection="few", opacity=0.0),
            Layer(
                name="few",
                selection="few",
                sigma_A=0.5,
                color_by="uniform",
                transfer_function=[TFPoint(x=0.5, alpha=0.3)],
            ),
        ],
    )
    plans = _plans(params, n, sets)
    assert [p.name for p in plans] == ["whole", "few"]
    assert plans[0].atoms is None  # every atom: drawn without a gather
    assert plans[0].params.iso_level == 0.5 and plans[0].params.sigma_A == 2.0
    assert plans[1].params.sigma_A == 0.5 and plans[1].params.iso_level == 0.3
    assert plans[1].params.color_by == "uniform" and plans[1].params.layers == []
    assert plans[1].params.transfer_function == [TFPoint(x=0.5, alpha=0.3)]
    assert plans[0].params.transfer_function == []
    assert np.array_equal(visible_atoms(plans, n), np.arange(n))
    assert np.array_equal(visible_atoms(plans[1:], n), [1, 3])
    assert plan_layers(RenderParams(), n, lambda t: (sets[t], t)) is None
    # a layer's preset replaces the session's own transfer-function points
    own = RenderParams(
        transfer_function=[TFPoint(x=1.0, alpha=0.5)],
        layers=[Layer(selection="few", tf_preset="shells")],
    )
    (shells,) = _plans(own, n, sets)
    assert shells.params.tf_preset == "shells" and shells.params.transfer_function == []


def test_subset_topology_renumbers_bonds() -> None:
    top = make_topology(6, bonds=np.array([[0, 1], [1, 2], [2, 5], [4, 5]]))
    sub = subset_topology(top, np.array([1, 2, 5], np.int32))
    assert sub.n_atoms == 3
    assert sub.bonds.to_numpy().tolist() == [[0, 1], [1, 2]]
    assert sub.elements == [top.elements[i] for i in (1, 2, 5)]
    assert sub.names == [top.names[i] for i in (1, 2, 5)]
    one = subset_topology(top, np.array([4], np.int32))  # a few of many: picked one by one
    assert one.names == [top.names[4]] and one.chain_ids == [top.chain_ids[4]]


def test_a_subset_of_a_system_past_the_wire_limits_is_not_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A part of a topology held in-process may exceed what one message may carry (a
    sort-last slab of a 100M-atom system): the wire's limits (here lowered to 100 atoms)
    are not applied to it."""
    import protocol.arrays

    top = make_topology(600, bonds=np.array([[i, i + 1] for i in range(599)]))
    monkeypatch.setattr(protocol.arrays, "DEFAULT_LIMITS", protocol.arrays.Limits(max_atoms=100))
    with pytest.raises(ValueError, match="limit"):
        make_topology(600)  # the lowered limit holds for what comes in
    sub = subset_topology(top, np.arange(1, 501, dtype=np.int32))
    assert sub.n_atoms == 500 and len(sub.bonds.to_numpy()) == 499
    assert sub.residue_ids.to_numpy().shape == (500,)


GOLDEN_LAYERS = {
    "layers_two": RenderParams(
        sigma_A=1.6,
        color_by="chain",
        layers=[
            Layer(name="surface", selection="A"),
            Layer(name="fine", selection="TRP", sigma_A=0.6, color_by="element"),
        ],
    ),
    "layers_three": RenderParams(
        sigma_A=1.6,
        color_by="chain",
        layers=[
            Layer(name="surface", selection="A"),
            Layer(name="fine", selection="TRP", sigma_A=0.6, color_by="element"),
            Layer(name="cloud", selection="B", mode="volume", sigma_A=2.5, opacity=0.7),
        ],
    ),
}


@pytest.mark.parametrize("name", sorted(GOLDEN_LAYERS))
def test_golden_layers(device: str, name: str, regen_golden: bool) -> None:
    top, pos = gramicidin()
    chains = np.asarray(top.chain_ids)
    residues = np.asarray(top.residue_names)
    sets = {
        "A": np.flatnonzero(chains == chains[0]).astype(np.int32),
        "B": np.flatnonzero(chains != chains[0]).astype(np.int32),
        "TRP": np.flatnonzero((chains != chains[0]) & (residues == "TRP")).astype(np.int32),
    }
    assert all(len(v) for v in sets.values())
    plans = _plans(GOLDEN_LAYERS[name], top.n_atoms, sets)
    cam = orbit(fit_camera(pos, W, H, margin=2.0), 35.0, 20.0)
    lr = _layered(device, top, pos, plans, cam, W, H)
    check_golden(lr.read_rgba()[..., :3], name, device, regen_golden)
    # every layer is in front somewhere (the finer one behind the cloud in the third image)
    shown = set(np.unique(lr.read_layers()).tolist())
    assert ({0, 1} if len(plans) == 2 else {0, 2}) <= shown


def test_a_cloud_stops_at_the_nearest_opaque_surface(device: str) -> None:
    """A volume march with a per-pixel limit equals the numpy compositor up to the limit (its
    last segment ends there); in a layered image the limit is the opaque layers' nearest
    depth."""
    import warp as wp

    from server.render.camera import camera_frame, image_rays
    from server.render.transfer import build_table

    n, w, h = 30, 20, 14
    top = make_topology(n)
    pos = blob(n, seed=4)
    params = RenderParams(mode="volume", sigma_A=1.3, step_sigmas=0.35, background=(0.1, 0.2, 0.3))
    cam = fit_camera(pos, w, h, margin=1.0)
    frame = camera_frame(cam, w, h)
    origins, dirs = image_rays(frame)
    full = Renderer(device)
    full.set_topology(top)
    full.set_positions(pos)
    full.render(params, cam, w, h)
    # stop each ray somewhere inside the molecule's extent along the view
    span = np.linalg.norm(pos - pos.mean(axis=0), axis=1).max()
    centre = float((pos.mean(axis=0) - frame.eye) @ frame.forward)
    rng = np.random.default_rng(0)
    limit = centre + rng.uniform(-0.6, 0.6, (h, w)) * span
    r = Renderer(device)
    r.set_topology(top)
    r.set_positions(pos)
    r.depth_limit = wp.array(limit.astype(np.float32).ravel(), dtype=float, device=device)
    r.render(params, cam, w, h)
    img = r.read_rgba().astype(np.float64) / 255.0
    assert not np.array_equal(img, full.read_rgba().astype(np.float64) / 255.0)
    lt = oracle_light(params, frame, r)
    table = build_table(params.transfer_function, params.tf_preset)
    mol = oracle_molecule(top, pos, params)
    dt = params.step_sigmas * params.sigma_A * VOLUME_STEPS  # volume's lattice
    for y in range(h):
        for x in range(w):
            jit = oracle.pixel_jitter(x, y)
            want, _d = oracle.composite(
                mol, origins[y, x], dirs[y, x], (0.0, limit[y, x]), dt, params.iso_level, table,
                lt, True, jitter=jit,
            )  # fmt: skip
            assert np.abs(img[y, x, :3] - want).max() <= 3.0 / 255.0, (x, y)


def test_a_cloud_around_a_surface_is_cut_at_it(device: str) -> None:
    n = 60
    top = make_topology(n)
    pos = blob(n, seed=8, spread=2.0)
    core = np.arange(0, 20, dtype=np.int32)
    params = RenderParams(
        sigma_A=1.0,
        layers=[
            Layer(name="core", selection="core", sigma_A=0.8),
            Layer(name="cloud", selection="all", mode="volume", sigma_A=2.0, opacity=0.9),
        ],
    )
    plans = _plans(params, n, {"core": core, "all": np.arange(n, dtype=np.int32)})
    cam = fit_camera(pos, 48, 36)
    lr = _layered(device, top, pos, plans, cam, 48, 36)
    surface = lr._children[0].renderer.read_depth()
    cloud = lr._children[1].renderer
    hit = np.isfinite(surface)
    assert hit.any() and (~hit).any()

    def cloud_alone(limit: object) -> Renderer:
        r = Renderer(device)
        r.coverage = True
        r.set_topology(top)
        r.set_positions(pos)
        r.depth_limit = limit
        r.render(plans[1].params, cam, 48, 36)
        return r

    import warp as wp

    cut = cloud_alone(wp.array(surface.ravel(), dtype=float, device=device))
    assert np.array_equal(cloud.read_rgba(), cut.read_rgba())  # the layer's cloud was cut there
    a_cut = cut.read_rgba()[..., 3].astype(int)
    a_whole = cloud_alone(None).read_rgba()[..., 3].astype(int)
    assert (a_cut[hit] <= a_whole[hit]).all() and (a_cut[hit] < a_whole[hit]).any()
    assert np.array_equal(a_cut[~hit], a_whole[~hit])  # nothing to stop at: the whole cloud


def test_gathering_a_layer_by_runs_or_by_take() -> None:
    from server.render.layers import MAX_RUNS, contiguous_runs, gather_into

    rng = np.random.default_rng(3)
    pos = rng.normal(size=(5000, 3)).astype(np.float32)
    protein_like = np.concatenate([np.arange(0, 1200), np.arange(1210, 1500), [4000]])
    scattered = np.sort(rng.choice(5000, 2000, replace=False))
    for atoms in (protein_like.astype(np.int32), scattered.astype(np.int32)):
        runs = contiguous_runs(atoms)
        out = np.empty((len(atoms), 3), np.float32)
        gather_into(pos, atoms, runs, out)
        assert np.array_equal(out, pos[atoms])
    assert contiguous_runs(protein_like.astype(np.int32)).tolist() == [  # type: ignore[union-attr]
        [0, 1200],
        [1210, 1500],
        [4000, 4001],
    ]
    assert contiguous_runs(np.arange(0, 4 * MAX_RUNS, 2, dtype=np.int32)) is None


def test_bands_of_a_layered_image_join_into_the_whole_image(device: str) -> None:
    """A one-off image is drawn in bands of rows (`server.pipeline.bands`): each band of a
    layered image (iso, a finer iso, a cloud, licorice and a tube) is that rectangle of the
    whole image, bit for bit, in colour, depth, atom and layer."""
    top, pos = gramicidin()
    chains = np.asarray(top.chain_ids)
    sets = {
        "A": np.flatnonzero(chains == chains[0]).astype(np.int32),
        "B": np.flatnonzero(chains != chains[0]).astype(np.int32),
    }
    params = RenderParams(
        sigma_A=1.6,
        layers=[
            Layer(name="surface", selection="B"),
            Layer(name="fine", selection="B", sigma_A=0.6),
            Layer(name="cloud", selection="A", mode="volume", sigma_A=2.5, opacity=0.7),
            Layer(name="sticks", selection="A", mode="licorice"),
            Layer(name="tube", selection="B", mode="tube"),
        ],
    )
    plans = _plans(params, top.n_atoms, sets)
    cam = orbit(fit_camera(pos, W, H, margin=1.2), 35.0, 20.0)
    whole = _layered(device, top, pos, plans, cam, W, H)
    want = [whole.read_rgba(), whole.read_depth(), whole.read_atom_ids(), whole.read_layers()]
    assert {0, 3} <= set(np.unique(want[3]).tolist())  # a density and a shape in front
    lr = LayeredRenderer(lambda: Renderer(device))
    y = 0
    for rows in (1, 7, H - 8):
        lr.render(plans, top, 1, pos, 1, cam, W, H, tile=(0, y, W, rows))
        got = [lr.read_rgba(), lr.read_depth(), lr.read_atom_ids(), lr.read_layers()]
        for a, b in zip(got, want, strict=True):
            assert a.shape[:2] == (rows, W)
            np.testing.assert_array_equal(a, b[y : y + rows])
        y += rows
