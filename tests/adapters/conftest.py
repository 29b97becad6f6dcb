"""Fixtures for the adapter tests: a real `/ws/sim` peer and a leaked-thread check."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from protocol import Frame, Topology, WireArray
from server.render.device import LAUNCH_POOL
from tests.adapters.sim_peer import SimPeer


@pytest.fixture
def peer() -> Iterator[SimPeer]:
    with SimPeer() as p:
        yield p


@pytest.fixture
def no_leaked_threads() -> Iterator[None]:
    """Fail if the test leaves threads behind (checked after everything it closed). The CPU
    device's launch pool is the process's, made once at its first split launch whichever test
    that falls in (`server.render.device.split_launch`), and is not the test's."""
    before = {t.ident for t in threading.enumerate()}
    yield
    deadline = time.monotonic() + 5.0
    while True:
        extra = [
            t
            for t in threading.enumerate()
            if t.ident not in before and t.is_alive() and not t.name.startswith(LAUNCH_POOL)
        ]
        if not extra or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert not extra, f"threads left running: {[t.name for t in extra]}"


def small_topology(n: int = 4) -> Topology:
    return Topology(
        n_atoms=n,
        elements=["C"] * n,
        names=[f"C{i}" for i in range(n)],
        residue_ids=WireArray.from_numpy(np.ones(n), "<i4"),
        residue_names=["MOL"] * n,
        chain_ids=["A"] * n,
        bonds=WireArray.from_numpy(np.array([[i, i + 1] for i in range(n - 1)]), "<i4"),
    )


def small_frame(step: int, n: int = 4) -> Frame:
    pos = np.arange(n * 3, dtype=np.float32).reshape(n, 3) + step
    return Frame(step=step, time_ps=step * 0.002, positions=WireArray.from_numpy(pos, "<f4"))
