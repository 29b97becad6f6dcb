"""Renderer behaviour: determinism, buffer reuse, timings, colouring, histogram, memory."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import Camera, Lighting, RenderParams
from server.render import Renderer
from server.render.camera import fit_camera, orbit
from server.render.grid import MIN_CELLS
from server.render.tuning import Tuning
from tests.render.conftest import blob, make_topology
from tests.render.helpers import render


def test_deterministic_for_identical_input(device: str) -> None:
    top = make_topology(60)
    pos = blob(60, seed=12)
    cam = fit_camera(pos, 48, 36)
    for mode in ("iso", "volume"):
        params = RenderParams(mode=mode, lighting=Lighting(ambient_occlusion=True, depth_cue=0.4))  # type: ignore[arg-type]
        a = render(device, top, pos, params, cam, 48, 36)
        b = render(device, top, pos, params, cam, 48, 36)
        a.set_positions(pos + 5.0)
        a.render(params, cam, 48, 36)
        a.set_positions(pos)
        a.render(params, cam, 48, 36)
        np.testing.assert_array_equal(a.read_rgba(), b.read_rgba())
        np.testing.assert_array_equal(a.read_depth(), b.read_depth())
        np.testing.assert_array_equal(a.read_atom_ids(), b.read_atom_ids())


def test_buffers_are_reused_across_frames(device: str) -> None:
    n = 50
    r = Renderer(device)
    r.set_topology(make_topology(n))
    pos = blob(n, seed=2)
    cam = fit_camera(pos, 40, 30)
    r.set_positions(pos)
    r.render(RenderParams(), cam, 40, 30)
    names = ("_sorted", "_inv2s2", "_colors", "_hit_k", "_hit_v", "_rgba", "_depth", "_ids")
    ptrs = {k: getattr(r, k).ptr for k in names}
    positions = [b.ptr for b in r._pos_buffers]
    grid_ptrs = (r._grid.keys.ptr, r._grid.order.ptr, r._grid.cell_start.ptr)
    rng = np.random.default_rng(0)
    for i in range(3):
        r.set_positions(pos + rng.normal(size=pos.shape).astype(np.float32) * 0.1)
        r.render(RenderParams(mode="volume" if i % 2 else "iso"), cam, 40, 30)
        r.render(RenderParams(), cam, 20, 10)
    assert {k: getattr(r, k).ptr for k in names} == ptrs
    assert [b.ptr for b in r._pos_buffers] == positions and r._pos.ptr in positions
    assert (r._grid.keys.ptr, r._grid.order.ptr, r._grid.cell_start.ptr) == grid_ptrs


def test_pinned_host_buffer_path(device: str) -> None:
    n = 30
    top = make_topology(n)
    pos = blob(n, seed=3)
    cam = fit_camera(pos, 32, 24)
    a = Renderer(device)
    a.set_topology(top)
    buf = a.host_positions()
    assert buf.shape == (n, 3) and buf.dtype == np.float32
    buf[:] = pos
    a.set_positions(buf)
    a.render(RenderParams(), cam, 32, 24)
    b = render(device, top, pos, RenderParams(), cam, 32, 24)
    np.testing.assert_array_equal(a.read_rgba(), b.read_rgba())


@pytest.mark.parametrize("pageable", [False, True], ids=["staged", "pageable"])
@pytest.mark.parametrize("double_buffer", [None, True])
def test_the_next_frame_uploads_while_the_last_renders(
    device: str, double_buffer: bool | None, pageable: bool
) -> None:
    """`render(wait=False)`, then the next frame's positions, then `finish`: the frames come out
    as they do one by one, while each upload overlaps the render before it (two buffers on
    CUDA; one buffer waits for the render first). Frames written into the renderer's
    page-locked buffer and frames in ordinary memory (which two buffers stage there) alike."""
    n = 80
    top = make_topology(n)
    rng = np.random.default_rng(5)
    frames = [blob(n, seed=6) + rng.normal(size=(n, 3)).astype(np.float32) * 0.4 for _ in range(4)]
    cam = fit_camera(frames[0], 40, 30)
    params = RenderParams()
    one_by_one = []
    for f in frames:
        r = render(device, top, f, params, cam, 40, 30)
        one_by_one.append((r.read_rgba(), r.read_depth()))
    r = Renderer(device, tuning=Tuning(double_buffer=double_buffer))
    r.set_topology(top)
    r.set_positions(frames[0])
    r.render(params, cam, 40, 30, wait=False)
    piped = []
    for f in [*frames[1:], None]:
        if f is not None and pageable:
            r.set_positions(f.copy())
        elif f is not None:
            buf = r.host_positions()
            buf[:] = f
            r.set_positions(buf)
        r.finish()
        piped.append((r.read_rgba(), r.read_depth()))
        assert r.timings["total"] > 0
        if f is not None:
            r.render(params, cam, 40, 30, wait=False)
    for (a_rgba, a_depth), (b_rgba, b_depth) in zip(one_by_one, piped, strict=True):
        np.testing.assert_array_equal(a_rgba, b_rgba)
        np.testing.assert_array_equal(a_depth, b_depth)


def test_uploads_in_a_row_keep_the_last_frame(device: str) -> None:
    """Frames in ordinary memory set one after another without a render between them (each
    staged through a page-locked buffer with two buffers): the render draws the last one."""
    n = 60
    top = make_topology(n)
    rng = np.random.default_rng(7)
    frames = [blob(n, seed=8) + rng.normal(size=(n, 3)).astype(np.float32) for _ in range(5)]
    cam = fit_camera(frames[0], 40, 30)
    want = render(device, top, frames[-1], RenderParams(), cam, 40, 30).read_rgba()
    r = Renderer(device, tuning=Tuning(double_buffer=True))
    r.set_topology(top)
    r.set_positions(frames[0])
    r.render(RenderParams(), cam, 40, 30, wait=False)
    for f in frames[1:]:
        r.set_positions(f.copy())
    r.render(RenderParams(), cam, 40, 30)
    np.testing.assert_array_equal(r.read_rgba(), want)


def test_timings_and_grid_reuse(device: str) -> None:
    n = 40
    r = Renderer(device)
    r.set_topology(make_topology(n))
    pos = blob(n, seed=4)
    cam = fit_camera(pos, 32, 24)
    r.set_positions(pos)
    r.render(RenderParams(), cam, 32, 24)
    assert set(r.timings) == {"upload", "grid", "raycast", "total"}
    key = r._grid_key
    r.render(RenderParams(), orbit(cam, 30.0, 0.0), 32, 24)
    assert r._grid_key == key and r.timings["upload"] == 0.0
    r.render(RenderParams(sigma_A=2.0), cam, 32, 24)
    assert r._grid_key != key


@pytest.mark.parametrize(
    "color_by", ["element", "residue", "chain", "uniform", "bfactor", "charge"]
)
def test_every_coloring_renders(device: str, color_by: str) -> None:
    n = 24
    pos = blob(n, seed=7)
    cam = fit_camera(pos, 24, 18, margin=-2.0)
    with_values = make_topology(
        n,
        bfactors=np.linspace(5, 60, n).astype(np.float32),
        charges=np.linspace(-1, 1, n).astype(np.float32),
    )
    bare = make_topology(n)
    params = RenderParams(color_by=color_by, uniform_color=(0.1, 0.9, 0.2))  # type: ignore[arg-type]
    img = render(device, with_values, pos, params, cam, 24, 18).read_rgba()
    fallback = render(device, bare, pos, params, cam, 24, 18).read_rgba()
    uniform = render(
        device, bare, pos, params.model_copy(update={"color_by": "uniform"}), cam, 24, 18
    )
    assert img.shape == (18, 24, 4)
    if color_by in ("bfactor", "charge"):
        np.testing.assert_array_equal(fallback, uniform.read_rgba())


def test_density_histogram(device: str) -> None:
    n = 40
    pos = blob(n, seed=10)
    r = render(
        device, make_topology(n), pos, RenderParams(iso_level=0.5), fit_camera(pos, 8, 8), 8, 8
    )
    counts, edges = r.density_histogram(32)
    assert counts.shape == (32,) and edges.shape == (33,)
    assert edges[0] == 0.0 and edges[-1] == pytest.approx(3.0)
    assert counts.sum() > 1000
    assert counts[0] > counts[-2]  # most of the box is thin density


def test_memory_per_atom_within_budget(device: str) -> None:
    n = 5000
    r = Renderer(device)
    r.set_topology(make_topology(n))
    mem = r.memory_bytes()
    beyond = mem["per_atom"] + mem["grid"] + mem["other"]
    # 64 bytes per atom plus the fixed minimum grid of MIN_CELLS cells (8 bytes each, and 4
    # for the list of the cells the bound walks, which outgrows the atoms' spare buffer)
    assert beyond <= 64 * n + 12 * MIN_CELLS + 64 * 1024


def test_graph_replay_draws_what_eager_launches_draw(device: str) -> None:
    """Frames replayed from a captured graph (a streamed trajectory, a still camera) equal
    eager launches while positions, camera, parameters, topology and image size change."""
    n = 60
    top = make_topology(n)
    pos = blob(n, seed=3)
    cam = fit_camera(pos, 32, 24)
    # one part choice: on CUDA a trial's turns would be set-ups of their own
    replay = Renderer(device, tuning=Tuning(graphs=True, part_trial=False))
    eager = Renderer(device, tuning=Tuning(graphs=False))
    rng = np.random.default_rng(5)
    steps: list[tuple[str, RenderParams, Camera, int, int]] = (
        [("stream", RenderParams(sigma_A=1.3), cam, 32, 24)] * 4
        + [("camera", RenderParams(sigma_A=1.3), orbit(cam, 30.0, 10.0), 32, 24)] * 3
        + [("volume", RenderParams(mode="volume", sigma_A=1.1), cam, 32, 24)] * 3
        + [("bigger", RenderParams(sigma_A=1.3), cam, 48, 40)] * 3
    )
    for r in (replay, eager):
        r.set_topology(top)
    replayed = 0
    for i, (what, params, camera, w, h) in enumerate(steps):
        if i == 10:  # same atom count, other elements: colours change on the device only
            top = make_topology(n, elements=["O"] * n)
            for r in (replay, eager):
                r.set_topology(top)
        frame = (pos + rng.normal(scale=0.3, size=pos.shape)).astype(np.float32)
        for r in (replay, eager):
            r.set_positions(frame)
            r.render(params, camera, w, h)
        assert replay._graphs.enabled
        replayed += int(replay._graphs.last_replayed)
        np.testing.assert_array_equal(replay.read_rgba(), eager.read_rgba(), err_msg=what)
        np.testing.assert_array_equal(replay.read_depth(), eager.read_depth(), err_msg=what)
        np.testing.assert_array_equal(replay.read_atom_ids(), eager.read_atom_ids())
    assert replayed >= 8, "every repeated set-up after its first frame should replay"


def test_cameras_taking_turns_replay_their_graphs(device: str) -> None:
    """Viewers with cameras of their own render in turn on one frame: after one round each
    set-up replays its own graph, and the images stay those of eager launches."""
    n = 50
    top = make_topology(n)
    pos = blob(n, seed=4)
    base = fit_camera(pos, 24, 20)
    cams = [orbit(base, 40.0 * k, 0.0) for k in range(3)]
    # one part choice: on CUDA a trial's turns would be set-ups of their own
    replay = Renderer(device, tuning=Tuning(graphs=True, part_trial=False))
    eager = Renderer(device, tuning=Tuning(graphs=False))
    params = RenderParams(sigma_A=1.2)
    for r in (replay, eager):
        r.set_topology(top)
        r.set_positions(pos)
    replayed = 0
    for i in range(12):
        cam = cams[i % 3]
        for r in (replay, eager):
            r.render(params, cam, 24, 20)
        assert replay._graphs.enabled
        replayed += int(replay._graphs.last_replayed)
        np.testing.assert_array_equal(replay.read_rgba(), eager.read_rgba())
    assert replayed >= 8


def test_fixed_costs_of_a_small_molecule_leave_its_image_as_it_was(device: str) -> None:
    """A small molecule's grid lists every cell its bound walks (the atoms' spare buffer held
    fewer: the rest were walked one thread each), and the mean density of relative levels is
    taken by several threads per sampled atom: the same bounds, the same image, the same scale
    up to the order of its float sums."""
    n = 400
    top = make_topology(n)
    pos = blob(n, seed=11)
    cam = fit_camera(pos, 64, 48)
    params = RenderParams(sigma_A=1.4)
    out = {}
    for label, tuning in {
        "before": Tuning(mean_lanes=1, cell_list=False),
        "list": Tuning(mean_lanes=1, cell_list=True),
        "lanes": Tuning(mean_lanes=4, cell_list=True),
    }.items():
        r = Renderer(device, tuning=tuning)
        r.set_topology(top)
        r.set_positions(pos)
        r.render(params, cam, 64, 48)
        out[label] = (r.read_rgba(), r.density_scale(), r._grid.work.shape[0])
    assert out["before"][2] == n and out["list"][2] >= MIN_CELLS
    assert np.array_equal(out["before"][0], out["list"][0])
    assert out["before"][1] == out["list"][1]
    assert out["lanes"][1] == pytest.approx(out["list"][1], rel=1e-5)
    differ = np.any(out["lanes"][0] != out["list"][0], axis=-1).mean()
    assert differ < 0.002  # a pixel whose ray grazes the level may flip
    with pytest.raises(Exception, match="mean_lanes must be >= 1"):
        Tuning(mean_lanes=0)
