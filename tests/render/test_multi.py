"""Sort-first rendering across devices (server/render/multi.py): a tile casts exactly the rays
of its rectangle of the whole image, and bands gathered from several devices (several warp CPU
devices here; CUDA devices where present) equal the one-device image bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import RenderParams
from server.render import Renderer
from server.render import device as render_device
from server.render.camera import fit_camera
from server.render.multi import MultiRenderer, balance, split_rows
from tests.render.molecules import villin

PARAMS = [
    RenderParams(),
    RenderParams(mode="volume", sigma_A=2.5),
    RenderParams(scale_space="warped", sigma_A=3.0),
]


def test_bands_cover_the_image_and_balance_by_cost() -> None:
    assert split_rows(100, [0.5]) == [(0, 50), (50, 50)]
    assert split_rows(100, [0.75]) == [(0, 75), (75, 25)]
    assert split_rows(10, [0.1, 0.2, 0.9]) == [(0, 4), (4, 4), (8, 2)]  # at least a tile row
    # the top band cost 3x the bottom one: the cut moves up to where the cost halves
    cuts = balance([(0, 50), (50, 50)], [30.0, 10.0], 100, 2)
    assert cuts == [pytest.approx(20 / 30 * 0.5)]
    assert balance([(0, 50), (50, 50)], [10.0, 10.0], 100, 2) == [0.5]


@pytest.mark.parametrize("params", PARAMS, ids=["iso", "volume", "warped"])
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


def multi_devices() -> list[str]:
    """Every CUDA device when there are several; one GPU standing in for two; else two CPU
    devices."""
    n = render_device.cuda_count()
    if n >= 2:
        return [f"cuda:{i}" for i in range(n)]
    return ["cuda:0", "cuda:0"] if n == 1 else ["cpu", "cpu"]


@pytest.mark.parametrize("params", PARAMS, ids=["iso", "volume", "warped"])
def test_several_devices_render_the_one_device_image(params: RenderParams) -> None:
    mol = villin()
    cam = fit_camera(mol.positions, 128, 96)
    one = Renderer(multi_devices()[0])
    one.set_topology(mol.topology)
    one.set_positions(mol.positions)
    one.render(params, cam, 128, 96)
    multi = MultiRenderer(multi_devices())
    multi.set_topology(mol.topology)
    multi.set_positions(mol.positions)
    for _ in range(3):  # the bands move as they are balanced; the image does not
        multi.render(params, cam, 128, 96)
        assert np.array_equal(multi.read_rgba(), one.read_rgba())
        assert np.array_equal(multi.read_atom_ids(), one.read_atom_ids())
    x, y = 64, 60
    assert multi.pick(x, y) == one.pick(x, y)
    assert len(multi.device_ms) == 2
    multi.close()


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
