"""The block-cooperative iso kernels (cooperative.py) draw the per-ray kernels' image bit for bit.

On the CPU, warp runs a block of 32 threads as cooperating fibers only when
`wp.config.enable_cpu_blocks` is set; the tests run both that way (groups, shared rows, the
leader rounds all exercised) and with one thread per block."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import warp as wp

from protocol import Camera, RenderParams
from server.render.renderer import Renderer
from tests.render import molecules

CASES = {
    "classical": {},
    "warped": {"scale_space": "warped", "warp_strength": 1.0},
    "vdw_occlusion": {"radius_mode": "vdw", "lighting": {"ambient_occlusion": True}},
    "wide": {"sigma_A": 3.0},
}


@pytest.fixture
def cpu_blocks() -> Iterator[None]:
    saved = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = saved


def draw(device: str, params: RenderParams, camera: Camera, size: tuple[int, int], **kw: object):
    mol = molecules.villin()
    r = Renderer(device, **kw)  # type: ignore[arg-type]
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    r.render(params, camera, *size)
    return r.read_rgba(), r.read_depth(), r.read_atom_ids()


def assert_same_images(device: str, params: RenderParams) -> None:
    centre = molecules.villin().positions.mean(axis=0)
    # near: a tile's rays look at one neighbourhood; far: 40x30 pixels over the whole box,
    # where neighbouring rays hit far apart and the block splits into several groups
    for distance, size in ((60.0, (96, 64)), (220.0, (40, 30))):
        camera = Camera(target=tuple(float(v) for v in centre), distance=distance)
        ref = draw(device, params, camera, size, march_budget=0)
        hits = int(np.isfinite(ref[1]).sum())
        assert hits > 10, "the view must show the molecule"
        for margin in (0.0, 4.0, 60.0):
            got = draw(device, params, camera, size, cooperative=True, coop_margin_steps=margin)
            np.testing.assert_array_equal(got[0], ref[0], err_msg=f"rgba, margin {margin}")
            np.testing.assert_array_equal(got[1], ref[1], err_msg=f"depth, margin {margin}")
            np.testing.assert_array_equal(got[2], ref[2], err_msg=f"atom ids, margin {margin}")


@pytest.mark.parametrize("case", sorted(CASES))
def test_cooperative_iso_draws_the_per_ray_image(device: str, cpu_blocks: None, case: str) -> None:
    assert_same_images(device, RenderParams.model_validate(CASES[case]))


def test_one_thread_blocks_draw_the_same_image() -> None:
    """Without CPU blocks each thread is its own block: the walks degenerate to per-ray ones."""
    assert not wp.config.enable_cpu_blocks
    assert_same_images("cpu", RenderParams())
