"""The session facade against a render backend without a GPU and clients without sockets:
frames become images for every viewer, steering is confirmed by acks, forces merge."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import protocol as p
from server.session.session import Session
from server.settings import ServerSettings
from tests.server.peers import frame, molecule
from tests.server.session.fakes import PaintBackend, client, run_on_own_loop, sent, services

SETTINGS = ServerSettings(token="t", default_size=(40, 30), stats_interval_s=60.0)


def run(test: Callable[[Session, PaintBackend], Coroutine[Any, Any, None]], tmp: Path) -> None:
    async def main() -> None:
        backend = PaintBackend()
        session = Session("s", SETTINGS, services(tmp, backend))
        try:
            await test(session, backend)
        finally:
            await session.close()
            session.services.steering_log.close()

    run_on_own_loop(main)


async def settle(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not predicate():
        if loop.time() > end:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.005)


def images(c: Any) -> list[p.Image]:
    return [m for m in sent(c) if isinstance(m, p.Image)]


def test_a_frame_reaches_every_viewer_as_one_shared_render(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        a, b = client("a", "viewer"), client("b", "viewer")
        session.attach(a)
        session.attach(b)
        session.on_topology(topo)
        session.on_frame(frame(pos, 5))
        await settle(lambda: bool(images(a)) and bool(images(b)))
        assert len(backend.requests) == 1  # one render served both
        request = backend.requests[0]
        assert request.snapshot.step == 5 and (request.width, request.height) == (40, 30)
        img = images(a)[0]
        assert img.step == 5 and img.still and (img.width, img.height) == (40, 30)
        assert images(b)[0].frame_id == img.frame_id

    run(body, tmp_path)


def test_each_frame_is_offered_to_the_backend_to_stage_as_it_arrives(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        session.on_topology(topo)
        session.on_frame(frame(pos, 1))
        session.on_frame(frame(pos, 2))
        assert backend.staged == [(session.slot, 1), (session.slot, 2)]

    run(body, tmp_path)


def test_frames_that_outrun_rendering_coalesce_to_the_newest(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        a = client("a", "viewer")
        session.attach(a)
        session.on_topology(topo)
        backend.gate = asyncio.Event()
        session.on_frame(frame(pos, 1))
        await settle(lambda: len(backend.requests) == 1)  # the render of step 1 is in flight
        for step in range(2, 40):
            session.on_frame(frame(pos, step))
        backend.gate.set()
        await settle(lambda: any(i.step == 39 for i in images(a)))
        assert [r.snapshot.step for r in backend.requests] == [1, 39]

    run(body, tmp_path)


def test_sim_params_show_only_once_the_engine_confirms(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        sim, steerer = client("sim", "simulation"), client("u")
        session.attach(sim)
        session.attach(steerer)
        session.on_topology(topo)
        session.on_frame(frame(pos, 0))
        await session.steer(steerer, p.SimParams(seq=4, temperature_K=900.0))
        forwarded = [m for m in sent(sim) if isinstance(m, p.SimParams)][-1]
        assert session.sim_params.temperature_K is None
        session.on_ack(p.ParamsAck(ref=forwarded.seq or 0, ok=False, detail="too hot"))
        assert session.sim_params.temperature_K is None
        reply = [m for m in sent(steerer) if isinstance(m, p.ParamsAck)][-1]
        assert reply.ref == 4 and not reply.ok
        await session.steer(steerer, p.SimParams(seq=5, temperature_K=310.0))
        forwarded = [m for m in sent(sim) if isinstance(m, p.SimParams)][-1]
        session.on_ack(p.ParamsAck(ref=forwarded.seq or 0, ok=True, step=3))
        assert session.sim_params.temperature_K == 310.0
        states = [m for m in sent(steerer) if isinstance(m, p.State) and m.sim_params]
        assert [s.sim_params.temperature_K for s in states] == [None, None, 310.0]  # type: ignore[union-attr]

    run(body, tmp_path)


def test_steering_without_a_simulation_is_refused_and_logged_nowhere(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        steerer = client("u")
        session.attach(steerer)
        with pytest.raises(p.ProtocolError) as err:
            await session.steer(steerer, p.Control(action="pause"))
        assert err.value.code == p.ErrorCode.NOT_READY
        assert session.services.steering_log.read("s") == []

    run(body, tmp_path)


def test_an_invalid_render_patch_names_the_field_and_changes_nothing(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        steerer = client("u")
        session.attach(steerer)
        before = session.render_params
        patch = p.SetRenderParams.model_construct(
            type="render_params", seq=3, params=p.RenderParams.model_construct(sigma_A=-1.0)
        )
        with pytest.raises(p.ProtocolError) as err:
            await session.steer(steerer, patch)
        assert err.value.path == "render_params.params.sigma_A"
        assert session.render_params is before

    run(body, tmp_path)


def test_a_render_change_the_log_cannot_record_changes_nothing(tmp_path: Path) -> None:
    """The steering log is written before the change takes effect: when it fails, the session
    keeps its parameters and tells no one of a change (the caller answers with an error)."""

    async def body(session: Session, backend: PaintBackend) -> None:
        steerer, viewer = client("u"), client("v", "viewer")
        session.attach(steerer)
        session.attach(viewer)
        before = session.render_params
        seen = len(sent(viewer))

        def unreadable(name: str) -> int:
            raise OSError(f"steering log of {name} unreadable")

        session.services.steering_log.next_id = unreadable  # type: ignore[method-assign]
        with pytest.raises(OSError, match="unreadable"):
            await session.steer(steerer, p.SetRenderParams(seq=4, params={"sigma_A": 3.0}))
        assert session.render_params is before
        assert not [m for m in sent(viewer)[seen:] if isinstance(m, p.State)]

    run(body, tmp_path)


def test_a_leaving_puller_releases_its_atoms_for_the_engine(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        sim, user = client("sim", "simulation"), client("u")
        session.attach(sim)
        session.attach(user)
        session.on_topology(topo)
        session.on_frame(frame(pos, 0))
        target = tuple(float(v) + 1.0 for v in pos[2])
        await session.steer(user, p.Pull(seq=1, atom=2, target=target))  # type: ignore[arg-type]
        pulled = [m for m in sent(sim) if isinstance(m, p.Forces)][-1]
        assert pulled.indices.to_numpy().tolist() == [2]
        session.on_frame(frame(pos + np.float32(0.5), 1))  # the spring follows the atom
        followed = [m for m in sent(sim) if isinstance(m, p.Forces)][-1]
        assert not np.allclose(followed.forces.to_numpy(), pulled.forces.to_numpy())
        session.detach(user)
        released = [m for m in sent(sim) if isinstance(m, p.Forces)][-1]
        assert released.indices.count == 0

    run(body, tmp_path)


def test_a_pick_answers_with_the_atom_and_where_it_is(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        a = client("a", "viewer")
        session.attach(a)
        with pytest.raises(p.ProtocolError):
            await session.pick(a, p.Pick(x=1, y=1))
        session.on_topology(topo)
        session.on_frame(frame(pos, 0))
        hit = await session.pick(a, p.Pick(seq=9, x=3, y=4))
        assert hit.ref == 9 and hit.atom == 0 and hit.element == topo.elements[0]
        assert hit.position == pytest.approx(tuple(float(v) for v in pos[0]))
        with pytest.raises(p.ProtocolError, match="outside"):
            await session.pick(a, p.Pick(x=40, y=0))

    run(body, tmp_path)


def test_a_viewer_that_acknowledges_its_jpeg_images_gets_them_paced(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        jpeg, video = client("j", "viewer"), client("v", "viewer")
        session.attach(jpeg)
        session.attach(video)
        session.on_topology(topo)
        session.on_frame(frame(pos, 1))
        await settle(lambda: bool(images(jpeg)))
        assert not jpeg.paced_images  # a script that never acknowledges gets every image
        shown = images(jpeg)[0].frame_id
        video.video_stream = 1  # on a video stream: its acks pace that stream already
        session.on_frame_ack(jpeg, p.FrameAck(frame_id=shown))
        session.on_frame_ack(video, p.FrameAck(frame_id=shown))
        assert jpeg.paced_images and not video.paced_images

    run(body, tmp_path)


def test_a_large_topology_takes_the_heap_out_of_the_collectors_walk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from server import heap

    settled: list[int] = []
    monkeypatch.setattr(heap, "settle", lambda: settled.append(1) or 0.0)
    monkeypatch.setattr(heap, "LARGE_TOPOLOGY", 30)

    async def body(session: Session, backend: PaintBackend) -> None:
        small, _ = molecule(29)
        session.on_topology(small)
        assert settled == []  # a small system: no full collection for it
        large, _ = molecule(30)
        session.on_topology(large)
        assert settled == [1]

    run(body, tmp_path)


def test_renders_for_video_viewers_only_do_not_read_the_rgba_image_back(tmp_path: Path) -> None:
    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        v = client("v", "viewer")
        v.view = p.View(width=40, height=30, video=["h264"])
        session.attach(v)
        session.on_topology(topo)
        session.on_frame(frame(pos, 1))
        await settle(lambda: any(r.snapshot.step == 1 for r in backend.requests))
        first = next(r for r in backend.requests if r.snapshot.step == 1)
        assert first.video_size == (40, 30) and first.rgba is False  # planes will do
        j = client("j", "viewer")  # a JPEG viewer of the same view joins the group
        session.attach(j)
        session.on_frame(frame(pos + np.float32(1.0), 2))
        await settle(lambda: any(r.snapshot.step == 2 for r in backend.requests))
        second = next(r for r in backend.requests if r.snapshot.step == 2)
        assert second.video_size == (40, 30) and second.rgba is True

    run(body, tmp_path)


def test_while_someone_steers_video_streams_at_the_interactive_size(tmp_path: Path) -> None:
    """Between a steerer's changes the view is not interactive, yet its stream keeps the
    interactive size (no keyframe per change): a group of video viewers renders no larger,
    a group with a JPEG viewer renders full size and the stream takes it scaled down."""

    def request(backend: PaintBackend, step: int) -> Any:
        return next(r for r in backend.requests if r.snapshot.step == step)

    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        u, v = client("u"), client("v", "viewer")
        for c in (u, v):
            c.view = p.View(width=40, height=30, video=["h264"])
            session.attach(c)
        session.on_topology(topo)
        session.on_frame(frame(pos, 1))
        await settle(lambda: any(r.snapshot.step == 1 for r in backend.requests))
        first = request(backend, 1)
        assert (first.width, first.height, first.video_size) == (40, 30, (40, 30))
        await session.steer(u, p.SetRenderParams(seq=2, params={"iso_level": 0.3}))  # type: ignore[arg-type]
        await asyncio.sleep(SETTINGS.interactive_idle_s + 0.05)  # no longer interactive
        session.on_frame(frame(pos + np.float32(1.0), 2))
        await settle(lambda: any(r.snapshot.step == 2 for r in backend.requests))
        steering = request(backend, 2)
        assert (steering.width, steering.height, steering.video_size) == (20, 15, (20, 15))
        session.attach(client("j", "viewer"))  # a JPEG viewer of the same view
        await session.steer(u, p.SetRenderParams(seq=3, params={"iso_level": 0.35}))  # type: ignore[arg-type]
        await asyncio.sleep(SETTINGS.interactive_idle_s + 0.05)
        session.on_frame(frame(pos + np.float32(2.0), 3))
        await settle(lambda: any(r.snapshot.step == 3 for r in backend.requests))
        mixed = request(backend, 3)
        assert (mixed.width, mixed.height, mixed.video_size) == (40, 30, (20, 15))

    run(body, tmp_path)


def test_an_adapter_that_starts_paused_is_shown_paused_with_its_first_frame(
    tmp_path: Path,
) -> None:
    """`scalesteer replay --paused` says it starts paused, then sends its first frame: the
    status is paused (it had read `running` until someone paused it again)."""

    async def body(session: Session, backend: PaintBackend) -> None:
        topo, pos = molecule()
        viewer = client("a", "viewer")
        session.attach(viewer)
        # the adapter's connection sends its queued events before its topology
        session.on_event(p.Event(level="info", code="paused", message="starts paused", step=0))
        session.on_topology(topo)
        session.on_frame(frame(pos, 0))
        await settle(lambda: bool(images(viewer)))
        assert session.status.state == "paused" and session.status.step == 0

    run(body, tmp_path)
