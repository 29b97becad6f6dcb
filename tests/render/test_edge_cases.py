"""Degenerate inputs render sensibly; invalid ones raise RenderError before any launch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from protocol import Camera, RenderParams
from server.render import Renderer, RenderError
from server.render.camera import fit_camera
from tests.render.conftest import blob, make_topology
from tests.render.helpers import render

BG = (0.2, 0.4, 0.6)


def _bg_rgba() -> np.ndarray:
    return np.array([round(c * 255) for c in BG] + [255], dtype=np.uint8)


def test_zero_atoms_gives_background(device: str) -> None:
    r = Renderer(device)
    r.set_topology(make_topology(0))
    r.set_positions(np.zeros((0, 3), np.float32))
    r.render(RenderParams(background=BG), Camera(), 24, 16)
    img = r.read_rgba()
    assert img.shape == (16, 24, 4)
    assert np.all(img == _bg_rgba())
    assert np.all(np.isinf(r.read_depth()))
    assert np.all(r.read_atom_ids() == -1)
    assert r.pick(3, 3) == (None, None)
    counts, edges = r.density_histogram(16)
    assert counts.sum() == 0 and len(edges) == 17


def test_a_frame_of_no_atoms_is_timed_and_the_next_renderer_draws(device: str) -> None:
    """A frame of no atoms uploads nothing, so it times no upload: on CUDA the elapsed time
    between upload events that were never recorded failed (the frame's total read 0 ms) and
    left its error pending for the next CUDA call that checks, which then failed in its
    place (the grid's scan of the next renderer)."""
    r = Renderer(device)
    r.set_topology(make_topology(0))
    r.set_positions(np.zeros((0, 3), np.float32))
    r.render(RenderParams(background=BG), Camera(), 24, 16)
    t = r.timings
    assert t["upload"] == 0.0
    assert t["total"] >= t["raycast"] > 0.0
    one = Renderer(device)
    one.set_topology(make_topology(1))
    one.set_positions(np.array([[3.0, -1.0, 2.0]], np.float32))
    one.render(RenderParams(background=BG), Camera(target=(3.0, -1.0, 2.0), distance=30.0), 9, 9)
    assert np.isfinite(one.read_depth()[4, 4])


def test_no_topology_gives_background(device: str) -> None:
    r = Renderer(device)
    r.render(RenderParams(mode="volume", background=BG), Camera(), 5, 7)
    assert np.all(r.read_rgba() == _bg_rgba())


@pytest.mark.parametrize("count", [1, 25])
@pytest.mark.parametrize("scale", ["absolute", "mean"])
def test_atoms_at_one_point_make_a_sphere(device: str, count: int, scale: str) -> None:
    """n coincident atoms: S = n exp(-r^2 / 2 s^2), a sphere of radius s sqrt(2 ln(n / iso))
    with absolute levels; relative ones divide S by its value at the atoms (n), so the sphere
    has radius s sqrt(2 ln(1 / iso)) however many atoms coincide."""
    top = make_topology(count)
    pos = np.tile(np.array([[3.0, -1.0, 2.0]], np.float32), (count, 1))
    params = RenderParams(sigma_A=1.5, iso_level=0.5, level_scale=scale)  # type: ignore[arg-type]
    cam = Camera(target=(3.0, -1.0, 2.0), distance=30.0, fov_deg=30.0)
    r = render(device, top, pos, params, cam, 41, 41)
    peak = count if scale == "absolute" else 1
    radius = 1.5 * math.sqrt(2 * math.log(peak / 0.5))
    assert r.read_depth()[20, 20] == pytest.approx(30.0 - radius, abs=2e-3)
    ids = r.read_atom_ids()
    assert np.all(ids[np.isfinite(r.read_depth())] == 0)
    # silhouette: the sphere's angular radius asin(R / D) against the vertical fov
    hit_rows = np.isfinite(r.read_depth()[:, 20]).sum()
    expected = 41 * math.tan(math.asin(radius / 30.0)) / math.tan(math.radians(15.0))
    assert abs(hit_rows - expected) <= 2


def test_huge_and_tiny_sigma_render(device: str) -> None:
    top = make_topology(30)
    pos = blob(30, seed=5)
    cam = fit_camera(pos, 32, 24)
    absolute = {"iso_level": 0.5, "level_scale": "absolute"}
    huge = render(device, top, pos, RenderParams(sigma_A=50.0, **absolute), cam, 32, 24)  # type: ignore[arg-type]
    d = huge.read_depth()
    # the camera sits inside one fat cloud of radius ~ 50 sqrt(2 ln 60) = 143 A: its far wall
    assert np.isfinite(d).mean() > 0.9 and np.nanmin(np.where(np.isfinite(d), d, np.nan)) > 100
    tiny = render(device, top, pos, RenderParams(sigma_A=0.05, **absolute), cam, 32, 24)  # type: ignore[arg-type]
    d = tiny.read_depth()
    # tiny spheres of radius ~0.06 A are mostly missed by the rays, never garbage
    assert np.all(np.isinf(d) | (d > 0))
    for mode in ("iso", "volume"):
        p = RenderParams(mode=mode, sigma_A=0.05)  # type: ignore[arg-type]
        assert render(device, top, pos, p, cam, 8, 6).read_rgba().shape == (6, 8, 4)


@pytest.mark.parametrize(("w", "h"), [(1, 1), (37, 11), (11, 37), (9, 1)])
def test_odd_image_shapes(device: str, w: int, h: int) -> None:
    top = make_topology(20)
    pos = blob(20, seed=6)
    params = RenderParams()
    cam = fit_camera(pos, w, h, margin=-3.0)
    r = render(device, top, pos, params, cam, w, h)
    assert r.read_rgba().shape == (h, w, 4)
    assert r.read_depth().shape == (h, w)
    assert r.read_atom_ids().shape == (h, w)
    # the same pixels rendered inside a larger buffer agree with a fresh renderer
    r.render(params, fit_camera(pos, 64, 64), 64, 64)
    r.render(params, cam, w, h)
    again = render(device, top, pos, params, cam, w, h)
    np.testing.assert_array_equal(r.read_rgba(), again.read_rgba())


def _renderer(device: str, n: int = 10) -> Renderer:
    r = Renderer(device, max_atoms=1000, max_pixels=10_000)
    r.set_topology(make_topology(n))
    r.set_positions(blob(n, seed=1))
    return r


@pytest.fixture
def no_launch(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any kernel launch (or sort/scan) fails loudly: errors must come first."""

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("a kernel was launched")

    monkeypatch.setattr(wp, "launch", boom)
    monkeypatch.setattr(wp.utils, "radix_sort_pairs", boom)
    monkeypatch.setattr(wp.utils, "array_scan", boom)


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.array([[0.0, np.nan, 0.0]] * 10, np.float32), "NaN or Inf"),
        (np.array([[0.0, 0.0, np.inf]] * 10, np.float32), "NaN or Inf"),
        (np.zeros((9, 3), np.float32), "9 atoms"),
        (np.zeros((10, 2), np.float32), "shape"),
        (np.array([["a", "b", "c"]] * 10), "real numbers"),
    ],
)
def test_invalid_positions(device: str, bad: np.ndarray, match: str, no_launch: None) -> None:
    r = Renderer(device, max_atoms=1000)
    r.set_topology(make_topology(10))
    with pytest.raises(RenderError, match=match):
        r.set_positions(bad)


@pytest.mark.parametrize(
    ("params", "size", "match"),
    [
        (RenderParams.model_construct(sigma_A=0.0), (8, 8), "sigma_A"),
        (RenderParams.model_construct(sigma_A=-1.0), (8, 8), "sigma_A"),
        (RenderParams.model_construct(iso_level=float("nan")), (8, 8), "iso_level"),
        (RenderParams.model_construct(step_sigmas=0.0), (8, 8), "step_sigmas"),
        # the protocol's range, from the same constants: a Gaussian reaches at most 6 sigma
        (RenderParams.model_construct(cutoff_sigmas=8.0), (8, 8), r"cutoff_sigmas .* 1\.\.6"),
        (RenderParams.model_construct(cutoff_sigmas=0.5), (8, 8), r"cutoff_sigmas .* 1\.\.6"),
        (RenderParams(), (0, 8), "at least 1x1"),
        (RenderParams(), (8, 0), "at least 1x1"),
        (RenderParams(), (200, 200), "limit"),
        (RenderParams(), (20000, 1), "limit"),
        (RenderParams(), (8.5, 8), "integers"),
    ],
)
def test_invalid_render_input(
    device: str, params: RenderParams, size: tuple[int, int], match: str
) -> None:
    r = _renderer(device)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(wp, "launch", lambda *a, **k: (_ for _ in ()).throw(AssertionError("launched")))
        with pytest.raises(RenderError, match=match):
            r.render(params, Camera(), *size)


def test_unchecked_non_finite_positions_draw_background(device: str) -> None:
    top = make_topology(12)
    pos = blob(12, seed=3)
    cam = fit_camera(pos, 16, 12)
    r = render(device, top, pos, RenderParams(background=BG), cam, 16, 12)
    assert np.isfinite(r.read_depth()).any()
    # 1e30 A: a step along a ray no longer moved it, and the render thread was held for good
    for bad in (np.nan, np.inf, -np.inf, 1e30, -2e6):
        broken = pos.copy()
        broken[5, 1] = bad
        r.set_positions(broken, check_finite=False)
        r.render(RenderParams(background=BG), cam, 16, 12)
        assert np.all(r.read_rgba() == _bg_rgba())
        r.set_positions(pos)
        r.render(RenderParams(background=BG), cam, 16, 12)
        assert np.isfinite(r.read_depth()).any()


def test_other_invalid_calls(device: str) -> None:
    r = Renderer(device, max_atoms=5)
    with pytest.raises(RenderError, match="set_topology"):
        r.set_positions(np.zeros((1, 3)))
    with pytest.raises(RenderError, match="allows 5"):
        r.set_topology(make_topology(6))
    r.set_topology(make_topology(3))
    with pytest.raises(RenderError, match="no positions"):
        r.render(RenderParams(), Camera(), 4, 4)
    with pytest.raises(RenderError, match="nothing rendered"):
        r.read_rgba()
    r.set_positions(np.zeros((3, 3)))
    r.render(RenderParams(), Camera(), 4, 4)
    with pytest.raises(RenderError, match="outside"):
        r.pick(4, 0)
    with pytest.raises(RenderError, match="bins"):
        r.density_histogram(0)
    with pytest.raises(RenderError, match="device"):
        Renderer("no-such-device")
    bad_cam = Camera.model_construct(
        target=(0.0, 0.0, 0.0), distance=10.0, orientation=(0.0, 0.0, 0.0, 0.0), fov_deg=40.0
    )
    with pytest.raises(RenderError, match="camera"):
        r.render(RenderParams(), bad_cam, 4, 4)
