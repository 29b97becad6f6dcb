"""The frames of a live session waiting for their movie render.

A movie of a live session (`POST /api/sessions/{id}/movies`) keeps every frame the simulation
sends while it records, each with the render parameters of its moment. Where a render takes
longer than the simulation takes to send the next frame (a CPU device, a large movie), frames
wait here and the movie finishes rendering them after it is stopped; only when the waiting
frames would hold more than `limit_bytes` of positions is a frame skipped, and then at once
counted, listed by step and told (`on_skip`), never dropped silently.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.gpu import Snapshot

MAX_SKIPPED_SPANS = 256
"""Runs of skipped frames listed one by one; later ones extend the last (its count stays true)."""
BEHIND_FRAMES = 8
"""Frames waiting to be rendered from which the movie says it renders slower than the
simulation sends them (once), with what that costs after the stop."""


@dataclass(frozen=True)
class MovieFrame:
    """One frame of the movie: the session's molecule and how it drew it at that moment."""

    snapshot: Snapshot
    params: p.RenderParams
    box: npt.NDArray[np.float32] | None = None

    @property
    def nbytes(self) -> int:
        return int(self.snapshot.positions.nbytes)


@dataclass
class MovieQueue:
    """Frames taken for a movie and not yet rendered, in order; at most `max_frames` are
    taken, and while the waiting ones hold `limit_bytes` the next is skipped."""

    limit_bytes: int
    max_frames: int
    on_skip: Callable[[MovieQueue, int], None] | None = None
    """Called with the step of each skipped frame, as it is skipped."""
    on_behind: Callable[[MovieQueue], None] | None = None
    """Called once, when `BEHIND_FRAMES` frames wait while the movie still takes frames."""
    render_s: float | None = None
    """A movie frame's render time (a running mean), once one is rendered."""
    told_behind: bool = False
    taken: int = 0
    skipped: int = 0
    skipped_spans: list[list[int]] = field(default_factory=list)
    """[first step, last step, frames skipped] of each run of skipped frames."""
    queued_bytes: int = 0
    closed: bool = False
    why_closed: str | None = None
    _frames: deque[MovieFrame] = field(default_factory=deque)
    _arrived: asyncio.Event = field(default_factory=asyncio.Event)
    _last_kept: bool = True
    _on_close: list[Callable[[], None]] = field(default_factory=list)

    def offer(self, frame: MovieFrame) -> bool:
        """Take `frame` (True), or skip it because too many wait (False, told at once); a
        closed queue takes nothing."""
        if self.closed:
            return False
        size = frame.nbytes
        if self._frames and self.queued_bytes + size > self.limit_bytes:
            self._skip(frame.snapshot.step)
            return False
        self._frames.append(frame)
        self.queued_bytes += size
        self.taken += 1
        self._last_kept = True
        self._arrived.set()
        if len(self._frames) >= BEHIND_FRAMES and not self.told_behind:
            self.told_behind = True
            if self.on_behind is not None:
                self.on_behind(self)
        if self.taken >= self.max_frames:
            self.close(f"it reached its {self.max_frames} frames (max_frames)")
        return True

    def _skip(self, step: int) -> None:
        self.skipped += 1
        if not self._last_kept and self.skipped_spans:
            span = self.skipped_spans[-1]
            span[1], span[2] = step, span[2] + 1
        elif len(self.skipped_spans) < MAX_SKIPPED_SPANS:
            self.skipped_spans.append([step, step, 1])
        else:
            span = self.skipped_spans[-1]
            span[1], span[2] = step, span[2] + 1
        self._last_kept = False
        if self.on_skip is not None:
            self.on_skip(self, step)

    def rendered(self, seconds: float) -> None:
        """A frame took `seconds` to render (and encode): the estimate of what waits."""
        self.render_s = seconds if self.render_s is None else 0.8 * self.render_s + 0.2 * seconds

    def behind_notice(self) -> str:
        """What a movie that renders slower than its frames come will cost."""
        each = f"{self.render_s:.2g} s" if self.render_s is not None else "longer"
        return (
            f"{self.waiting} frames wait to be rendered (a movie frame takes {each} here): the "
            "movie keeps every frame and renders those still waiting after it stops taking "
            "frames (a smaller window films faster)"
        )

    def skip_warning(self) -> str | None:
        """What the skipped frames mean (None: none was skipped)."""
        if not self.skipped:
            return None
        return (
            f"{self.skipped} of the {self.taken + self.skipped} frames the session sent are not "
            f"in the movie: the frames waiting to be rendered held "
            f"{self.limit_bytes / (1 << 20):g} MiB (movie_queue_bytes), as this device renders "
            "a movie frame slower than the simulation sends them; the movie keeps every frame "
            "up to each gap in skipped_spans"
        )

    def close(self, why: str) -> None:
        """Take no more frames (the ones waiting are still rendered)."""
        if self.closed:
            return
        self.closed, self.why_closed = True, why
        self._arrived.set()
        hooks, self._on_close = self._on_close, []
        for hook in hooks:
            hook()

    def when_closed(self, hook: Callable[[], None]) -> None:
        """Run `hook` once the queue takes no more frames (now, if it is closed already)."""
        if self.closed:
            hook()
        else:
            self._on_close.append(hook)

    @property
    def waiting(self) -> int:
        return len(self._frames)

    async def next(self) -> MovieFrame | None:
        """The oldest waiting frame, waiting for one; None once closed and empty."""
        while not self._frames:
            if self.closed:
                return None
            self._arrived.clear()
            await self._arrived.wait()
        frame = self._frames.popleft()
        self.queued_bytes -= frame.nbytes
        return frame

    def describe(self) -> dict[str, Any]:
        eta = None if self.render_s is None else round(self.waiting * self.render_s, 1)
        return {
            "taken": self.taken,
            "waiting": self.waiting,
            "render_s": None if self.render_s is None else round(self.render_s, 3),
            "eta_s": eta,
            "skipped": self.skipped,
            "skipped_spans": [list(s) for s in self.skipped_spans],
            "recording": not self.closed,
            "ended_because": self.why_closed,
        }
