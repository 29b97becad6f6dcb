"""Settling the heap: one collection, then everything alive leaves the collector's walk."""

from __future__ import annotations

import gc

from server import heap


def test_settle_collects_garbage_and_freezes_what_is_alive() -> None:
    class Node:
        def __init__(self) -> None:
            self.me = self  # a reference cycle: only the collector frees it

    gc.unfreeze()
    try:
        Node()  # garbage already
        kept = [Node() for _ in range(100)]
        before = len(gc.get_objects())
        ms = heap.settle()
        assert ms >= 0.0
        assert gc.get_freeze_count() >= 100  # `kept` and everything else alive is frozen
        assert len(gc.get_objects()) < before  # the collector walks none of it now
        assert not any(type(o) is Node for o in gc.get_objects())
        assert len(kept) == 100
    finally:
        gc.unfreeze()
