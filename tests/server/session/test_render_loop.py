"""The render loop's decisions against a host that is only its state and a backend without a
GPU: what a change renders, for which views, and what a failure leaves behind."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

import protocol as p
from server.pipeline.gpu import GpuQueue, RenderOutput, RenderRequest, Snapshot
from server.render.errors import CapacityError, RenderError
from server.session.clients import Client
from server.session.delivery import Delivery
from server.session.render_loop import RenderLoop, Scene
from server.session.scheduler import RenderScheduler
from server.settings import ServerSettings
from tests.render.test_device_jpeg import COMMENT, LaneEncoder
from tests.server.peers import molecule
from tests.server.session.fakes import PaintBackend, client, run_on_own_loop, sent, services

SETTINGS = ServerSettings(
    token="t", default_size=(40, 30), stats_interval_s=60.0, viewer_views_per_pass=64
)


@dataclass
class Host:
    """A session reduced to what the render loop reads and tells."""

    topology: p.Topology
    positions: npt.NDArray[np.float32]
    clients: dict[str, Client] = field(default_factory=dict)
    camera: p.Camera | None = field(default_factory=lambda: p.Camera(distance=40.0))
    render_params: p.RenderParams = SETTINGS.render_defaults
    version: int = 1
    drawable: bool = True
    """False: `scene` answers None (a new topology arrived, or layers are being evaluated)."""
    taken: list[Snapshot] = field(default_factory=list)
    broadcasts: list[p.Message] = field(default_factory=list)

    def can_render(self) -> bool:
        return True

    def take_snapshot(self) -> Snapshot | None:
        snap = Snapshot(
            self.topology, self.positions, positions_id=self.version, version=self.version
        )
        self.taken.append(snap)
        return snap

    def scene(self, snap: Snapshot) -> Scene | None:
        return Scene(None) if self.drawable else None

    def broadcast(self, message: p.Message) -> None:
        self.broadcasts.append(message)

    def take_back_render_params(self, params: p.RenderParams, why: str) -> bool:
        if params == self.render_params:
            return False
        self.render_params = params
        self.version += 1
        return True


@dataclass
class FailingOnce(PaintBackend):
    """Raises on its first render, paints after."""

    failures: int = 1

    async def render(self, request: RenderRequest) -> RenderOutput:
        if self.failures:
            self.failures -= 1
            self.requests.append(request)
            raise RuntimeError("the device went away")
        return await super().render(request)


class Refusing(PaintBackend):
    """Refuses every render, its numbers changing from one to the next (a system re-split
    each frame whose slab is too large for its device)."""

    async def render(self, request: RenderRequest) -> RenderOutput:
        self.requests.append(request)
        raise RenderError(f"a slab holds {3000 + len(self.requests)} atoms; a device holds 2000")


class TooLargeGeodesic(PaintBackend):
    """Paints the classical density and refuses the geodesic one as too large (a sigma whose
    samples would walk more routes than the server allows)."""

    async def render(self, request: RenderRequest) -> RenderOutput:
        if request.params.scale_space == "geodesic":
            self.requests.append(request)
            raise CapacityError("the geodesic density would walk about 66,396 routes a sample")
        return await super().render(request)


Body = Callable[[RenderLoop, Host, PaintBackend], Coroutine[Any, Any, None]]


def run(
    body: Body,
    tmp: Path,
    backend: PaintBackend | None = None,
    slots: int = 2,
    settings: ServerSettings = SETTINGS,
) -> None:
    async def main() -> None:
        back = backend or PaintBackend()
        svc = services(tmp, back, slots)
        topo, pos = molecule()
        host = Host(topo, pos.astype(np.float32))
        delivery = Delivery("s", svc)
        loop = RenderLoop(
            host, "s", "session:s", settings, svc, RenderScheduler(settings), delivery
        )
        task = loop.start()
        try:
            await body(loop, host, back)
        finally:
            task.cancel()
            for t in [task, *delivery.in_flight()]:
                t.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await t
            delivery.close()
            svc.steering_log.close()

    run_on_own_loop(main)


async def settle(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not predicate():
        if loop.time() > end:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.005)


async def quiet() -> None:
    """Let every ready task run (the loop wakes, renders with the paint backend, delivers)."""
    for _ in range(20):
        await asyncio.sleep(0)
    await asyncio.sleep(0.05)


def images(c: Client) -> list[p.Image]:
    return [m for m in sent(c) if isinstance(m, p.Image)]


def test_a_change_renders_once_however_often_it_is_marked(tmp_path: Path) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        a = client("a", "viewer")
        host.clients["a"] = a
        for _ in range(5):
            loop.mark_dirty()
        await settle(lambda: bool(images(a)))
        for _ in range(5):
            loop.mark_dirty()
            await quiet()
        assert [r.snapshot.version for r in backend.requests] == [1]
        host.version = 2
        loop.mark_dirty()
        await settle(lambda: len(backend.requests) == 2)
        await quiet()
        assert [r.snapshot.version for r in backend.requests] == [1, 2]
        assert loop.render_count == 2

    run(body, tmp_path)


def test_a_change_during_a_render_is_rendered_next_not_lost(tmp_path: Path) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        a = client("a", "viewer")
        host.clients["a"] = a
        backend.gate = asyncio.Event()
        loop.mark_dirty()
        await settle(lambda: len(backend.requests) == 1)  # version 1 in flight
        host.version = 2
        loop.mark_dirty()
        await quiet()
        assert len(backend.requests) == 1  # one render at a time
        backend.gate.set()
        await settle(lambda: len(backend.requests) == 2)
        assert backend.requests[1].snapshot.version == 2
        await settle(lambda: any(i.frame_id == 2 for i in images(a)))

    run(body, tmp_path)


def test_a_viewer_with_its_own_camera_gets_its_own_render_of_the_same_snapshot(
    tmp_path: Path,
) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        a, b, c = client("a", "viewer"), client("b", "viewer"), client("c", "viewer")
        own = p.Camera(distance=90.0)
        c.view = p.View(camera=own, width=40, height=30)
        host.clients.update(a=a, b=b, c=c)
        loop.mark_dirty()
        await settle(lambda: all(images(x) for x in (a, b, c)))
        cameras = sorted(r.camera.distance for r in backend.requests)
        assert cameras == [40.0, 90.0]  # a and b share the session's camera
        assert len(host.taken) == 1  # both renders drew the one snapshot of the pass
        assert images(a)[0].frame_id == images(b)[0].frame_id != images(c)[0].frame_id

    run(body, tmp_path)


def test_a_failed_render_is_reported_to_every_client_and_the_loop_goes_on(
    tmp_path: Path,
) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        a = client("a", "viewer")
        host.clients["a"] = a
        loop.mark_dirty()
        await settle(lambda: bool(host.broadcasts))
        (error,) = host.broadcasts
        assert isinstance(error, p.Error) and error.code == p.ErrorCode.INTERNAL
        assert loop.services.encode_slots._value == 2  # its encode slot was given back
        host.version = 2
        loop.mark_dirty()
        await settle(lambda: bool(images(a)))
        assert images(a)[0].step == 0 and loop.render_count == 1

    run(body, tmp_path, FailingOnce())


def test_a_refusal_is_told_with_its_reason_once_while_it_repeats(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A render refused by what was sent: the clients get the reason, not "render failed",
    and the same reason (its numbers aside) is not told again on every pass."""
    monkeypatch.setattr("server.session.render_loop.FAILED_RENDER_PAUSE_S", 0.01)

    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        host.clients["a"] = client("a", "viewer")
        for version in range(2, 6):
            host.version = version
            loop.mark_dirty()
            await settle(lambda v=version: len(backend.requests) >= v - 1)  # type: ignore[misc]
            await quiet()
        assert len(backend.requests) >= 4
        (error,) = host.broadcasts
        assert isinstance(error, p.Error) and error.code == p.ErrorCode.INVALID_MESSAGE
        assert error.message.startswith("render refused: a slab holds 300")

    run(body, tmp_path, Refusing())


async def drawn_then_geodesic(
    loop: RenderLoop, host: Host, new_molecule: bool = False, **update: Any
) -> p.RenderParams:
    """One image drawn for a viewer, then the session steered to the geodesic density (with
    `update` too, and a new topology with `new_molecule`); returns the parameters drawn."""
    a = client("a", "viewer")
    host.clients["a"] = a
    loop.mark_dirty()
    await settle(lambda: len(images(a)) == 1)
    drawn = host.render_params
    if new_molecule:
        host.topology = host.topology.model_copy()  # a new topology arrived
    host.render_params = drawn.model_copy(update={"scale_space": "geodesic", **update})
    host.version = 2
    loop.mark_dirty()
    return drawn


def test_a_steer_too_large_to_draw_is_taken_back_to_what_the_session_last_drew(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Geodesic at sigma 6 A was refused as too large, yet the session kept it: the dashboard
    showed Geodesic over the last classical image, at 0 fps, until something else changed."""
    monkeypatch.setattr("server.session.render_loop.FAILED_RENDER_PAUSE_S", 0.01)

    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        drawn = await drawn_then_geodesic(loop, host, sigma_A=6.0)
        await settle(lambda: len(backend.requests) == 3)  # the parameters it drew, drawn again
        assert host.render_params == drawn
        (error,) = host.broadcasts
        assert isinstance(error, p.Error) and error.code == p.ErrorCode.TOO_LARGE
        assert "routes a sample" in error.message and "went back" in error.message
        assert backend.requests[-1].params == drawn

    run(body, tmp_path, TooLargeGeodesic())


def test_parameters_refused_before_anything_was_drawn_are_only_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With no image drawn yet there is nothing to go back to: the refusal is told, the
    parameters stay."""
    monkeypatch.setattr("server.session.render_loop.FAILED_RENDER_PAUSE_S", 0.01)

    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        host.clients["a"] = client("a", "viewer")
        host.render_params = host.render_params.model_copy(update={"scale_space": "geodesic"})
        loop.mark_dirty()
        await settle(lambda: bool(host.broadcasts))
        (error,) = host.broadcasts
        assert isinstance(error, p.Error) and error.code == p.ErrorCode.TOO_LARGE
        assert "went back" not in error.message
        assert host.render_params.scale_space == "geodesic"

    run(body, tmp_path, TooLargeGeodesic())


def test_a_new_molecule_too_large_for_the_parameters_does_not_take_them_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Refused with a molecule other than the last image's, the size may be the molecule's
    own: a steer made with it is not undone (it is only refused)."""
    monkeypatch.setattr("server.session.render_loop.FAILED_RENDER_PAUSE_S", 0.01)

    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        await drawn_then_geodesic(loop, host, new_molecule=True)
        await settle(lambda: bool(host.broadcasts))
        (error,) = host.broadcasts
        assert isinstance(error, p.Error) and "went back" not in error.message
        assert host.render_params.scale_space == "geodesic"

    run(body, tmp_path, TooLargeGeodesic())


def test_a_snapshot_the_host_cannot_draw_yet_renders_nothing_and_frees_its_slot(
    tmp_path: Path,
) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        a = client("a", "viewer")
        host.clients["a"] = a
        host.drawable = False
        loop.mark_dirty()
        await settle(lambda: bool(host.taken))
        await quiet()
        assert backend.requests == [] and images(a) == []
        assert loop.services.encode_slots._value == 1
        host.drawable = True  # the layers' atoms arrived: the host marks the loop dirty
        loop.mark_dirty()
        await settle(lambda: bool(images(a)))  # the same version, not yet drawn, is due still
        assert [r.snapshot.version for r in backend.requests] == [1]

    run(body, tmp_path, slots=1)


def test_without_viewers_nothing_is_rendered_and_no_frame_is_taken(tmp_path: Path) -> None:
    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        loop.mark_dirty()
        await quiet()
        assert backend.requests == [] and host.taken == []
        host.clients["a"] = a = client("a", "viewer")
        loop.mark_dirty()
        await settle(lambda: bool(images(a)))

    run(body, tmp_path)


def test_views_a_pass_leaves_render_in_the_passes_that_follow_at_once(tmp_path: Path) -> None:
    """`viewer_views_per_pass` (1): with a steerer in the session, five viewers each on a
    camera of their own get one image each from one change, one pass after another (the first
    with the steerer's view), and a pass that can draw nothing (layers still being evaluated)
    does not come straight back and spin."""

    async def body(loop: RenderLoop, host: Host, backend: PaintBackend) -> None:
        steerer = client("s", "steerer")
        viewers = [client(f"v{i}", "viewer") for i in range(5)]
        host.clients["s"] = steerer
        for i, v in enumerate(viewers):
            v.view = p.View(camera=p.Camera(distance=50.0 + i), width=40, height=30)
            host.clients[v.client_id] = v
        loop.mark_dirty()
        await settle(lambda: all(images(v) for v in [steerer, *viewers]))
        assert len(backend.requests) == 6 and len(host.taken) == 5  # five passes
        assert backend.requests[0].camera.distance == 40.0  # the steerer's view first
        host.version = 2
        host.drawable = False
        loop.mark_dirty()
        await settle(lambda: len(host.taken) == 6)
        await quiet()
        assert len(host.taken) == 6  # one pass that drew nothing, not one after another

    run(body, tmp_path, settings=replace(SETTINGS, viewer_views_per_pass=1))


@dataclass
class LaneBackend(PaintBackend):
    """The real render lane on warp's CPU device, whose JPEGs are encoded where they were
    rendered (by the stand-in for nvJPEG) and come back without their pixels."""

    queue: GpuQueue = field(default_factory=lambda: GpuQueue(device="cpu"))

    def __post_init__(self) -> None:
        self.queue.jpeg = LaneEncoder("cpu")
        self.actual_device = "cpu"

    async def render(self, request: RenderRequest) -> RenderOutput:
        self.requests.append(request)
        if self.gate is not None:
            await self.gate.wait()
        return await self.queue.render(request)


def test_a_viewer_that_turns_video_on_while_its_jpeg_renders_on_the_lane_keeps_video(
    tmp_path: Path,
) -> None:
    """The render was planned for a JPEG viewer, so only its JPEG comes back; the viewer asks
    for video before it is delivered (a dashboard's view arrives just after it connects). It
    gets that JPEG, and video from the next render: no stream is fed a render without pixels
    (its encoder would fail, and the viewer be held to JPEG)."""
    backend = LaneBackend(gate=asyncio.Event())

    async def body(loop: RenderLoop, host: Host, lane: PaintBackend) -> None:
        a = client("a", "viewer")
        a.view = p.View(width=40, height=30)
        host.clients["a"] = a
        loop.mark_dirty()
        await settle(lambda: len(lane.requests) == 1)
        assert lane.requests[0].jpeg_quality is not None and lane.requests[0].video_size is None
        # its new view, as the session takes it
        a.view, a.view_ref, a.needs_image = p.View(width=40, height=30, video=["h264"]), 1, True
        loop.mark_dirty()
        assert lane.gate is not None
        lane.gate.set()
        await settle(lambda: bool(images(a)), timeout=30)
        assert COMMENT in images(a)[0].data  # the JPEG the lane encoded
        assert not a.force_jpeg
        await settle(lambda: bool(a._video), timeout=30)
        first = p.decode(a._video[0][1], p.Limits(max_message_bytes=1 << 30))
        assert isinstance(first, p.Image) and first.format == "h264" and first.key

    try:
        run(body, tmp_path, backend)
    finally:
        backend.queue.close()
