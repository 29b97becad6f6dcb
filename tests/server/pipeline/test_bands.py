"""How a one-off image is cut into bands, and when its bands refuse the rest
(`server.pipeline.bands`): the weights the molecule's footprint gives each pixel, and the
arithmetic on the times the bands report (a cost per pixel stands in for the device)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from protocol import Camera, RenderParams
from server.pipeline import bands
from server.pipeline.bands import (
    BLOCK,
    BandPlan,
    TooCostlyError,
    advice_for,
    footprint,
    reach_of,
)
from server.render.camera import camera_frame, image_rays
from server.render.errors import CapacityError
from server.render.layerplan import LayerPlan

Cost = Callable[[int, int, int, int], float]


def per_pixel(costs: np.ndarray) -> Cost:
    """A device whose pixel (x, y) takes costs[y, x] seconds."""
    table = np.zeros((costs.shape[0] + 1, costs.shape[1] + 1))
    table[1:, 1:] = costs.cumsum(axis=0).cumsum(axis=1)

    def cost(x0: int, y0: int, w: int, h: int) -> float:
        return float(table[y0 + h, x0 + w] - table[y0, x0 + w] - table[y0 + h, x0] + table[y0, x0])

    return cost


def draw(
    plan: BandPlan,
    cost: Cost,
    first_extra: float = 0.0,
    per_band: float = 0.0,
    apart: bool = True,
) -> list[tuple[tuple, float]]:
    """Every band drawn, with its seconds: its work (the ray cast, `cost`, told apart when
    `apart`) and `per_band` more whatever it draws; checks that each pixel is drawn once."""
    seen = np.zeros((plan.height, plan.width), dtype=np.int32)
    tile: tuple[int, int, int, int] | None = plan.first()
    out = []
    while tile is not None:
        x0, y0, w, h = tile
        seen[y0 : y0 + h, x0 : x0 + w] += 1
        work = cost(*tile) + (first_extra if not out else 0.0)
        out.append((tile, work + per_band))
        tile = plan.drawn(tile, work + per_band, work if apart else None)
    assert (seen == 1).all()
    return out


def blocks_for(costs: np.ndarray) -> np.ndarray:
    """Block weights that follow `costs` exactly."""
    h, w = costs.shape
    padded = np.zeros((-(-h // BLOCK) * BLOCK, -(-w // BLOCK) * BLOCK))
    padded[:h, :w] = costs
    return padded.reshape(padded.shape[0] // BLOCK, BLOCK, -1, BLOCK).sum(axis=(1, 3))


def test_the_footprint_puts_each_atom_where_its_ray_is() -> None:
    """An atom on the ray of pixel (x, y) weighs on that pixel's block and its reach around."""
    cam = Camera(target=(0.0, 0.0, 0.0), distance=60.0)
    frame = camera_frame(cam, 320, 240)
    origins, dirs = image_rays(frame)
    atoms = np.array([origins[200, 40] + 55.0 * dirs[200, 40]], dtype=np.float32)
    blocks = footprint(atoms, frame, reach=0.0)
    assert blocks.shape == (30, 40) and blocks.sum() == 1.0
    assert blocks[200 // BLOCK, 40 // BLOCK] == 1.0
    wide = footprint(atoms, frame, reach=6.0)  # 5 blocks around it at 55 A, cut at the edge
    assert wide[200 // BLOCK, 40 // BLOCK] == 1.0 and wide.sum() == 10 * 11
    behind = np.array([frame.eye - 10.0 * frame.forward], dtype=np.float32)
    assert footprint(behind, frame, reach=6.0).sum() == 0.0


def test_bands_of_an_even_image_take_a_tenth_of_a_second_each() -> None:
    costs = np.full((1080, 1920), 1e-6)  # 2.07 s in all
    plan = BandPlan(1920, 1080, limit_s=60.0, blocks=blocks_for(costs))
    got = draw(plan, per_pixel(costs))
    assert got[0][0] == (0, 0, 507, 1)  # 1/4096 of the cover: part of the first row
    later = [s for _tile, s in got[1:-1]]
    assert max(later) <= 0.1 + 2e-3 and np.median(later) >= 0.09
    assert plan.spent_s == pytest.approx(2.0736 - 507 * 1e-6)


def test_empty_rows_above_the_molecule_do_not_lead_into_one_long_band() -> None:
    """Sized by rows, a band of empty rows was followed by one of 170 s: the molecule's rows
    weigh more before they are drawn."""
    costs = np.full((1080, 1920), 1e-8)
    costs[600:] = 2e-4  # the molecule in the bottom rows: 186 s
    plan = BandPlan(1920, 1080, limit_s=1000.0, blocks=blocks_for(costs))
    got = draw(plan, per_pixel(costs))
    assert max(s for _tile, s in got[1:]) <= 0.13  # an empty pixel weighs 1e-3 of the densest
    assert any(w < 1920 for (_x, _y, w, _h), _s in got)  # a row weighs more than a band


def test_a_cheap_image_takes_few_bands() -> None:
    costs = np.full((500, 500), 1e-9)
    got = draw(BandPlan(500, 500, limit_s=60.0, blocks=blocks_for(costs)), per_pixel(costs))
    assert len(got) <= 6


def test_a_band_slowed_by_compiling_is_not_counted_and_only_shrinks_the_next() -> None:
    costs = np.full((480, 640), 1e-6)
    plan = BandPlan(640, 480, limit_s=1.0, blocks=blocks_for(costs))
    got = draw(plan, per_pixel(costs), first_extra=30.0)
    first = got[0][0]
    assert first[3] == 1 and got[1][0][3] == 1 and got[1][0][2] < 640  # parts of the row
    assert plan.spent_s == pytest.approx((480 * 640 - first[2]) * 1e-6)


def test_an_image_past_the_limit_is_refused_once_its_bands_took_half_a_second() -> None:
    costs = np.full((1080, 1920), 1.3e-4)  # about 270 s
    plan = BandPlan(1920, 1080, 60.0, blocks_for(costs), advice_for(RenderParams()))
    with pytest.raises(TooCostlyError) as err:
        draw(plan, per_pixel(costs))
    assert isinstance(err.value, CapacityError)
    assert 0.5 <= plan.spent_s < 0.7
    text = str(err.value)
    assert "1920x1080" in text and "about 270 s" in text and "limit of 60 s" in text
    assert "one_off_render_seconds" in text and "a smaller sigma" in text


def test_a_molecule_in_the_top_third_is_drawn_within_the_limit() -> None:
    """Measured on its first (dense) rows, the rest at that rate made a 29 s image look like
    69 s: the rows left are weighed by what covers them."""
    costs = np.full((1080, 1920), 1e-9)
    costs[:360] = 4e-5  # 27.6 s
    plan = BandPlan(1920, 1080, limit_s=60.0, blocks=blocks_for(costs))
    got = draw(plan, per_pixel(costs))
    assert sum(s for _t, s in got) == pytest.approx(costs.sum())


def test_weights_that_miss_a_costly_part_still_refuse_it_in_time() -> None:
    """Past the limit in time alone it is refused, whatever the weights say is left."""
    costs = np.full((400, 400), 1e-3)  # 160 s, where the weights see an even, empty image
    plan = BandPlan(400, 400, limit_s=5.0)
    with pytest.raises(TooCostlyError):
        draw(plan, per_pixel(costs))
    assert plan.spent_s <= 5.0 + 0.5


def molecule_costs(width: int, height: int, seconds: float) -> np.ndarray:
    """An image whose pixels cost like a molecule's: a bump of cover in its middle, empty
    corners, `seconds` in all."""
    y, x = np.mgrid[0:height, 0:width]
    r2 = ((x - width / 2) / (0.3 * width)) ** 2 + ((y - height / 2) / (0.3 * height)) ** 2
    costs = np.exp(-r2)
    return costs * (seconds / costs.sum())


def test_a_bands_fixed_cost_is_not_taken_for_work() -> None:
    """On two busy CPU cores each band of a small image took some 45 ms whatever it drew; taken
    for work, the first bands' few rows made a 320x240 image of a second or so look like 139 s,
    and it was refused. With the work told apart, it is drawn in a few bands, and judged
    against a limit just above its whole time it still passes."""
    costs = molecule_costs(320, 240, 0.6)
    for limit in (60.0, 1.5):
        plan = BandPlan(320, 240, limit_s=limit, blocks=blocks_for(costs))
        got = draw(plan, per_pixel(costs), first_extra=0.5, per_band=0.045)
        assert len(got) <= 12 and plan.spent_s < 1.2
        assert plan.c == pytest.approx(0.045)
    taken_for_work = BandPlan(320, 240, limit_s=60.0, blocks=blocks_for(costs))
    with pytest.raises(TooCostlyError):  # the control: every second taken for work
        draw(taken_for_work, per_pixel(costs), 0.5, 0.045, apart=False)


def test_an_image_past_the_limit_with_fixed_costs_is_still_refused() -> None:
    """The fixed cost taken out of the rates is counted again for each band left."""
    costs = molecule_costs(1920, 1080, 270.0)
    plan = BandPlan(1920, 1080, 60.0, blocks_for(costs), advice_for(RenderParams()))
    with pytest.raises(TooCostlyError) as err:
        draw(plan, per_pixel(costs), per_band=0.045)
    assert plan.spent_s < 1.0
    estimate = float(str(err.value).split("about ")[1].split(" s")[0].replace(",", ""))
    assert 270.0 <= estimate <= 270.0 * 1.6  # its work, and 0.045 s a band of 0.1 s of it
    # rows of 0.06 s of work go one to a band, not 0.6: 1,080 bands of 0.105 s are 113 s
    rows = np.full((1080, 1920), 0.06 / 1920)
    by_rows = BandPlan(1920, 1080, limit_s=100.0, blocks=blocks_for(rows))
    with pytest.raises(TooCostlyError):
        draw(by_rows, per_pixel(rows), per_band=0.045)
    assert by_rows.spent_s < 2.0
    even = np.full((400, 400), 2.0 / 400**2)  # 2 s of work in bands of 0.1 s, 1 s more each
    fixed = BandPlan(400, 400, limit_s=5.0, blocks=blocks_for(even))
    with pytest.raises(TooCostlyError):
        draw(fixed, per_pixel(even), per_band=1.0)
    assert fixed.spent_s < 2.5


def test_one_costly_row_is_drawn_in_parts_of_it() -> None:
    costs = np.full((1, 4096), 0.03)  # 123 s in one row
    plan = BandPlan(4096, 1, limit_s=1000.0, blocks=blocks_for(costs))
    got = draw(plan, per_pixel(costs))
    assert max(s for _t, s in got[1:]) <= 0.5  # 16 pixels at least a band


def test_what_a_refusal_suggests_and_how_far_a_layer_reaches() -> None:
    assert "classical density" in advice_for(RenderParams(scale_space="geodesic"))
    assert "lower quality" in advice_for(RenderParams(mode="volume"))
    assert "classical" not in advice_for(RenderParams())
    params = RenderParams(sigma_A=1.5)
    assert reach_of(params) == 1.5 * params.cutoff_sigmas
    wide = RenderParams(sigma_A=3.0, cutoff_sigmas=3.0)
    plans = [LayerPlan("a", None, params), LayerPlan("b", None, wide)]
    assert reach_of(params, plans) == 9.0  # the widest layer drawn


def test_the_constants_say_what_the_docs_say() -> None:
    assert bands.FIRST_SHARE == 1 / 4096 and bands.BAND_SECONDS == 0.1


def test_a_large_system_is_weighed_from_every_kth_atom(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    atoms = (rng.normal(size=(200_000, 3)) * [30.0, 10.0, 10.0]).astype(np.float32)
    frame = camera_frame(Camera(target=(0.0, 0.0, 0.0), distance=150.0), 640, 360)
    some = footprint(atoms, frame, reach=4.0)
    monkeypatch.setattr(bands, "WEIGHED_ATOMS", 1 << 30)
    every = footprint(atoms, frame, reach=4.0)
    assert some.sum() == pytest.approx(every.sum(), rel=0.01)
    assert np.corrcoef(some.ravel(), every.ravel())[0, 1] > 0.99


def test_a_camera_that_magnifies_an_atom_past_the_image_weighs_no_more_than_the_image() -> None:
    """A tiny ortho_height asked `footprint` for a box of 110 GiB."""
    frame = camera_frame(
        Camera(projection="orthographic", ortho_height=0.01, distance=100.0), 1920, 1080
    )
    atoms = np.zeros((3000, 3), dtype=np.float32)
    blocks = footprint(atoms, frame, reach=4.5)
    assert blocks.shape == (135, 240) and (blocks == 3000).all()


def test_only_the_atoms_a_visible_layer_draws_are_weighed(monkeypatch: pytest.MonkeyPatch) -> None:
    """Hidden solvent's even cover set the rate while the bands crossed it, and a band over
    the protein then took 8.4 s: hidden atoms weigh nothing."""
    import asyncio

    from server.pipeline import gpu as gpu_module
    from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
    from server.render.camera import fit_camera
    from tests.render.conftest import blob, make_topology

    weighed: list[int] = []
    real = gpu_module.footprint

    def spy(positions: np.ndarray, frame: object, reach: float) -> np.ndarray:
        weighed.append(len(positions))
        return real(positions, frame, reach)

    monkeypatch.setattr(gpu_module, "footprint", spy)
    top, pos = make_topology(200), blob(200, seed=2)
    protein = RenderParams(sigma_A=1.2)
    plans = (LayerPlan("protein", np.arange(10, dtype=np.int32), protein),)
    cam = fit_camera(pos, 32, 24)
    request = RenderRequest("rest:weighed", Snapshot(top, pos), protein, cam, 32, 24, layers=plans)
    queue = GpuQueue(device="cpu")
    try:
        out = asyncio.run(queue.render_bands(request, 60.0))
    finally:
        queue.close()
    assert weighed == [10] and out.image().shape == (24, 32, 4)
