"""The GPU queue over several devices (server/pipeline/gpu.py): a lone session is drawn across
every device, several sessions each get one, and the threads that drive the devices never
share one. Two CPU devices stand in for two GPUs; the images are checked against one device's.
On a CUDA host the pipelined path (the next staged frame uploaded while a render runs) is
checked too."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest

from protocol import Camera, RenderParams, Topology
from server.pipeline.gpu import GpuQueue, RenderRequest, Snapshot
from server.render import Renderer
from server.render import device as render_device
from server.render.multi import MultiRenderer
from server.render.sortlast import SortLastRenderer
from server.render.tuning import Tuning
from tests.server.peers import molecule as helix


def image_of(topology: Topology, positions: np.ndarray, camera: Camera, device: str) -> np.ndarray:
    r = Renderer(device)
    r.set_topology(topology)
    r.set_positions(positions)
    r.render(RenderParams(), camera, 48, 32)
    return r.read_rgba()


def request(slot: str, topology: Topology, positions: np.ndarray, camera: Camera) -> RenderRequest:
    return RenderRequest(slot, Snapshot(topology, positions), RenderParams(), camera, 48, 32)


def test_sessions_spread_over_every_device_alone_and_take_one_each_together(
    molecule: Callable[..., tuple[Topology, np.ndarray]],
) -> None:
    topology, positions = molecule(60, seed=3)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    want = image_of(topology, positions, camera, "cpu")
    queue = GpuQueue(devices=("cpu", "cpu"))

    async def run() -> None:
        a = await queue.render(request("session:a", topology, positions, camera))
        assert queue.spread == "session:a"
        assert isinstance(queue._slots["session:a"].renderer, MultiRenderer)
        job = await queue.render(request("job:1", topology, positions, camera))
        assert queue.lane_device("job:1") == "cpu" and queue._lane_of["job:1"] == 0
        await queue.release("job:1")
        b = await queue.render(request("session:b", topology, positions, camera))
        # the second session moves the first onto the first device and takes the other
        assert queue.spread is None
        assert queue._lane_of == {"session:a": 0, "session:b": 1}
        a2 = await queue.render(request("session:a", topology, positions, camera))
        assert isinstance(queue._slots["session:a"].renderer, Renderer)
        for out in (a, job, b, a2):
            assert np.array_equal(out.image(), want)
        await queue.release("session:b")
        assert queue.spread == "session:a"  # alone again: across every device
        a3 = await queue.render(request("session:a", topology, positions, camera))
        assert isinstance(queue._slots["session:a"].renderer, MultiRenderer)
        assert np.array_equal(a3.image(), want)

    try:
        asyncio.run(run())
    finally:
        queue.close()


def test_a_session_one_device_cannot_hold_keeps_every_device_beside_others() -> None:
    """Over `device_atoms`, the lone session is split by space (sort-last) and is not gathered
    onto one device when a second session comes: that one shares the first device's thread.
    A later, smaller system of the same session goes back to image bands."""
    big, big_pos = helix(240, seed=4)  # 170 A long: a slab and its halo hold some of it
    small, small_pos = helix(60, seed=3)
    camera = Camera(target=tuple(big_pos.mean(axis=0)), distance=200.0)
    want_big = image_of(big, big_pos, camera, "cpu")
    want_small = image_of(small, small_pos, camera, "cpu")
    queue = GpuQueue(devices=("cpu", "cpu"), device_atoms=150)

    def close_to(got: np.ndarray, want: np.ndarray) -> bool:
        return int(np.abs(got.astype(np.int16) - want.astype(np.int16)).max()) <= 1

    async def run() -> None:
        a = await queue.render(request("session:a", big, big_pos, camera))
        assert isinstance(queue._slots["session:a"].renderer, SortLastRenderer)
        b = await queue.render(request("session:b", small, small_pos, camera))
        assert queue.spread == "session:a"
        assert queue._lane_of == {"session:a": 0, "session:b": 0}
        a2 = await queue.render(request("session:a", big, big_pos, camera))
        job = await queue.render(request("job:1", big, big_pos, camera))  # a movie of it
        assert queue._lane_of["job:1"] == 0
        assert isinstance(queue._slots["job:1"].renderer, SortLastRenderer)
        await queue.release("job:1")
        for out in (a, a2, job):
            assert close_to(out.image(), want_big)
        assert np.array_equal(b.image(), want_small)
        await queue.release("session:b")
        shrunk = Snapshot(small, small_pos, topology_id=2, positions_id=2)
        a3 = await queue.render(RenderRequest("session:a", shrunk, RenderParams(), camera, 48, 32))
        assert isinstance(queue._slots["session:a"].renderer, MultiRenderer)
        assert np.array_equal(a3.image(), want_small)

    try:
        asyncio.run(run())
    finally:
        queue.close()


def test_a_large_system_gathers_the_sessions_that_hold_devices_and_gives_them_back() -> None:
    """Two sessions hold a device each (nobody need watch them); a system one device does
    not hold then comes, twice at once (two one-off renders): both are split by space, the
    sessions move beside them and still draw their own pictures, and once the large ones
    are gone the sessions take a device each again."""
    big, big_pos = helix(240, seed=4)
    small, small_pos = helix(60, seed=3)
    camera = Camera(target=tuple(big_pos.mean(axis=0)), distance=200.0)
    want_big = image_of(big, big_pos, camera, "cpu")
    want_small = image_of(small, small_pos, camera, "cpu")
    queue = GpuQueue(devices=("cpu", "cpu"), device_atoms=150)

    async def run() -> None:
        await queue.render(request("session:a", small, small_pos, camera))
        await queue.render(request("session:b", small, small_pos, camera))
        assert sorted(queue._lane_of.values()) == [0, 1]
        one, two = await asyncio.gather(
            queue.render(request("render:1", big, big_pos, camera)),
            queue.render(request("render:2", big, big_pos, camera)),
        )
        for out in (one, two):
            assert int(np.abs(out.image().astype(np.int16) - want_big).max()) <= 1
        assert set(queue._lane_of.values()) == {0}
        a = await queue.render(request("session:a", small, small_pos, camera))
        b = await queue.render(request("session:b", small, small_pos, camera))
        assert np.array_equal(a.image(), want_small) and np.array_equal(b.image(), want_small)
        await queue.release("render:1")
        await queue.release("render:2")
        assert sorted(queue._lane_of.values()) == [0, 1]
        b = await queue.render(request("session:b", small, small_pos, camera))
        assert np.array_equal(b.image(), want_small)

    try:
        asyncio.run(run())
    finally:
        queue.close()


def test_layers_together_past_what_one_device_holds_are_refused_by_their_total() -> None:
    """Layers are drawn on one device, a renderer each: with `device_atoms` set, what they
    hold together must fit it, not only each one."""
    from dataclasses import replace

    from server.render.errors import RenderError
    from server.render.layerplan import LayerPlan

    topology, positions = helix(120, seed=5)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=80.0)
    queue = GpuQueue(devices=("cpu", "cpu"), device_atoms=150)
    plan = LayerPlan("half", np.arange(100, dtype=np.int32), RenderParams(), atoms_key=1)
    base = request("session:a", topology, positions, camera)
    try:
        one = queue.render_sync(replace(base, layers=(plan,)))
        assert one.image().any()
        two = replace(base, layers=(plan, replace(plan, name="again")))
        with pytest.raises(RenderError, match="layers hold 200 atoms together"):
            queue.render_sync(two)
    finally:
        queue.close()


def test_each_device_has_a_thread_of_its_own_and_cpu_devices_take_turns(
    molecule: Callable[..., tuple[Topology, np.ndarray]],
) -> None:
    """Each device is driven by a thread of its own. Warp's CPU kernels cannot run on two
    threads at once (two CPU lanes crashed the two-device benchmark 1 run in 5), so lanes on CPU
    devices take turns: a session on the second CPU device renders once the first device's
    work ends, and is not lost meanwhile."""
    topology, positions = molecule(40, seed=4)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=30.0)
    queue = GpuQueue(devices=("cpu", "cpu"))
    held = threading.Event()
    names: set[str] = set()

    def hold() -> None:
        names.add(threading.current_thread().name)
        held.wait(30)

    async def run() -> None:
        await queue.render(request("session:a", topology, positions, camera))
        await queue.render(request("session:b", topology, positions, camera))
        assert queue._lane_of == {"session:a": 0, "session:b": 1}
        blocker = asyncio.ensure_future(queue._run(0, hold))
        while not names:  # the first device's thread is working (holding the CPU)
            await asyncio.sleep(0.01)
        second = asyncio.ensure_future(
            queue.render(request("session:b", topology, positions, camera))
        )
        await asyncio.sleep(0.3)
        assert not second.done()  # its turn comes when the first device's work ends
        held.set()
        out = await second
        assert out.image().any()
        await blocker

    try:
        asyncio.run(run())
    finally:
        held.set()
        queue.close()
    assert names == {"gpu_0"}


@pytest.mark.gpu
@pytest.mark.skipif(render_device.cuda_count() == 0, reason="needs a CUDA device")
def test_the_next_staged_frame_uploads_while_a_render_runs(
    molecule: Callable[..., tuple[Topology, np.ndarray]],
) -> None:
    """A live render uploads the newest staged frame into the spare buffer before it returns;
    the request for that frame then draws it without another upload, the same image."""
    from server.pipeline.staging import State

    topology, positions = molecule(3000, seed=5)
    camera = Camera(target=tuple(positions.mean(axis=0)), distance=60.0)
    moved = (positions + np.float32(0.6)).astype(np.float32)
    queue = GpuQueue(device="cuda:0", stage_atoms=10, tuning=Tuning(double_buffer=True))
    try:
        queue.render_sync(request("session:a", topology, positions, camera))
        slot = queue._slots["session:a"]
        assert slot.renderer.pipelined
        queue.stage("session:a", 2, moved)
        deadline = time.monotonic() + 10
        while slot.stager is None or State.READY not in slot.stager.states():
            assert time.monotonic() < deadline, "the frame was never staged"
            time.sleep(0.005)
        queue.render_sync(request("session:a", topology, positions, camera))  # frame 1 again
        assert slot.positions_id == 2 and slot.prefetched is not None
        snap = Snapshot(topology, moved, positions_id=2)
        out = queue.render_sync(RenderRequest("session:a", snap, RenderParams(), camera, 48, 32))
        assert np.array_equal(out.image(), image_of(topology, moved, camera, "cuda:0"))
        assert slot.prefetched is None  # given back once the render read it
        assert slot.stager.states() == [State.FREE] * 3
    finally:
        queue.close()


def test_each_devices_thread_says_how_long_its_work_has_run() -> None:
    """A render that held a device's thread for 20 minutes was invisible to /healthz, which
    answered "ok" all along; `busy` tells each device's current work and how long it has run."""
    queue = GpuQueue(devices=("cpu", "cpu"))
    started = threading.Event()
    release = threading.Event()

    def hold() -> str:
        started.set()
        release.wait(30)
        return "done"

    async def run() -> None:
        assert [b["busy_s"] for b in queue.busy()] == [0.0, 0.0]
        held = asyncio.ensure_future(queue.call(hold))
        await asyncio.to_thread(started.wait, 30)
        await asyncio.sleep(0.3)
        first, second = queue.busy()
        assert first["device"] == "cpu" and first["busy_s"] >= 0.3 and second["busy_s"] == 0.0
        release.set()
        assert await held == "done"
        assert [b["busy_s"] for b in queue.busy()] == [0.0, 0.0]

    try:
        asyncio.run(run())
    finally:
        release.set()
        queue.close()
