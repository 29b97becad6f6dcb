"""Frames staged in page-locked memory as they arrive (`GpuQueue.stage`) draw exactly what an
upload from the frame itself draws; the CPU device stages nothing."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from protocol import Camera, RenderParams, Topology
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.pipeline.staging import State


def test_a_staged_frame_draws_the_same_image(
    device: str, molecule: Callable[..., tuple[Topology, np.ndarray]]
) -> None:
    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    params = RenderParams(sigma_A=1.2)
    moved = (positions + np.float32(0.7)).astype(np.float32)
    staging, plain = GpuQueue(device=device, stage_atoms=10), GpuQueue(device=device)
    try:
        images = []
        for queue in (staging, plain):
            first = RenderRequest("t", Snapshot(topology, positions), params, camera, 64, 48)
            queue.render_sync(first)  # the slot exists from here on
            queue.stage("t", 2, moved)  # the next frame arrives
            if queue is staging and device.startswith("cuda"):
                deadline = time.monotonic() + 10
                while (s := queue._slots["t"].stager) is None or State.WRITING in s.states():
                    assert time.monotonic() < deadline, "the frame was never staged"
                    time.sleep(0.005)
            snap = Snapshot(topology, moved, positions_id=2)
            images.append(queue.render_sync(RenderRequest("t", snap, params, camera, 64, 48)))
        assert np.array_equal(images[0].image(), images[1].image())
        stager = staging._slots["t"].stager
        if device.startswith("cuda"):
            assert stager is not None
            assert stager.states() == [State.FREE] * 3  # taken by the render, then given back
        else:
            assert stager is None  # the CPU device reads the frame where it is
        staging.release_sync("t")
        assert "t" not in staging._slots  # its buffers went with it
    finally:
        staging.close()
        plain.close()


def test_a_render_gives_its_staged_copy_back_also_when_it_fails(
    molecule: Callable[..., tuple[Topology, np.ndarray]],
) -> None:
    """The take-and-give-back path, here on the CPU device with a pageable stand-in for the
    page-locked buffers (on CUDA the test above runs it for real)."""
    import pytest

    from server.pipeline.staging import FrameStager
    from server.render.errors import RenderError

    def plain(n: int) -> tuple[object, np.ndarray]:
        a = np.empty((n, 3), np.float32)
        return a, a

    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    params = RenderParams(sigma_A=1.2)
    queue = GpuQueue(device="cpu")
    try:
        queue.render_sync(RenderRequest("t", Snapshot(topology, positions), params, camera, 64, 48))
        stager = queue._slots["t"].stager = FrameStager(len(positions), queue._stage_pool, plain)
        for k, (w, h) in enumerate([(64, 48), (0, 48)], start=2):  # the second size is refused
            moved = (positions + np.float32(0.5 * k)).astype(np.float32)
            assert stager.offer(k, moved)
            snap = Snapshot(topology, moved, positions_id=k)
            request = RenderRequest("t", snap, params, camera, w, h)
            if w:
                queue.render_sync(request)
            else:
                with pytest.raises(RenderError):
                    queue.render_sync(request)
            assert stager.states() == [State.FREE] * 3, f"frame {k} kept its buffer"
            assert stager.take(k, 0.0) is None  # taken by its render, not left ready
    finally:
        queue.close()
