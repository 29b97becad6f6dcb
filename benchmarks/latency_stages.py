"""Where a steer's "queue" time goes inside the server: timestamps along one change's path.

`latency_bench.py --stages` runs its latency part with these marks in place. The server runs in
the benchmark's own process (`ServerThread`), so the marks wrap its methods there; nothing in
the server knows of them. Per change, from the steering message to the image packed for the
socket (milliseconds, between consecutive marks):

    steer     the render-parameter change applied (merge, log, state to the viewers)
    wake      until the session's render loop runs
    plan      the loop's plan and snapshot, until the render is asked of the device
    to_thread until the device's thread starts it
    thread    the device's thread (render_ms is part of it; the rest is the request's set-up)
    back      until the loop has the result again
    deliver   until the image is packed (encode_ms is part of it where the host encodes)

A change whose marks are incomplete (another render came between) is left out.
"""

from __future__ import annotations

import contextlib
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from server.pipeline.gpu import GpuQueue
from server.session.delivery import Delivery
from server.session.render_loop import RenderLoop
from server.session.session import Session

MARKS = (
    "steer_in",
    "steer_out",
    "loop",
    "render",
    "thread_in",
    "thread_out",
    "back",
    "packed",
)
STAGES = ("steer", "wake", "plan", "to_thread", "thread", "back", "deliver")
"""Each stage runs from the mark of its index to the next one."""


class Marks:
    """Timestamps of the marks, in the order they happened (any thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.events: list[tuple[str, float]] = []

    def __call__(self, label: str) -> None:
        with self._lock:
            self.events.append((label, time.perf_counter()))

    def changes(self) -> list[dict[str, float]]:
        """One row of stage durations (ms) per change with every mark, in order."""
        rows: list[dict[str, float]] = []
        current: dict[str, float] | None = None
        for label, t in self.events:
            if label == "steer_in":
                current = {"steer_in": t}
                continue
            if current is None or label in current:
                continue
            want = MARKS[len(current)]
            if label != want:
                continue
            current[label] = t
            if len(current) == len(MARKS):
                rows.append(
                    {
                        stage: (current[MARKS[i + 1]] - current[MARKS[i]]) * 1000
                        for i, stage in enumerate(STAGES)
                    }
                )
                current = None
        return rows


def summarise(rows: list[dict[str, float]]) -> dict[str, Any]:
    """p50 / p95 / mean of each stage over the changes."""
    out: dict[str, Any] = {"changes": len(rows)}
    for stage in STAGES:
        vals = np.asarray([r[stage] for r in rows])
        out[stage] = {
            "p50": float(np.percentile(vals, 50)) if len(vals) else float("nan"),
            "p95": float(np.percentile(vals, 95)) if len(vals) else float("nan"),
            "mean": statistics.fmean(vals) if len(vals) else float("nan"),
        }
    return out


def _wrap_async(owner: type, name: str, before: str | None, after: str | None, mark: Marks) -> Any:
    original = getattr(owner, name)

    async def wrapped(*args: Any, **kwargs: Any) -> Any:
        if before:
            mark(before)
        result = await original(*args, **kwargs)
        if after:
            mark(after)
        return result

    setattr(owner, name, wrapped)
    return original


def _wrap_sync(owner: type, name: str, before: str | None, after: str | None, mark: Marks) -> Any:
    original: Callable[..., Any] = getattr(owner, name)

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        if before:
            mark(before)
        result = original(*args, **kwargs)
        if after:
            mark(after)
        return result

    setattr(owner, name, wrapped)
    return original


@contextlib.contextmanager
def traced() -> Iterator[Marks]:
    """The marks in place for the duration (the server's classes as they were after)."""
    mark = Marks()
    wraps = [
        (Session, "_set_render_params", "steer_in", "steer_out", True),
        (RenderLoop, "render_pending", "loop", None, True),
        (RenderLoop, "_render", "render", "back", True),
        (GpuQueue, "render_sync", "thread_in", "thread_out", False),
        (Delivery, "_packer", None, "packed", False),
    ]
    saved = []
    try:
        for owner, name, before, after, is_async in wraps:
            wrap = _wrap_async if is_async else _wrap_sync
            saved.append((owner, name, wrap(owner, name, before, after, mark)))
        yield mark
    finally:
        for owner, name, original in saved:
            setattr(owner, name, original)
