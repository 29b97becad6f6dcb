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
