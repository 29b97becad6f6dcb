"""The session's render loop: when the session changes, render what its viewers are due (the
`RenderScheduler` says which view groups, at which size and quality), then hand each image to
`Delivery`. It talks to its session through `RenderHost` (what it reads, what it tells it) and
to the GPU through `services.RenderBackend`, so its decisions are tested without either.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.gpu import RenderOutput, RenderRequest, Snapshot
from server.render.errors import CapacityError, RenderError
from server.render.layerplan import LayerPlan
from server.session.clients import Client
from server.session.delivery import Delivery, Rendered
from server.session.scheduler import RenderScheduler, ViewKey
from server.session.services import Services
from server.settings import ServerSettings

log = logging.getLogger("scalesteer.session")

REFUSAL_REPEAT_S = 10.0
"""A render refused for the same reason is told to the clients again after this long (a viewer
that joins meanwhile hears it then), not on every pass."""
FAILED_RENDER_PAUSE_S = 0.5
"""After a render raised, the loop waits this long before it looks again (a render that keeps
failing does not spin, and its error reaches the viewers once a pass)."""

FPS_WINDOW_S = 2.0
"""Renders per second are counted over this window (the stats message's `render_fps`)."""


@dataclass(frozen=True)
class Scene:
    """What a snapshot is drawn with: its layers (None: every atom, the default style)."""

    layers: tuple[LayerPlan, ...] | None


class RenderHost(Protocol):
    """What the render loop reads from its session, and what it tells it."""

    @property
    def clients(self) -> Mapping[str, Client]: ...

    @property
    def camera(self) -> p.Camera | None:
        """The session's camera (a view without one of its own shares it)."""

    @property
    def render_params(self) -> p.RenderParams: ...

    @property
    def version(self) -> int:
        """Counts every change to what the session draws."""

    def can_render(self) -> bool:
        """Whether there is a molecule to draw (a topology and a frame)."""

    def take_snapshot(self) -> Snapshot | None:
        """The molecule as it is now, for one pass; the newest frame counts as taken."""

    def scene(self, snap: Snapshot) -> Scene | None:
        """What `snap` is drawn with, its legend sent; None when it cannot be drawn now (a new
        topology arrived since, or a layer's atoms are still being evaluated: the session marks
        the loop dirty once they are)."""

    def broadcast(self, message: p.Message) -> None: ...

    def take_back_render_params(self, params: p.RenderParams, why: str) -> bool:
        """Go back to `params`, the last the session drew, because its present ones are too
        large to draw here (`why`); False when nothing changed."""


class RenderLoop:
    """Renders a session's due view groups each time it is marked dirty."""

    def __init__(
        self,
        host: RenderHost,
        session_id: str,
        slot: str,
        settings: ServerSettings,
        services: Services,
        scheduler: RenderScheduler,
        delivery: Delivery,
    ) -> None:
        self.host = host
        self.session_id = session_id
        self.slot = slot
        self.settings = settings
        self.services = services
        self.scheduler = scheduler
        self.delivery = delivery
        self.render_count = 0
        self.last_timings: dict[str, float] = {}
        self.histogram: npt.NDArray[np.float32] | None = None
        """The last histogram of the density a still came with."""
        self._render_times: list[float] = []
        self._image_ids = itertools.count(1)
        self._dirty = asyncio.Event()
        self._drawn: tuple[p.RenderParams, p.Topology] | None = None
        """The render parameters and the molecule of the last image drawn."""
        self._refused: tuple[p.RenderParams, p.Topology] | None = None
        """Those of the last render refused as too large for this server."""
        self._told: tuple[str, float] = ("", -math.inf)
        """The reason of the last refusal told to the clients (its numbers left out: they change
        frame by frame) and when; the same reason is told again only after `REFUSAL_REPEAT_S`."""

    def start(self) -> asyncio.Task[None]:
        return asyncio.create_task(self.run(), name=f"render-{self.session_id}")

    def mark_dirty(self) -> None:
        self._dirty.set()

    def mark_dirty_later(self, delay_s: float) -> None:
        """Look for due renders again after `delay_s` (a refinement coming due)."""
        asyncio.get_running_loop().call_later(delay_s, self.mark_dirty)

    def fps(self, now: float) -> float:
        """Renders per second over the last `FPS_WINDOW_S`."""
        self._render_times = [t for t in self._render_times if now - t < FPS_WINDOW_S]
        return len(self._render_times) / FPS_WINDOW_S

    async def run(self) -> None:
        """Until cancelled: wait for a change, render what it made due. A render that raises
        is logged and reported to every client (a refusal with its reason), and the loop goes
        on."""
        while True:
            await self._dirty.wait()
            self._dirty.clear()
            try:
                await self.render_pending()
            except asyncio.CancelledError:
                raise
            except RenderError as exc:  # what was sent cannot be drawn here: say what
                now = time.monotonic()
                said, when = self._told
                reason = re.sub(r"[0-9.]+", "#", str(exc))  # frame by frame, counts change
                took_back = self._take_back(exc)
                if took_back or reason != said or now - when >= REFUSAL_REPEAT_S:
                    log.warning("render refused in session %s: %s", self.session_id, exc)
                    # too large for this server (valid input), or parameters it cannot draw
                    code = (
                        p.ErrorCode.TOO_LARGE
                        if isinstance(exc, CapacityError)
                        else p.ErrorCode.INVALID_MESSAGE
                    )
                    text = f"render refused: {exc}"
                    if took_back:
                        text += "; the session went back to the parameters it last drew"
                    self.host.broadcast(p.Error(code=code, message=text))
                    self._told = (reason, now)
                if took_back:  # what it went back to is drawn again, for every view
                    self.mark_dirty()
                await asyncio.sleep(FAILED_RENDER_PAUSE_S)
            except Exception:
                log.exception("render failed in session %s", self.session_id)
                self.host.broadcast(
                    p.Error(code=p.ErrorCode.INTERNAL, message="render failed; see the server log")
                )
                await asyncio.sleep(FAILED_RENDER_PAUSE_S)

    def _take_back(self, exc: RenderError) -> bool:
        """A steer made the session's parameters too large to draw here (a refusal of the
        parameters in effect, which differ from those of the last image): the session goes
        back to those, so its controls show what its images show. A molecule that grew too
        large for unchanged parameters is only refused."""
        refused, drawn = self._refused, self._drawn
        if not isinstance(exc, CapacityError) or refused is None or drawn is None:
            return False
        (params, molecule), (drawn_params, drawn_molecule) = refused, drawn
        if molecule is not drawn_molecule:  # a new molecule: the size may be its own
            return False
        if params != self.host.render_params or params == drawn_params:
            return False
        return self.host.take_back_render_params(drawn_params, str(exc))

    async def render_pending(self) -> None:
        """One pass: every view group the scheduler finds due, each rendered once."""
        host = self.host
        if not host.can_render() or not host.clients:
            return
        now = time.monotonic()
        plan = self.scheduler.plan(host.clients.values(), now, host.version, host.camera)
        taken: list[Snapshot] = []  # the snapshot of this pass, taken when its first render starts
        drew = False
        for key, members in plan.groups:
            planned = {c.client_id: (c.view, c.view_ref) for c in members}
            version = await self._render_group(key, members, planned, taken)
            if version is not None:
                drew = True
                self.scheduler.rendered(key, version)
                if any(c.video_stream is not None for c in members):
                    self.scheduler.video_shown(key, version, time.monotonic())
                    if not key.rest:  # its rest still is due if nothing changes until then
                        self.mark_dirty_later(self.settings.rest_after_s + 0.01)
        if plan.come_back_in == 0.0 and not drew:
            return  # views left for the next pass, but nothing could be drawn: the session
            # marks the loop dirty when it can (layers evaluated, a new frame)
        if plan.come_back_in is not None:  # the full-quality still once the interaction pauses
            asyncio.get_running_loop().call_later(plan.come_back_in, self.mark_dirty)

    async def _render_group(
        self,
        key: ViewKey,
        members: list[Client],
        planned: dict[str, tuple[p.View | None, int | None]],
        taken: list[Snapshot],
    ) -> int | None:
        """Render one view group, then leave its encoding and delivery to a task of its own.
        Returns the version rendered (None: nothing was).

        The encode slot is taken before the snapshot, so a render waiting for a free encoder
        renders the newest frame once it gets one; the other groups of the same pass render
        that same snapshot (`taken`), so its upload and grid serve them all.
        """
        slots = self.services.encode_slots
        await slots.acquire()
        # the change each image shows: the render parameters are read as the render starts,
        # right after this, so a steer since the plan counts; a member that sent a new view
        # since the plan keeps the planned ref (the image shows the planned camera)
        refs = {
            c.client_id: c.view_ref
            if c.view is planned[c.client_id][0]
            else planned[c.client_id][1]
            for c in members
        }
        try:
            if not taken:
                snap = self.host.take_snapshot()
                if snap is not None:
                    taken.append(snap)
            codecs = [self.delivery.streams.codec_for(c) for c in members]
            video = not key.rest and any(codecs)
            video_only = video and all(codecs)  # no JPEG viewer: no RGBA image needed
            steering = video and self.scheduler.steering(members, time.monotonic())
            rendered = (
                await self._render(key, taken[0], video, video_only, steering) if taken else None
            )
        except BaseException:
            slots.release()
            raise
        if rendered is None:
            slots.release()
            return None
        self.delivery.start(rendered, members, refs, lambda: self.scheduler.forget(key))
        return taken[0].version

    async def _render(
        self,
        key: ViewKey,
        snap: Snapshot,
        video: bool = False,
        video_only: bool = False,
        steering: bool = False,
    ) -> Rendered | None:
        """One render of `snap` for a view group; None when the host cannot draw it now (a new
        topology arrived since the snapshot was taken: the next pass renders that one).
        `video`: a member takes it as a video frame (the device then also converts it for the
        encoder); `video_only`: every member does (the RGBA image need not come back);
        `steering`: the group's stream is at its steering size (`RenderScheduler.steering`),
        and a group of video viewers only renders no larger than that."""
        scene = self.host.scene(snap)
        if scene is None:
            return None
        params = self.host.render_params
        device = self.services.backend.device_name
        on_cpu = device.startswith("cpu")
        width, height = self.scheduler.image_size(key, params.quality, on_cpu)
        stream_size = self.scheduler.stream_size(key, params.quality, on_cpu, steering)
        budget_size = (width, height)
        steered = (
            video_only
            and steering
            and key.refine == 0  # a refinement is for the picture at rest: drawn as it was
            and stream_size[0] * stream_size[1] < width * height
        )
        if steered:  # every member takes the stream: more pixels would be scaled away
            width, height = stream_size
        now = time.monotonic()
        quality = self.scheduler.jpeg_quality(key, params, (width, height))
        request = RenderRequest(
            slot=self.slot,
            snapshot=snap,
            params=params,
            camera=key.camera,
            width=width,
            height=height,
            histogram=self.scheduler.histogram_due(key, now),
            layers=scene.layers,
            video_size=stream_size if video else None,
            rgba=not video_only,
            jpeg_quality=None if video_only else quality,
        )
        try:
            out: RenderOutput = await self.services.backend.render(request)
        except CapacityError:
            self._refused = (params, snap.topology)
            raise
        self._drawn = (params, snap.topology)
        reduced = self.scheduler.note_render(
            key,
            snap.version,
            (width, height),
            out.timings.get("total", 0.0),
            time.monotonic(),
            budget_size=budget_size,
        )
        if reduced:
            after = self.settings.refine_after_s if key.refine == 0 else self.settings.final_after_s
            self.mark_dirty_later(after + 0.01)
        if out.histogram is not None:
            self.histogram = out.histogram
        self.render_count += 1
        self.last_timings = out.timings
        self._render_times.append(time.monotonic())
        metrics = self.services.metrics
        metrics.frames_rendered.inc()
        metrics.render_ms.observe(out.timings.get("total", 0.0))
        return Rendered(
            out,
            next(self._image_ids),
            snap.step,
            width,
            height,
            quality,
            not key.interactive and not reduced and not steered,
            camera_json=key.camera_json,
            stream_size=stream_size,
            rest=key.rest,
        )
