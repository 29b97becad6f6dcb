"""Selection workers: answers equal to evaluating here; a worker past its time or memory is
killed, its caller told the limit, and a fresh worker (with the topology again) serves what
follows; workers end with the process that started them, also when it is killed."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from structures.selection import SelectionError, Selector
from structures.selection_cost import SelectionLimits
from structures.selection_pool import (
    FairQueue,
    PoolLimits,
    SelectionBusyError,
    SelectionPool,
    _Task,
)
from tests.structures.test_selection_cost import backbone

pytest.importorskip("MDAnalysis")

ROOT = Path(__file__).resolve().parents[2]
UNPRICED = SelectionLimits(max_pairs=10**15)
"""An estimate that lets everything through: what it misses meets the worker's limits."""
SLOW = "around 5 (" * 30 + "name CA" + ")" * 30
"""About half a minute of MDAnalysis on 40,000 atoms."""


def gone(pid: int, within: float = 10.0) -> bool:
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # reaped by its parent, or a zombie of a dead one
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return True
        except OSError:
            return True
        time.sleep(0.05)
    return False


@pytest.fixture
def pool() -> Iterator[SelectionPool]:
    pool = SelectionPool(
        PoolLimits(workers=1, timeout_s=2.0, memory_bytes=400 * 2**20, selection=UNPRICED)
    )
    yield pool
    pool.close()


def test_answers_equal_evaluating_here() -> None:
    topo, pos = backbone(4000)
    here = Selector(topo)
    pool = SelectionPool(PoolLimits(workers=2))
    try:
        held = pool.hold(topo)
        texts = ["name CA", "around 4 index 0:9", "byres around 3 index 100", "not name C"]
        found = held.evaluate(texts, pos, positions_key=1)
        for text, atoms in zip(texts, found, strict=True):
            assert np.array_equal(atoms, here.select(text, pos)), text  # type: ignore[arg-type]
        counts = held.submit(texts, pos, positions_key=1, counts=True).result()
        assert counts == [len(a) for a in found]  # type: ignore[arg-type]
        # moved atoms: new positions, new answer
        moved = pos + np.float32(50.0) * (np.arange(len(pos)) == 5)[:, None]
        again = held.evaluate(["around 4 index 5"], moved, positions_key=2)[0]
        assert np.array_equal(again, here.select("around 4 index 5", moved))  # type: ignore[arg-type]
        bad = held.evaluate(["name CA and"])[0]
        assert isinstance(bad, SelectionError) and bad.position == len("name CA and")
        held.release()
    finally:
        pool.close()


def test_a_selection_past_its_time_is_killed_and_the_worker_replaced(
    pool: SelectionPool,
) -> None:
    topo, pos = backbone(40_000)
    held = pool.hold(topo)
    assert held.submit(["name CA"], counts=True).result() == [10_000]
    (first,) = pool.pids()
    with pytest.raises(SelectionError) as info:
        held.evaluate([SLOW], pos)
    assert info.value.limit == "selection_timeout_s" and "longer than 2 s" in info.value.reason
    assert gone(first) and pool.kills == 1
    # the topology is given again to the new worker, unasked
    assert held.submit(["name CA"], counts=True).result() == [10_000]
    assert pool.pids() and pool.pids()[0] != first


def test_a_selection_past_its_memory_is_stopped_and_the_worker_replaced(
    pool: SelectionPool,
) -> None:
    topo, pos = backbone(40_000)
    held = pool.hold(topo)
    assert held.submit(["name CA"], counts=True).result() == [10_000]
    (first,) = pool.pids()
    with pytest.raises(SelectionError) as info:
        held.evaluate(["same x as all"], pos)  # 40,000 x 40,000 comparisons held at once
    assert info.value.limit == "selection_memory_bytes" and "400 MiB" in info.value.reason
    assert gone(first)
    assert held.submit(["name CA"], counts=True).result() == [10_000]


def test_a_full_queue_refuses_at_once() -> None:
    limits = PoolLimits(workers=1, timeout_s=1.0, max_waiting=1, selection=UNPRICED)
    small = SelectionPool(limits)
    try:
        topo, pos = backbone(40_000)
        held = small.hold(topo)
        futures = [held.submit([SLOW], pos, positions_key=1) for _ in range(4)]
        busy = [f for f in futures if isinstance(f.exception(timeout=60), SelectionBusyError)]
        assert busy, "every request was queued"
        for f in futures:  # the others ran to their limit: none is left waiting
            error = f.exception(timeout=60)
            assert isinstance(error, SelectionError)
    finally:
        small.close()


def test_one_owners_costly_selections_cannot_hold_the_worker_from_others() -> None:
    """One client typing costly (but allowed) selections one after another kept the workers every
    session shares busy: each owner now has `owner_seconds_per_min` of worker time."""
    limits = PoolLimits(workers=1, timeout_s=1.0, owner_seconds_per_min=1.5, selection=UNPRICED)
    shared = SelectionPool(limits)
    try:
        topo, pos = backbone(40_000)
        held = shared.hold(topo)
        assert held.submit(["name CA"], counts=True, owner="other").result() == [10_000]
        refused, ran = None, 0
        while refused is None and ran < 10:  # each runs to the 1 s limit and is charged for it
            error = held.submit([SLOW], pos, positions_key=1, owner="greedy").exception(60)
            if isinstance(error, SelectionBusyError):
                refused = error
            else:
                assert isinstance(error, SelectionError), error
                assert error.limit == "selection_timeout_s"
                ran += 1
        assert refused is not None and 1 <= ran <= 2, ran  # refused once 1.5 s are used
        assert "selection_seconds_per_min" in refused.reason
        assert shared.used_s("greedy") >= 1.5 and shared.used_s("other") < 1.5
        # the control: another owner is answered, as is work charged to no one
        assert held.submit(["name CA"], counts=True, owner="other").result() == [10_000]
        assert held.submit(["name CA"], counts=True).result() == [10_000]
        # the time is earned back a minute later
        assert shared.used_s("greedy", now=time.monotonic() + 61.0) == 0.0
    finally:
        shared.close()


def test_waiting_requests_are_served_one_owner_after_another() -> None:
    """Three selections a greedy client queued together had kept a steerer's one waiting behind
    all three (22-45 s for a layer change): each owner now takes its turn."""
    waiting = FairQueue()
    held = object()
    tasks = [_Task("select", held, (name,), None, owner=owner) for name, owner in
             [("g1", "greedy"), ("g2", "greedy"), ("g3", "greedy"), ("s1", "steerer"),
              ("n1", None)]]  # fmt: skip
    for task in tasks:
        waiting.put(task)
    assert waiting.qsize() == 5
    order = [waiting.get().args[0] for _ in range(5)]  # type: ignore[union-attr]
    assert order == ["g1", "s1", "n1", "g2", "g3"]
    with pytest.raises(queue.Empty):
        waiting.get_nowait()
    waiting.put(tasks[0])
    waiting.put(None)  # a stop goes first
    assert waiting.get() is None and waiting.get() is tasks[0]


PARENT = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    from structures.selection_cost import SelectionLimits
    from structures.selection_pool import PoolLimits, SelectionPool
    from tests.structures.test_selection_cost import backbone

    pool = SelectionPool(PoolLimits(workers=1, selection=SelectionLimits(max_pairs=10**15)))
    topo, pos = backbone(40_000)
    held = pool.hold(topo)
    held.submit(["name CA"], counts=True).result()
    print(pool.pids()[0], flush=True)
    if {busy}:
        held.submit([{slow!r}], pos)  # still evaluating when this process dies
    time.sleep(60)
    """
)


@pytest.mark.parametrize("busy", [False, True], ids=["idle", "evaluating"])
def test_a_worker_ends_with_the_process_that_started_it(busy: bool) -> None:
    code = PARENT.format(root=str(ROOT), busy=busy, slow=SLOW)
    parent = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, cwd=ROOT, text=True
    )
    try:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        time.sleep(0.3)
        assert not gone(worker, within=0.1)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        # idle, it sees its pipe close; evaluating, the kernel kills it with its parent
        assert gone(worker, within=3.0), "the worker outlived its parent"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if parent.stdout is not None:
            parent.stdout.close()


def test_closing_the_pool_ends_its_workers() -> None:
    topo, _pos = backbone(400)
    pool = SelectionPool(PoolLimits(workers=2))
    a, b = pool.hold(topo), pool.hold(topo)
    a.submit(["name CA"]).result()
    b.submit(["name CA"]).result()
    pids = pool.pids()
    assert len(pids) == 2
    pool.close()
    assert all(gone(pid) for pid in pids) and pool.pids() == []
    with pytest.raises(SelectionBusyError):
        a.submit(["name CA"]).result()
