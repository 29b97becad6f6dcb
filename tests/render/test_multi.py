"""Sort-first rendering across devices (server/render/multi.py): a tile casts exactly the rays
of its rectangle of the whole image, and bands gathered from several devices (several warp CPU
devices here; CUDA devices where present) equal the one-device image bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import RenderParams, WireArray
from server.render import Renderer
from server.render import device as render_device
from server.render.camera import band_planes, camera_frame, fit_camera
from server.render.multi import MultiRenderer, balance, split_rows
from server.render.reach import reach_sigmas
from tests.render.molecules import Mol, villin

PARAMS = [
    RenderParams(),
    RenderParams(mode="volume", sigma_A=2.5),
    RenderParams(scale_space="carved", sigma_A=3.0),
    RenderParams(level_scale="absolute", iso_level=0.4, radius_mode="vdw"),
    RenderParams(scale_space="geodesic", sigma_A=1.2),
]
IDS = ["iso", "volume", "carved", "absolute-vdw", "geodesic"]


def test_bands_cover_the_image_and_balance_by_cost() -> None:
    # edges on whole row quanta (a balanced frame set-up repeats: graphs replay)
    assert split_rows(100, [0.5]) == [(0, 48), (48, 52)]
    assert split_rows(100, [0.75]) == [(0, 72), (72, 28)]
    assert split_rows(1080, [0.25, 0.5, 0.7]) == [(0, 272), (272, 272), (544, 208), (752, 328)]
    assert split_rows(10, [0.1, 0.2, 0.9]) == [(0, 4), (4, 4), (8, 2)]  # at least a tile row
    # the top band cost 3x the bottom one: the cut moves up to where the cost halves
    cuts = balance([(0, 50), (50, 50)], [30.0, 10.0], 100, 2)
    assert cuts == [pytest.approx(20 / 30 * 0.5)]
    assert balance([(0, 50), (50, 50)], [10.0, 10.0], 100, 2) == [0.5]


@pytest.mark.parametrize("params", PARAMS[:3], ids=IDS[:3])
def test_a_tile_is_its_rectangle_of_the_whole_image(device: str, params: RenderParams) -> None:
    mol = villin()
    cam = fit_camera(mol.positions, 120, 90)
    r = Renderer(device)
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    r.render(params, cam, 120, 90)
    whole = (r.read_rgba(), r.read_depth(), r.read_atom_ids())
    r.render(params, cam, 120, 90, tile=(30, 37, 61, 29))
    tile = (r.read_rgba(), r.read_depth(), r.read_atom_ids())
    for a, b in zip(whole, tile, strict=True):
        assert np.array_equal(a[37:66, 30:91], b)
    with pytest.raises(ValueError, match="not inside"):
        r.render(params, cam, 120, 90, tile=(100, 0, 30, 10))


def villins(copies: int) -> Mol:
    """`copies` villins side by side along x (a system wider than any one band's reach)."""
    one = villin()
    n = len(one.positions)
    pos = np.concatenate([one.positions + np.float32([32.0 * i, 0.0, 0.0]) for i in range(copies)])
    top = one.topology
    bonds = top.bonds.to_numpy().reshape(-1, 2)
    topology = top.model_copy(
        update={
            "n_atoms": n * copies,
            "elements": top.elements * copies,
            "names": top.names * copies,
            "residue_names": top.residue_names * copies,
            "chain_ids": top.chain_ids * copies,
            "residue_ids": WireArray.from_numpy(
                np.tile(top.residue_ids.to_numpy(), copies).astype(np.int32), "<i4"
            ),
            "bonds": WireArray.from_numpy(
                np.concatenate([bonds + n * i for i in range(copies)]).astype(np.int32), "<i4"
            ),
        }
    )
    return Mol(topology, pos.astype(np.float32))


@pytest.mark.parametrize(
    "params",
    [RenderParams(level_scale="absolute", iso_level=0.3), RenderParams(sigma_A=0.9)],
    ids=["absolute", "relative"],
)
def test_a_band_grid_holds_the_atoms_its_rays_reach(device: str, params: RenderParams) -> None:
    """A culled band keeps every atom within reach of its rays (and, for relative levels, of the
    atoms the mean density is taken at), fewer than all, and draws the whole image's rows."""
    mol = villins(4)
    w, h = 64, 96  # the system lies across the bands
    turn = (0.7071068, 0.0, 0.0, 0.7071068)  # the row of villins runs down the image
    cam = fit_camera(mol.positions, w, h, orientation=turn)
    whole = Renderer(device)
    whole.set_topology(mol.topology)
    whole.set_positions(mol.positions)
    whole.render(params, cam, w, h)
    image = whole.read_rgba()
    band = Renderer(device)
    band.cull_to_tile = True
    band.set_topology(mol.topology)
    band.set_positions(mol.positions)
    frame = camera_frame(cam, w, h)
    n = len(mol.positions)
    reach = reach_sigmas(params.sigma_A, params.cutoff_sigmas) * params.sigma_A
    kept_counts = []
    for y0 in range(0, h, 24):
        band.render(params, cam, w, h, tile=(0, y0, w, 24))
        assert np.array_equal(band.read_rgba(), image[y0 : y0 + 24])
        grid = band._grid
        kept = int(grid.cell_start.numpy()[grid.capacity])
        ids = set(grid.order.numpy()[:kept].tolist())
        top, bottom = band_planes(frame, y0, y0 + 24)
        p = mol.positions.astype(np.float64)
        near = (p @ top[:3] + top[3] >= -reach) & (p @ bottom[:3] + bottom[3] >= -reach)
        assert set(np.nonzero(near)[0].tolist()) <= ids
        kept_counts.append(kept)
    if params.level_scale == "absolute":
        assert max(kept_counts) < n and min(kept_counts) < n // 2


def multi_devices() -> list[str]:
    """Every CUDA device when there are several; one GPU standing in for two; else two CPU
    devices."""
    n = render_device.cuda_count()
    if n >= 2:
        return [f"cuda:{i}" for i in range(n)]
    return ["cuda:0", "cuda:0"] if n == 1 else ["cpu", "cpu"]


@pytest.mark.parametrize("params", PARAMS, ids=IDS)
@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
@pytest.mark.parametrize("upload", ["split", "whole"])
def test_several_devices_render_the_one_device_image(
    params: RenderParams, projection: str, upload: str
) -> None:
    """Bit-equal to one device, whether each device uploads 1/N of every frame and takes the
    rest from the others or uploads all of it."""
    mol = villins(2)
    cam = fit_camera(mol.positions, 128, 96, projection)  # type: ignore[arg-type]
    one = Renderer(multi_devices()[0])
    one.set_topology(mol.topology)
    one.set_positions(mol.positions)
    one.render(params, cam, 128, 96)
    multi = MultiRenderer(multi_devices(), upload=upload)
    assert multi.split_upload == (upload == "split")
    multi.set_topology(mol.topology)
    moved = [mol.positions + np.float32(0.3 * k) for k in range(3)]
    for k in range(3):  # the bands move as they are balanced; the image does not
        for r in (one, multi):
            r.set_positions(moved[k])
            r.render(params, cam, 128, 96)
        assert np.array_equal(multi.read_rgba(), one.read_rgba())
        assert np.array_equal(multi.read_atom_ids(), one.read_atom_ids())
    x, y = 64, 60
    assert multi.pick(x, y) == one.pick(x, y)
    assert len(multi.device_ms) == len(multi_devices())
    assert len(multi.issue_ms) == len(multi_devices())
    multi.close()


def test_a_frame_uploaded_in_part_renders_only_once_whole() -> None:
    """`set_positions(part=...)` copies a slice from the host; rendering before `receive` has
    brought the rest is refused, and so is receiving from a renderer that holds no part."""
    mol = villin()
    cam = fit_camera(mol.positions, 32, 24)
    n = len(mol.positions)
    a, b = Renderer("cpu"), Renderer("cpu")
    for r in (a, b):
        r.set_topology(mol.topology)
    a.set_positions(mol.positions, part=(0, n // 2))
    with pytest.raises(ValueError, match="receive the rest"):
        a.render(RenderParams(), cam, 32, 24)
    with pytest.raises(ValueError, match="holds no part"):
        a.receive([(b, n // 2, n)])
    b.set_positions(mol.positions, part=(n // 2, n))
    a.set_positions(mol.positions, part=(0, n // 2))
    a.receive([(b, n // 2, n)])
    a.render(RenderParams(), cam, 32, 24)
    whole = Renderer("cpu")
    whole.set_topology(mol.topology)
    whole.set_positions(mol.positions)
    whole.render(RenderParams(), cam, 32, 24)
    assert np.array_equal(a.read_rgba(), whole.read_rgba())


def test_a_failing_device_is_dropped_and_the_others_render(
    caplog: pytest.LogCaptureFixture,
) -> None:
    mol = villin()
    cam = fit_camera(mol.positions, 64, 48)
    multi = MultiRenderer(["cpu", "cpu"])
    multi.set_topology(mol.topology)
    multi.set_positions(mol.positions)

    def broken(*args: object, **kwargs: object) -> None:
        raise MemoryError("device lost")

    multi.renderers[1].render = broken  # type: ignore[method-assign]
    multi.render(RenderParams(), cam, 64, 48)
    assert len(multi.renderers) == 1 and "going on without it" in caplog.text
    one = Renderer("cpu")
    one.set_topology(mol.topology)
    one.set_positions(mol.positions)
    one.render(RenderParams(), cam, 64, 48)
    assert np.array_equal(multi.read_rgba(), one.read_rgba())
    multi.close()


def test_an_image_reads_into_the_callers_array() -> None:
    """`read_rgba_into`: the same pixels as `read_rgba`, into an array the caller keeps (from
    CUDA devices one copy into it); a wrong array is refused with its expected shape."""
    mol = villin()
    cam = fit_camera(mol.positions, 40, 30)
    for r in (Renderer(multi_devices()[0]), MultiRenderer(multi_devices())):
        r.set_topology(mol.topology)
        r.set_positions(mol.positions)
        r.render(RenderParams(), cam, 40, 30)
        out = np.zeros((30, 40, 4), np.uint8)
        r.read_rgba_into(out)
        assert np.array_equal(out, r.read_rgba()) and out.any()
        with pytest.raises(ValueError, match=r"\(30, 40, 4\) uint8"):
            r.read_rgba_into(np.zeros((40, 30, 4), np.uint8))
