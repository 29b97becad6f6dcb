"""When a session renders, and at which quality: the image scheduler.

Viewers with the same camera and canvas share one render (a *view group*). A group renders when
what it shows changed (a new frame, new render parameters: the session's `version`) or one of
its members asked for an image. While someone interacts (drags the camera, slides a parameter)
images are rendered smaller and encoded at a lower JPEG quality; a full-quality still follows
once the interaction has paused for `interactive_idle_s`. Bursts coalesce: the scheduler is
asked what is due, never told to render each change. Time comes in as an argument, so the
policy is tested without sleeping.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import protocol as p
from server.session.clients import Client
from server.settings import ServerSettings

MAX_REMEMBERED = 256
"""View groups whose last rendered version is remembered (older ones just render again)."""
HISTOGRAM_INTERVAL_S = 1.0


@dataclass(frozen=True)
class ViewKey:
    """A view group: what its members see and whether it is an interactive (reduced) view."""

    camera_json: str
    width: int
    height: int
    interactive: bool

    @property
    def camera(self) -> p.Camera:
        return p.Camera.model_validate_json(self.camera_json)


@dataclass
class Plan:
    """What to render now: groups with their members, and when to come back for stills."""

    groups: list[tuple[ViewKey, list[Client]]]
    come_back_in: float | None = None


@dataclass
class RenderScheduler:
    settings: ServerSettings
    _rendered: dict[ViewKey, int] = field(default_factory=dict)
    _interactive_until: float = 0.0
    _last_histogram: float = float("-inf")

    def interacting(self, now: float) -> None:
        """Shared render parameters changed: every view is interactive for a moment."""
        self._interactive_until = now + self.settings.interactive_idle_s

    def view_of(self, client: Client, default_camera: p.Camera | None) -> tuple[p.Camera, int, int]:
        if client.view is not None:
            return client.view.camera, client.view.width, client.view.height
        w, h = self.settings.default_size
        return default_camera or p.Camera(), w, h

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
        version yet or a member needs an image. Members are marked served here (a view that
        arrives during the render marks its client again)."""
        due: list[tuple[ViewKey, list[Client]]] = []
        interactive = False
        for key, members in self.groups(clients, now, default_camera).items():
            interactive = interactive or key.interactive
            if self._rendered.get(key) == version and not any(c.needs_image for c in members):
                continue
            for c in members:
                c.needs_image = False
            due.append((key, members))
        come_back = self.settings.interactive_idle_s + 0.01 if interactive else None
        return Plan(due, come_back)

    def rendered(self, key: ViewKey, version: int) -> None:
        if len(self._rendered) >= MAX_REMEMBERED:
            self._rendered.clear()
        self._rendered[key] = version

    def forget(self, key: ViewKey) -> None:
        """Render this group again on the next pass (its image was lost)."""
        self._rendered.pop(key, None)

    def image_size(self, key: ViewKey, quality: float, on_cpu: bool = False) -> tuple[int, int]:
        """Pixels to render for a group: its canvas times the quality (halved, by default,
        while interacting), shrunk to the server's image limits, and on the CPU device to
        `cpu_max_live_pixels` (one huge canvas must not hold every session's renders for
        seconds; the browser scales the image up)."""
        scale = quality * (self.settings.interactive_scale if key.interactive else 1.0)
        rw, rh = max(1, round(key.width * scale)), max(1, round(key.height * scale))
        lim = self.settings.limits
        pixels = lim.max_image_pixels
        if on_cpu:
            pixels = min(pixels, self.settings.cpu_max_live_pixels)
        shrink = min(1.0, lim.max_image_side / max(rw, rh), (pixels / (rw * rh)) ** 0.5)
        return max(1, int(rw * shrink)), max(1, int(rh * shrink))

    def jpeg_quality(self, key: ViewKey, params: p.RenderParams) -> int:
        return self.settings.interactive_jpeg_quality if key.interactive else params.jpeg_quality

    def histogram_due(self, key: ViewKey, now: float) -> bool:
        """Whether this render also measures the density histogram: stills, once a second."""
        if key.interactive or now - self._last_histogram <= HISTOGRAM_INTERVAL_S:
            return False
        self._last_histogram = now
        return True
