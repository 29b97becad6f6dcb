"""A periodic frame displayed on the render device is drawn from there (server/pipeline/gpu.py,
`_Slot.shown`): its render copies it device to device instead of uploading the host copy
again, and draws exactly what the host copy holds; a frame whose device copy a later display
replaced uploads from the host. On a CUDA host the read-back buffers are lent
(server/render/loans.py) and come back only when no array views them."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from protocol import Camera, RenderParams, Topology
from server.pipeline.gpu import DisplayRequest, GpuQueue, RenderRequest, Snapshot
from server.render import Renderer
from server.render import device as render_device
from server.render.boxes import Options
from tests.render.conftest import make_topology
from tests.render.test_gpu_lanes import image_of

BOX = 18.0


def chain(n: int, seed: int) -> tuple[Topology, np.ndarray]:
    """A bonded random walk of 1.5 A steps wrapped into a cubic box: the box cuts it."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(n, 3))
    steps *= 1.5 / np.linalg.norm(steps, axis=1, keepdims=True)
    walk = np.cumsum(steps, axis=0) + BOX / 2
    bonds = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    return make_topology(n, bonds=bonds), np.mod(walk, BOX).astype(np.float32)


def test_a_displayed_frame_is_drawn_from_the_device(device: str) -> None:
    topology, raw = chain(400, seed=3)
    box = np.eye(3, dtype=np.float32) * BOX
    camera = Camera(target=(BOX / 2,) * 3, distance=70.0)
    queue = GpuQueue(device=device)
    slot = "session:a"

    def display(positions: np.ndarray) -> np.ndarray:
        request = DisplayRequest(slot, topology, positions, box, Options(mode="molecules"))
        return queue.display_sync(request).positions

    def render(positions: np.ndarray, positions_id: int) -> tuple[np.ndarray, str]:
        snap = Snapshot(topology, positions, positions_id=positions_id)
        out = queue.render_sync(RenderRequest(slot, snap, RenderParams(), camera, 48, 32))
        return out.image(), queue._slots[slot].renderer.uploaded_from

    try:
        first = display(raw)
        assert np.ptp(first, axis=0).max() > BOX  # made whole across the box
        image, source = render(first, 1)
        assert source == "device"
        np.testing.assert_array_equal(image, image_of(topology, first.copy(), camera, device))
        second = display(raw + np.float32(0.7))
        assert not np.array_equal(second, first)
        image, source = render(first, 2)  # the device holds the second frame now
        assert source == "host"
        np.testing.assert_array_equal(image, image_of(topology, first.copy(), camera, device))
        image, source = render(second, 3)
        assert source == "device"
        np.testing.assert_array_equal(image, image_of(topology, second.copy(), camera, device))
    finally:
        queue.close()


def test_a_device_copy_of_another_size_is_refused(device: str) -> None:
    import warp as wp

    from server.render.errors import RenderError

    topology, raw = chain(50, seed=4)
    r = Renderer(device)
    r.set_topology(topology)
    other = wp.zeros(20, dtype=wp.vec3, device=r.device)
    with pytest.raises(RenderError, match="a device copy of 20 atoms"):
        r.set_positions(raw, on_device=other)


@pytest.mark.gpu
@pytest.mark.skipif(render_device.cuda_count() == 0, reason="needs a CUDA device")
def test_a_lent_read_back_buffer_comes_back_only_when_no_array_views_it() -> None:
    from server.render.loans import HostLoans

    loans = HostLoans(10, keep=2)
    owner, array = loans.lend()
    array[:] = 1.0
    view = array[2:5]
    del array
    gc.collect()
    assert loans.waiting == 0  # the slice still views it
    again_owner, again = loans.lend()
    assert again_owner is not owner and not np.shares_memory(again, view)
    np.testing.assert_array_equal(view, 1.0)
    del view, again
    gc.collect()
    assert loans.waiting == 2 and loans.made == 2
    _third_owner, third = loans.lend()
    assert loans.made == 2  # taken from the pool, not page-locked again
    assert third.shape == (10, 3) and third.dtype == np.float32


@pytest.mark.gpu
@pytest.mark.skipif(render_device.cuda_count() == 0, reason="needs a CUDA device")
@pytest.mark.parametrize("mode", ["whole", "molecules", "unwrap", "wrap"])
@pytest.mark.parametrize("fit", ["off", "rotation"])
def test_replayed_frames_match_frames_launched_one_by_one(mode: str, fit: str) -> None:
    """A trajectory in a box of fixed shape replays its steps as a CUDA graph: every frame the
    same as launching each kernel, the fit's reference and the followed atoms included."""
    from server.render.periodic import PeriodicTransform

    topology, raw = chain(600, seed=6)
    box = np.eye(3, dtype=np.float32) * BOX
    atoms = np.arange(0, 600, 3, dtype=np.int32)
    options = Options(
        mode=mode,
        centre=atoms,
        fit=fit,
        fit_atoms=atoms if fit != "off" else None,
    )
    rng = np.random.default_rng(7)
    replayed = PeriodicTransform("cuda:0")
    eager = PeriodicTransform("cuda:0", graphs=False)
    for t in (replayed, eager):
        t.set_topology(topology)
    walk = raw.copy()
    for _ in range(8):
        walk = np.mod(walk + rng.normal(scale=0.4, size=walk.shape), BOX).astype(np.float32)
        got = replayed.apply(walk, box, options)
        want = eager.apply(walk, box, options)
        np.testing.assert_array_equal(got.positions, want.positions)
        np.testing.assert_array_equal(got.rotation, want.rotation)
    assert replayed.replays >= 5 and eager.replays == 0
