"""When a session renders, and at which quality: the image scheduler.

Viewers with the same camera and canvas share one render (a *view group*). A group renders when
what it shows changed (a new frame, new render parameters: the session's `version`) or one of
its members asked for an image. While someone interacts (drags the camera, slides a parameter)
images are rendered smaller and encoded at a lower JPEG quality; a full-quality still follows
once the interaction has paused for `interactive_idle_s`. Bursts coalesce: the scheduler is
asked what is due, never told to render each change. Time comes in as an argument, so the
policy is tested without sleeping.

A frame-time budget keeps slow devices interactive: the scheduler learns what a pixel costs on
this session's device and shrinks every image to what renders in `frame_budget_ms` (the browser
scales it up). When what a reduced image shows stays unchanged for `refine_after_s`, a refined
image follows, within the larger `refine_budget_ms`; when that one stays unchanged for
`final_after_s`, the full-size image follows, shrunk only if it would take longer than
`final_budget_ms` (progressive refinement: a paused simulation on a laptop ends at full
quality, and a density that costs a minute a frame does not hold every change that long). On
a GPU the budget is far above a full-size frame and nothing shrinks.

Video viewers see frames of a stream tuned for motion; when their view rests (what it shows
unchanged for `rest_after_s`) a *rest* render follows, sent to them as a near-lossless JPEG
still, so a picture that stops moving ends sharp. While someone steers a view, its stream is
encoded at the interactive image's size, and a group of video viewers only renders at that
size (*steering*); the stream keeps that size until nobody has interacted for
`video_steer_hold_s`, so steering in bursts does not cost a keyframe per burst.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import protocol as p
from server.session.clients import Client
from server.settings import ServerSettings

MAX_REMEMBERED = 256
"""View groups whose last rendered version is remembered (older ones just render again)."""
HISTOGRAM_INTERVAL_S = 1.0
FINAL = 2
"""The last refinement level: the full-size image, whatever it costs."""
MIN_BUDGET_PIXELS = 160 * 90
"""The budget never shrinks an image below this (a coarse image still shows the molecule)."""
MAGNIFIED_JPEG_QUALITY = 92
"""The least JPEG quality of an image the browser scales up twice or more: its blocks grow with
it (a 8x8 block of a 4:2:0 chroma plane, scaled 4x, is a 64-pixel tile of colour); a budget
image of 20,000 pixels (villin) takes 3.5 KB at it, 2.4 KB at 85."""


@dataclass(frozen=True)
class ViewKey:
    """A view group: what its members see and whether it is an interactive (reduced) view."""

    camera_json: str
    width: int
    height: int
    interactive: bool
    refine: int = 0
    """Refinement level of a budget-reduced image: 0 none, 1 within the refine budget,
    `FINAL` at full size."""
    rest: bool = False
    """The still that ends a resting video view (sent as a high-quality JPEG)."""

    @property
    def camera(self) -> p.Camera:
        return p.Camera.model_validate_json(self.camera_json)


@dataclass
class Plan:
    """What to render now: groups with their members, and when to come back for stills."""

    groups: list[tuple[ViewKey, list[Client]]]
    come_back_in: float | None = None


def _steered(members: list[Client]) -> bool:
    """Whether a steerer is among a view's members."""
    return any(c.role == "steerer" for c in members)


@dataclass
class FrameCost:
    """What one pixel costs to render on this device (an exponential moving average of
    measured renders), and so how many pixels fit in a time budget."""

    ms_per_px: float | None = None
    weight: float = 0.3

    def note(self, pixels: int, ms: float) -> None:
        if pixels < 1024 or not ms > 0:  # tiny renders are dominated by fixed costs
            return
        sample = ms / pixels
        self.ms_per_px = (
            sample
            if self.ms_per_px is None
            else (1 - self.weight) * self.ms_per_px + self.weight * sample
        )

    def pixels_within(self, budget_ms: float) -> int | None:
        """Pixels that render in `budget_ms`; None while nothing was measured."""
        if self.ms_per_px is None or budget_ms <= 0:
            return None
        return max(1, int(budget_ms / self.ms_per_px))


@dataclass
class RenderScheduler:
    settings: ServerSettings
    _rendered: dict[ViewKey, int] = field(default_factory=dict)
    _interactive_until: float = 0.0
    _last_histogram: float = float("-inf")
    cost: FrameCost = field(default_factory=FrameCost)
    _quality: float = 1.0
    _reduced: dict[ViewKey, tuple[int, float, int]] = field(default_factory=dict)
    """Groups whose last image was shrunk by the budget: (version, when, refinement level)."""
    _video: dict[ViewKey, tuple[int, float, int]] = field(default_factory=dict)
    """Groups whose last full image went to video viewers: (version, when, refinement level),
    until their rest still is rendered."""
    _interacted_at: float = float("-inf")
    """When the shared render parameters last changed (monotonic seconds)."""

    def interacting(self, now: float) -> None:
        """Shared render parameters changed: every view is interactive for a moment."""
        self._interactive_until = now + self.settings.interactive_idle_s
        self._interacted_at = now

    def steering(self, members: Iterable[Client], now: float) -> bool:
        """Whether a group's video stream is at its steering size: the shared parameters
        changed, or one of its members sent an interacting view, within `video_steer_hold_s`.
        (Interactive renders come and go between a user's changes; the stream's size, which
        changes only at a keyframe, holds for the whole burst of them.)"""
        hold = self.settings.video_steer_hold_s
        if hold <= 0:
            return False
        last = max([self._interacted_at, *(c.interacted_at for c in members)])
        return now - last < hold

    def view_of(self, client: Client, default_camera: p.Camera | None) -> tuple[p.Camera, int, int]:
        camera = default_camera or p.Camera()
        if client.view is not None:
            return client.view.camera or camera, client.view.width, client.view.height
        w, h = self.settings.default_size
        return camera, w, h

    def groups(
        self, clients: Iterable[Client], now: float, default_camera: p.Camera | None
    ) -> dict[ViewKey, list[Client]]:
        out: dict[ViewKey, list[Client]] = {}
        for client in clients:
            camera, w, h = self.view_of(client, default_camera)
            interactive = now < self._interactive_until or now < client.interacting_until
            key = ViewKey(camera.model_dump_json(), w, h, interactive)
            out.setdefault(key, []).append(client)
        return out

    def plan(
        self,
        clients: Iterable[Client],
        now: float,
        version: int,
        default_camera: p.Camera | None,
    ) -> Plan:
        """The groups due for a render of `version`; a group is due when it has not drawn that
        version yet or a member needs an image. In a session with a steerer: every view a
        steerer is in, then at most `viewer_views_per_pass` others, the longest unserved first
        (the rest stay due: the plan says to come back at once). Members are marked served here
        (a view that arrives during the render marks its client again)."""
        due: list[tuple[ViewKey, list[Client]]] = []
        interactive = False
        refine_in: float | None = None
        more = False
        ordered = self._by_priority(self.groups(clients, now, default_camera))
        # with a steerer in the session, other views take turns; without, a pass renders
        # them all from one frame (one upload and grid, the same step in every view)
        cap = self.settings.viewer_views_per_pass if any(_steered(m) for _, m in ordered) else None
        for key, members in ordered:
            interactive = interactive or key.interactive
            others = sum(1 for _, planned in due if not _steered(planned))
            if cap is not None and not _steered(members) and others >= cap:  # left for later
                more = more or self._due(key, members, version)
                continue
            if self._rendered.get(key) == version and not any(c.needs_image for c in members):
                reduced = self._reduced.get(key)
                if reduced is None or reduced[0] != version or key.interactive:
                    shown = self._video.get(key)
                    if shown is None or shown[0] != version or key.interactive:
                        continue
                    wait = self.settings.rest_after_s - (now - shown[1])
                    if wait > 0:
                        refine_in = wait if refine_in is None else min(refine_in, wait)
                        continue
                    del self._video[key]
                    due.append((replace(key, refine=shown[2], rest=True), members))
                    continue
                after = (
                    self.settings.refine_after_s if reduced[2] == 0 else self.settings.final_after_s
                )
                wait = after - (now - reduced[1])
                if wait > 0:  # not yet: come back when it is due
                    refine_in = wait if refine_in is None else min(refine_in, wait)
                    continue
                del self._reduced[key]
                due.append((replace(key, refine=reduced[2] + 1), members))
                continue
            for c in members:
                c.needs_image = False
            due.append((key, members))
        for _, members in due:
            for c in members:
                c.served_at = now
        come_back = self.settings.interactive_idle_s + 0.01 if interactive else None
        if refine_in is not None:
            come_back = min(come_back or refine_in, refine_in) + 0.01
        if more:
            come_back = 0.0
        return Plan(due, come_back)

    @staticmethod
    def _by_priority(
        groups: dict[ViewKey, list[Client]],
    ) -> list[tuple[ViewKey, list[Client]]]:
        """Groups with a steerer first, then the one whose members have waited longest."""

        def rank(item: tuple[ViewKey, list[Client]]) -> tuple[bool, float]:
            members = item[1]
            return (not _steered(members), min(c.served_at for c in members))

        return sorted(groups.items(), key=rank)

    def _due(self, key: ViewKey, members: list[Client], version: int) -> bool:
        """Whether a group has a version it has not drawn or a member waiting for an image (a
        refinement or rest still to come has a timer of its own)."""
        return self._rendered.get(key) != version or any(c.needs_image for c in members)

    def rendered(self, key: ViewKey, version: int) -> None:
        if len(self._rendered) >= MAX_REMEMBERED:
            self._rendered.clear()
        self._rendered[replace(key, refine=0, rest=False)] = version

    def video_shown(self, key: ViewKey, version: int, now: float) -> None:
        """A group's image went to video viewers: once it rests, its still is due. Images
        still to be refined (and the rest still itself) wait for nothing."""
        base = replace(key, refine=0, rest=False)
        if key.rest or key.interactive or base in self._reduced:
            self._video.pop(base, None)
            return
        if len(self._video) >= MAX_REMEMBERED:
            self._video.clear()
        self._video[base] = (version, now, key.refine)

    def note_render(
        self,
        key: ViewKey,
        version: int,
        size: tuple[int, int],
        ms: float,
        now: float,
        budget_size: tuple[int, int] | None = None,
    ) -> bool:
        """Learn from a render; True when its size was shrunk by the budget (the next
        refinement is then due once the group's image stays unchanged for a while).
        `budget_size`: what `image_size` gave, when the render was smaller still for another
        reason (a steering stream's size): the refinements follow as they would have."""
        self.cost.note(size[0] * size[1], ms)
        base = replace(key, refine=0, rest=False)
        wanted = self._wanted_size(key)
        shown = budget_size or size
        if key.refine < FINAL and shown[0] * shown[1] < wanted[0] * wanted[1]:
            if len(self._reduced) >= MAX_REMEMBERED:
                self._reduced.clear()
            self._reduced[base] = (version, now, key.refine)
            return True
        self._reduced.pop(base, None)
        return False

    def forget(self, key: ViewKey) -> None:
        """Render this group again on the next pass (its image was lost)."""
        self._rendered.pop(key, None)

    def _wanted_size(self, key: ViewKey, quality: float | None = None) -> tuple[int, int]:
        if quality is None:
            quality = self._quality
        scale = quality * (self.settings.interactive_scale if key.interactive else 1.0)
        return max(1, round(key.width * scale)), max(1, round(key.height * scale))

    def _limited(self, rw: int, rh: int, pixels: int) -> tuple[int, int]:
        shrink = min(
            1.0, self.settings.limits.max_image_side / max(rw, rh), (pixels / (rw * rh)) ** 0.5
        )
        return max(1, int(rw * shrink)), max(1, int(rh * shrink))

    def stream_size(
        self, key: ViewKey, quality: float, on_cpu: bool = False, steering: bool = False
    ) -> tuple[int, int]:
        """The size a video stream of this group encodes at: the canvas times the quality
        within the server's limits (the interactive image's size while `steering`), never
        shrunk by the frame budget or a single interactive render (a stream changes size only
        with a keyframe)."""
        base = replace(key, interactive=steering)
        rw, rh = self._wanted_size(base, quality)
        pixels = self.settings.limits.max_image_pixels
        if on_cpu:
            pixels = min(pixels, self.settings.cpu_max_live_pixels)
        return self._limited(rw, rh, pixels)

    def image_size(self, key: ViewKey, quality: float, on_cpu: bool = False) -> tuple[int, int]:
        """Pixels to render for a group: its canvas times the quality (halved, by default,
        while interacting), shrunk to the server's image limits, on the CPU device to
        `cpu_max_live_pixels` (one huge canvas must not hold every session's renders for
        seconds), and to what the frame-time budget affords (the refine budget for a
        refinement). The browser scales the image up to the canvas."""
        self._quality = quality
        rw, rh = self._wanted_size(key, quality)
        lim = self.settings.limits
        pixels = lim.max_image_pixels
        if on_cpu:
            pixels = min(pixels, self.settings.cpu_max_live_pixels)
        settings = self.settings
        budget = (settings.frame_budget_ms, settings.refine_budget_ms, settings.final_budget_ms)
        affordable = self.cost.pixels_within(budget[min(key.refine, FINAL)])
        if affordable is not None:
            pixels = min(pixels, max(affordable, MIN_BUDGET_PIXELS))
        return self._limited(rw, rh, pixels)

    def pick_size(self, width: int, height: int) -> tuple[int, int]:
        """The size a pick renders at: the view's, shrunk to what the frame budget affords,
        so picking answers as fast as a frame renders."""
        affordable = self.cost.pixels_within(self.settings.frame_budget_ms)
        if affordable is None or width * height <= affordable:
            return width, height
        shrink = (max(affordable, MIN_BUDGET_PIXELS) / (width * height)) ** 0.5
        return max(1, int(width * shrink)), max(1, int(height * shrink))

    def jpeg_quality(
        self, key: ViewKey, params: p.RenderParams, size: tuple[int, int] | None = None
    ) -> int:
        """The JPEG quality of a group's image: a resting video view's still at
        `rest_jpeg_quality`; the interactive one while interacting, else the parameters'; an
        image of `size` the browser scales up twice or more (the CPU's frame budget) at least
        `MAGNIFIED_JPEG_QUALITY`, whose 4:4:4 chroma and finer steps keep its 8-pixel blocks
        from showing as 16-pixel or larger tiles of colour. Asked before the render: a render
        lane that encodes its JPEG itself encodes it at this quality."""
        if key.rest:
            return self.settings.rest_jpeg_quality
        quality = self.settings.interactive_jpeg_quality if key.interactive else params.jpeg_quality
        if size is not None and 4 * size[0] * size[1] <= key.width * key.height:
            quality = max(quality, MAGNIFIED_JPEG_QUALITY)
        return quality

    def histogram_due(self, key: ViewKey, now: float) -> bool:
        """Whether this render also measures the density histogram: stills, once a second."""
        if key.interactive or now - self._last_histogram <= HISTOGRAM_INTERVAL_S:
            return False
        self._last_histogram = now
        return True
