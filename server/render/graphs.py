"""Launch sequences replayed as CUDA graphs: the renderer's frame and the periodic steps.

A sequence is named by a key that holds everything its launches read by address or value. One
seen among the last few calls is captured once and from then on replayed with one call, which
removes the host's cost per launch (most of a small molecule's frame, and of the periodic steps).
A capture that fails turns graphs off for good: the launches then run one by one, as they would
without a graph.
"""

from __future__ import annotations

import logging
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

import warp

wp: Any = warp  # warp's host API is unannotated
log = logging.getLogger(__name__)

T = TypeVar("T")


class GraphCache:
    """The graphs of one device's launch sequences, the least recently used dropped past
    `size`; `what` names them in the warning a failed capture logs."""

    def __init__(self, device: str, size: int, enabled: bool, what: str) -> None:
        self.device = device
        self.size = size
        self.what = what
        self._graphs: OrderedDict[Hashable, Any] | None = OrderedDict() if enabled else None
        self._recent: deque[Hashable] = deque(maxlen=size)
        self.replays = 0
        """Calls that replayed a graph."""
        self.last_replayed = False
        """Whether the last call replayed a graph."""

    @property
    def enabled(self) -> bool:
        """Graphs are captured and replayed (off when asked, or after a capture failed)."""
        return self._graphs is not None

    def clear(self) -> None:
        """Forget every graph: they hold the addresses of buffers that were reallocated."""
        if self._graphs is not None:
            self._graphs.clear()
        self._recent.clear()
        self.last_replayed = False

    def run(self, key: Hashable, launch: Callable[[], T]) -> T | None:
        """Run the launches `key` names: replay their graph (None), capture it first when the
        same key came among the last `size` calls, else launch them (their result)."""
        graphs = self._graphs
        self.last_replayed = False
        if graphs is None:
            return launch()
        graph = graphs.get(key)
        if graph is None and key in self._recent:
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                    launch()
            except Exception as exc:  # any capture failure: launch one by one from now on
                log.warning("%s: graph capture failed, launching one by one: %s", self.what, exc)
                self._graphs = None
                self._recent.clear()
                return launch()
            graph = graphs[key] = cap.graph
            while len(graphs) > self.size:
                graphs.pop(next(iter(graphs)))
        self._recent.append(key)
        if graph is None:
            return launch()
        graphs.move_to_end(key)
        wp.capture_launch(graph)
        self.replays += 1
        self.last_replayed = True
        return None
