"""Sort-last rendering (server/render/sortlast.py): each device holds the atoms of one slab of
space and its halo, casts its rays only inside its slab, and the parts blend on the first device
into the image one device renders. Several warp CPU devices (or one CUDA device several times)
stand in for several GPUs here."""

from __future__ import annotations

import itertools
import math

import numpy as np
import numpy.typing as npt
import pytest

from protocol import Camera, Layer, RenderParams, WireArray
from server.render import Renderer, sortlast
from server.render.camera import fit_camera
from server.render.errors import RenderError
from server.render.sortlast import SortLastRenderer, chunks, split_slabs
from tests.render.molecules import Mol, topology
from tests.render.test_multi import multi_devices, villins

W, H = 120, 90
S = math.sqrt(0.5)
ALONG_X = (S, 0.0, S, 0.0)
"""The camera on the +x side looking down -x: every ray crosses every slab."""


def one_device(device: str, mol: Mol, params: RenderParams, cam: Camera) -> Renderer:
    r = Renderer(device)
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    r.render(params, cam, W, H)
    return r


def sort_last(
    device: str, parts: int, mol: Mol, params: RenderParams, cam: Camera, gather: str = "device"
) -> SortLastRenderer:
    s = SortLastRenderer([device] * parts, gather=gather)
    s.set_topology(mol.topology)
    s.set_positions(mol.positions)
    s.render(params, cam, W, H)
    return s


def assert_same_image(
    a: Renderer | SortLastRenderer, b: SortLastRenderer, levels: int, placed: float = 1.0
) -> None:
    """The colours within `levels` 8-bit levels, the same pixels hit (at least a fraction
    `placed` of the pixels one device places), their depths within 1e-3 A and the same atoms
    (as whole-system indices) under every pixel but ties."""
    ca = a.read_rgba().astype(np.int16)
    cb = b.read_rgba().astype(np.int16)
    assert int(np.abs(ca - cb).max()) <= levels
    da, db = a.read_depth(), b.read_depth()
    hit, got = np.isfinite(da), np.isfinite(db)
    assert hit.any()
    assert not (got & ~hit).any()
    assert float(got.sum()) >= placed * float(hit.sum())
    assert float(np.abs(da[got] - db[got]).max()) < 1.0e-3
    same = a.read_atom_ids() == b.read_atom_ids()
    assert float(same[got | ~hit].mean()) > 0.99


CASES = [
    pytest.param(RenderParams(), 1, id="iso"),
    pytest.param(RenderParams(mode="volume", sigma_A=2.5), 1, id="volume"),
    pytest.param(
        RenderParams(level_scale="absolute", iso_level=0.4, radius_mode="vdw"), 1, id="vdw"
    ),
    pytest.param(RenderParams(lighting={"depth_cue": 0.6}), 2, id="depth-cue"),
]


@pytest.mark.parametrize(("params", "levels"), CASES)
@pytest.mark.parametrize(("parts", "gather"), [(2, "device"), (3, "device"), (2, "host")])
def test_the_parts_blend_into_the_one_device_image(
    device: str, params: RenderParams, levels: int, parts: int, gather: str
) -> None:
    """Each part's atoms picked on the devices from the 1/N of the frame each uploads, or
    gathered on the host (the control)."""
    mol = villins(3)
    cam = fit_camera(mol.positions, W, H)
    one = one_device(device, mol, params, cam)
    s = sort_last(device, parts, mol, params, cam, gather)
    assert_same_image(one, s, levels)
    # each part holds its slab's atoms and a halo: fewer than all, together all
    held = s.atoms_held()
    assert len(held) == parts and max(held) < len(mol.positions)
    assert sum(held) >= len(mol.positions)


@pytest.mark.parametrize(("params", "levels"), CASES[:2])
def test_parts_on_distinct_devices_blend_into_the_first_devices_image(
    params: RenderParams, levels: int
) -> None:
    """One part per device (every CUDA device where there are two or more, else CPU devices
    standing in): each part's positions go to its own device and its image is blended on the
    first, which must give that device's own image."""
    devices = multi_devices()
    mol = villins(3)
    cam = fit_camera(mol.positions, W, H)
    one = one_device(devices[0], mol, params, cam)
    s = SortLastRenderer(devices)
    s.set_topology(mol.topology)
    for k in range(2):  # a second frame reuses the split on every device
        moved = mol.positions + np.float32(0.2 * k)
        one.set_positions(moved)
        one.render(params, cam, W, H)
        s.set_positions(moved)
        s.render(params, cam, W, H)
        assert_same_image(one, s, levels)
    assert [str(r.device) for r in s.renderers] == devices


@pytest.mark.parametrize("color_by", ["chain", "bfactor"])
def test_parts_colour_their_atoms_as_the_whole_system_does(device: str, color_by: str) -> None:
    """A chain's colour is its rank in the whole system and the b-factor ramp spans the whole
    system's range: a part that holds only later chains, or a narrower range, colours alike."""
    mol = villins(3)
    n = len(mol.positions)
    chains = [c for c in "ABC" for _ in range(n // 3)]
    bfactors = WireArray.from_numpy(np.linspace(5.0, 80.0, n).astype(np.float32), "<f4")
    top = mol.topology.model_copy(update={"chain_ids": chains, "bfactors": bfactors})
    coloured = Mol(top, mol.positions)
    params = RenderParams(color_by=color_by)  # type: ignore[arg-type]
    cam = fit_camera(mol.positions, W, H)
    one = one_device(device, coloured, params, cam)
    assert_same_image(one, sort_last(device, 3, coloured, params, cam), 1)


@pytest.mark.parametrize(
    "camera",
    [
        pytest.param({"orientation": ALONG_X}, id="down-the-axis"),
        pytest.param({"orientation": (S, 0.0, -S, 0.0)}, id="up-the-axis"),
        pytest.param({"orientation": ALONG_X, "projection": "orthographic"}, id="orthographic"),
        pytest.param({"orientation": ALONG_X, "inside": True}, id="inside"),
    ],
)
@pytest.mark.parametrize("mode", ["iso", "volume"])
def test_rays_that_cross_every_slab(device: str, camera: dict[str, object], mode: str) -> None:
    """Rays along the split axis pass all parts, in either order, and from inside one."""
    mol = villins(3)
    inside = bool(camera.pop("inside", False))
    cam = fit_camera(mol.positions, W, H, **camera)  # type: ignore[arg-type]
    if inside:  # the eye in the middle slab, looking down the axis
        cam = cam.model_copy(update={"distance": 8.0})
    if cam.projection == "orthographic":
        cam = cam.model_copy(update={"ortho_height": 40.0})
    params = RenderParams(mode=mode, sigma_A=2.0 if mode == "volume" else 1.5)
    one = one_device(device, mol, params, cam)
    s = sort_last(device, 3, mol, params, cam)
    # a volume blends each part's 8-bit premultiplied colour and coverage: a level of
    # rounding per part the ray crosses. It is placed where one part's own opacity reaches
    # the depth threshold: a ray that reaches it only over several parts has no depth
    volume = mode == "volume"
    assert_same_image(one, s, 4 if volume else 1, 0.9 if volume else 1.0)


def block() -> Mol:
    """A solid block of atoms 40 A long in x: its surface is the block's faces."""
    axes = [np.arange(0.0, 40.0, 1.5), np.arange(0.0, 16.0, 1.5), np.arange(0.0, 16.0, 1.5)]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return Mol(topology(["C"] * len(pos), []), pos.astype(np.float32))


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_a_camera_inside_the_surface_finds_the_way_out_in_a_part_behind(
    device: str, projection: str
) -> None:
    """The eye inside the block just before the cut, looking down the axis: every ray starts
    inside the surface and leaves it through the far face, in the second part."""
    mol = block()
    params = RenderParams(sigma_A=1.5)
    cut = split_slabs(mol.positions[:, 0], 2)[0][1]
    eye = np.array([cut - 2.0, 8.0, 8.0])
    cam = Camera(
        target=tuple(float(v) for v in eye + np.array([4.0, 0.0, 0.0])),  # type: ignore[arg-type]
        distance=4.0,
        orientation=(S, 0.0, -S, 0.0),  # the eye on the -x side, looking down +x
        projection=projection,  # type: ignore[arg-type]
        fov_deg=30.0,
        ortho_height=6.0,
    )
    one = one_device(device, mol, params, cam)
    depth = one.read_depth()
    assert np.isfinite(depth).all() and float(depth.min()) > cut - eye[0] + 5.0
    s = sort_last(device, 2, mol, params, cam)
    assert_same_image(one, s, 1)


def test_a_pick_names_the_whole_systems_atom(device: str) -> None:
    mol = villins(3)
    cam = fit_camera(mol.positions, W, H, orientation=ALONG_X)
    one = one_device(device, mol, RenderParams(), cam)
    s = sort_last(device, 3, mol, RenderParams(), cam)
    ids = one.read_atom_ids()
    ys, xs = np.nonzero(ids >= 0)
    for k in range(0, len(xs), max(len(xs) // 7, 1)):
        atom, depth = s.pick(int(xs[k]), int(ys[k]))
        assert atom == int(ids[ys[k], xs[k]])
        assert depth == pytest.approx(float(one.read_depth()[ys[k], xs[k]]), abs=1e-3)
    assert s.pick(0, 0) == (None, None)
    with pytest.raises(RenderError, match="outside"):
        s.pick(W, 0)


def moved(mol: Mol, shift: npt.NDArray[np.float32]) -> Mol:
    return Mol(mol.topology, (mol.positions + shift).astype(np.float32))


@pytest.mark.parametrize(
    ("gather", "chunk"),
    [("device", None), ("host", None), ("host", 97)],
    ids=["on-devices", "on-host", "on-host-many-ranges"],
)
def test_atoms_that_move_past_the_slack_split_the_system_again(
    device: str, gather: str, chunk: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The devices measure the move of their shares; the host gathers and checks in one range
    per part, or in many (as a large system is, on several threads)."""
    if chunk is not None:
        monkeypatch.setattr(sortlast, "GATHER_CHUNK", chunk)
    mol = villins(3)
    cam = fit_camera(mol.positions, W, H)
    params = RenderParams()
    s = sort_last(device, 3, mol, params, cam, gather)
    first = s.atoms_held()
    # a small move keeps the split; a move past the slack (one molecule along the axis) splits
    # again, and every frame is still the one-device image
    for shift, split_again in ((0.5, False), (12.0, True)):
        step = np.zeros_like(mol.positions)
        step[: len(mol.positions) // 3, 0] = shift
        now = moved(mol, step)
        before = s._split
        s.set_positions(now.positions)
        s.render(params, cam, W, H)
        assert (s._split is not before) == split_again
        assert_same_image(one_device(device, now, params, cam), s, 1)
    assert s.atoms_held() != first


def test_a_stray_atom_does_not_turn_the_cuts(device: str) -> None:
    """One atom far out along another axis: the cuts still run across the axis the atoms
    spread along, and the image is one device's."""
    mol = villins(3)
    pos = mol.positions.copy()
    pos[0] = pos.mean(axis=0) + np.float32([0.0, 300.0, 0.0])
    stray = Mol(mol.topology, pos)
    cam = fit_camera(mol.positions, W, H)
    params = RenderParams()
    s = sort_last(device, 2, stray, params, cam)
    assert s.renderers[0].region is not None and s.renderers[0].region[0] == 0
    assert_same_image(one_device(device, stray, params, cam), s, 1)


@pytest.mark.parametrize("gather", ["device", "host"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, 2.0e6])
def test_a_frame_one_device_draws_as_background_is_background_and_splits_nothing(
    device: str, bad: float, gather: str
) -> None:
    """A coordinate that is not finite or lies past MAX_COORDINATE_A (passed unchecked): the
    whole frame is background, as on one device, and the next good frame draws again."""
    mol = villins(3)
    cam = fit_camera(mol.positions, W, H)
    params = RenderParams()
    s = SortLastRenderer([device] * 2, gather=gather)
    s.set_topology(mol.topology)
    one = Renderer(device)
    one.set_topology(mol.topology)
    frame = mol.positions.copy()
    frame[7, 2] = bad
    for r in (s, one):  # the first frame of all: nothing is split from it
        r.set_positions(frame, check_finite=False)
        r.render(params, cam, W, H)
    assert not np.isfinite(s.read_depth()).any() and not np.isfinite(one.read_depth()).any()
    assert np.array_equal(s.read_rgba(), one.read_rgba())
    s.set_positions(mol.positions)
    s.render(params, cam, W, H)
    assert_same_image(one_device(device, mol, params, cam), s, 1)
    # once split: a bad coordinate along the split's axis or across it is background too,
    # and the split is kept for the next good frame
    split = s._split
    assert split is not None
    for column in (split["axis"], (split["axis"] + 1) % 3):
        frame = mol.positions.copy()
        frame[7, column] = bad
        s.set_positions(frame, check_finite=False)
        s.render(params, cam, W, H)
        assert not np.isfinite(s.read_depth()).any()
        assert np.array_equal(s.read_rgba(), one.read_rgba())
        assert s._split is split
    s.set_positions(mol.positions + np.float32(0.1))
    s.render(params, cam, W, H)
    assert np.isfinite(s.read_depth()).any()


def test_fewer_atoms_than_parts(device: str) -> None:
    mol = villins(1)
    one_atom = Mol(
        mol.topology.model_copy(
            update={
                "n_atoms": 1,
                "elements": mol.topology.elements[:1],
                "names": mol.topology.names[:1],
                "residue_names": mol.topology.residue_names[:1],
                "chain_ids": mol.topology.chain_ids[:1],
                "residue_ids": type(mol.topology.residue_ids).from_numpy(
                    mol.topology.residue_ids.to_numpy()[:1], "<i4"
                ),
                "bonds": type(mol.topology.bonds).from_numpy(np.zeros(0, np.int32), "<i4"),
            }
        ),
        mol.positions[:1],
    )
    cam = fit_camera(one_atom.positions, W, H, margin=6.0)
    params = RenderParams(level_scale="absolute", iso_level=0.2)
    one = one_device(device, one_atom, params, cam)
    assert_same_image(one, sort_last(device, 3, one_atom, params, cam), 0)


@pytest.mark.parametrize(
    ("params", "why"),
    [
        (RenderParams(scale_space="geodesic"), "geodesic density reads every atom's bonds"),
        (RenderParams(time_smoothing="classical"), "smoothing in time"),
        (RenderParams(layers=[Layer(selection="all")]), "layers"),
    ],
)
def test_what_sort_last_cannot_split_is_refused_by_name(params: RenderParams, why: str) -> None:
    mol = villins(2)
    s = SortLastRenderer(["cpu", "cpu"])
    s.set_topology(mol.topology)
    s.set_positions(mol.positions)
    with pytest.raises(RenderError, match=why):
        s.render(params, fit_camera(mol.positions, W, H), W, H)


def test_a_slab_that_overflows_its_device_is_refused_by_its_numbers() -> None:
    """A slab holds more atoms than a device may: the error says how many, the halo and the
    device's limit; where no cut can split the system (the halo reaches across it) it says
    that."""
    mol = villins(2)
    s = SortLastRenderer(["cpu", "cpu"], max_atoms=600)
    s.set_topology(mol.topology)
    s.set_positions(mol.positions)
    n = len(mol.positions)
    with pytest.raises(RenderError, match=rf"{n}-atom system holds \d+ atoms .* holds 600"):
        s.render(RenderParams(sigma_A=1.0), fit_camera(mol.positions, W, H), W, H)
    with pytest.raises(RenderError, match=r"spans [\d.]+ A .* no cut splits it .* holds 600"):
        s.render(RenderParams(sigma_A=6.0), fit_camera(mol.positions, W, H), W, H)
    with pytest.raises(RenderError, match="devices of 100 each hold fewer"):
        SortLastRenderer(["cpu", "cpu"], max_atoms=100).set_topology(mol.topology)
    # every atom at one point: no cut splits it, and the error says so
    s.set_positions(np.zeros_like(mol.positions))
    with pytest.raises(RenderError, match=r"spans 0.0 A .* no cut splits it"):
        s.render(RenderParams(), fit_camera(mol.positions, W, H), W, H)


def test_a_refusal_says_why_the_system_is_split_and_what_splits() -> None:
    s = SortLastRenderer(["cpu", "cpu"])
    with pytest.raises(RenderError, match=r"geodesic.*--device-atoms.*scale_space 'classical'"):
        s.render(RenderParams(scale_space="geodesic"), Camera(), W, H)


def test_bad_input_is_refused() -> None:
    mol = villins(2)
    s = SortLastRenderer(["cpu", "cpu"])
    with pytest.raises(RenderError, match="set_topology"):
        s.set_positions(mol.positions)
    s.set_topology(mol.topology)
    with pytest.raises(RenderError, match="no positions"):
        s.render(RenderParams(), fit_camera(mol.positions, W, H), W, H)
    with pytest.raises(RenderError, match="shape"):
        s.set_positions(mol.positions[:-1])
    bad = mol.positions.copy()
    bad[5, 1] = np.nan
    with pytest.raises(RenderError, match="first index 5"):
        s.set_positions(bad)
    s.set_positions(mol.positions)
    with pytest.raises(RenderError, match="camera distance"):
        s.render(RenderParams(), Camera(distance=1e-9).model_copy(update={"distance": -1.0}), W, H)


def test_a_system_without_atoms_draws_the_background(device: str) -> None:
    empty = Mol(topology([], []), np.zeros((0, 3), np.float32))
    cam = Camera()
    s = sort_last(device, 2, empty, RenderParams(), cam)
    one = one_device(device, empty, RenderParams(), cam)
    assert np.array_equal(s.read_rgba(), one.read_rgba())
    assert not np.isfinite(s.read_depth()).any()


def test_slabs_hold_equal_shares_and_cover_space() -> None:
    x = np.arange(100, dtype=np.float32)
    slabs = split_slabs(x, 4)
    assert slabs[0][0] == -math.inf and slabs[-1][1] == math.inf
    assert all(a[1] == b[0] for a, b in itertools.pairwise(slabs))
    counts = [int(((x >= lo) & (x < hi)).sum()) for lo, hi in slabs]
    assert counts == [25, 25, 25, 25]


def test_ranges_cover_every_atom_once() -> None:
    assert chunks(0, 4) == [(0, 0)]
    assert chunks(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunks(8, 4) == [(0, 4), (4, 8)]


def test_each_part_takes_the_whole_systems_radii() -> None:
    """A part's radii are the whole system's for its atoms, handed over, not derived again
    from the elements' names (a slow pass over tens of millions of names at large sizes)."""
    from server.render import colors

    mol = villins(2)
    cam = fit_camera(mol.positions, W, H)
    s = sort_last("cpu", 2, mol, RenderParams(radius_mode="vdw"), cam)
    whole = colors.atom_radii(mol.topology)
    assert s._split is not None
    for r, atoms in zip(s.renderers, s._split["members"], strict=True):
        assert r._topology is not None and r._topology.radii is not None
        assert np.array_equal(r._topology.radii.to_numpy(), whole[atoms])
