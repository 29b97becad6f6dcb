"""A session's layer book: static selections once per topology, distance-based ones following
the frames (at most every REFRESH_S, off the event loop), plans reused while nothing changes."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

import protocol as p
from server.session.layers import REFRESH_S, LayerBook
from tests.server.peers import molecule
from tests.server.session.fakes import run_on_own_loop

pytest.importorskip("MDAnalysis")


def test_distance_selections_follow_the_frames() -> None:
    topo, pos = molecule(24)
    moved: list[float] = []

    async def main() -> None:
        book = LayerBook(lambda: moved.append(time.monotonic()))
        book.topology(topo, 1)
        params = p.RenderParams(
            layers=[
                p.Layer(name="core", selection="index 0:3"),
                p.Layer(name="near", selection="around 3 index 0"),
            ]
        )
        first = book.plans(params, topo.n_atoms, pos, 1)
        assert first is not None and [x.name for x in first] == ["core", "near"]
        near0 = first[1].atoms
        assert near0 is not None
        d = np.linalg.norm(pos - pos[0], axis=1)
        assert np.array_equal(near0, np.flatnonzero((d < 3) & (d > 0)))
        # nothing changed: the same plans (and parameter objects) again
        assert book.plans(params, topo.n_atoms, pos, 1) is first
        # atom 0 moves next to the chain's far end: the selection follows, off the loop
        later = pos.copy()
        later[0] = pos[-1] + np.float32(1.0)
        await asyncio.sleep(REFRESH_S)
        assert book.plans(params, topo.n_atoms, later, 2) is first  # the last result, meanwhile
        for _ in range(100):
            if moved:
                break
            await asyncio.sleep(0.02)
        assert moved, "the refresh never reported"
        again = book.plans(params, topo.n_atoms, later, 2)
        assert again is not None and again is not first
        d = np.linalg.norm(later - later[0], axis=1)
        assert np.array_equal(again[1].atoms, np.flatnonzero((d < 3) & (d > 0)))
        assert again[0].atoms_key == first[0].atoms_key  # the static layer did not change

    run_on_own_loop(main)


def test_a_new_topology_forgets_old_results() -> None:
    topo, pos = molecule(24)
    small, small_pos = molecule(10)

    async def main() -> None:
        book = LayerBook(lambda: None)
        book.topology(topo, 1)
        params = p.RenderParams(layers=[p.Layer(selection="index 0:14")])
        plans = book.plans(params, topo.n_atoms, pos, 1)
        assert plans is not None and len(plans[0].atoms) == 15  # type: ignore[arg-type]
        book.topology(small, 2)
        plans = book.plans(params, small.n_atoms, small_pos, 1)
        assert plans is not None and plans[0].atoms is None  # every atom of the smaller system

    run_on_own_loop(main)


def test_a_large_topology_prepares_its_selections_off_the_loop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import server.session.layers as layers

    monkeypatch.setattr(layers, "BUILD_AWAY_ATOMS", 10)
    topo, pos = molecule(24)
    ready: list[bool] = []

    async def main() -> None:
        book = LayerBook(lambda: ready.append(True))
        book.topology(topo, 1)
        params = p.RenderParams(layers=[p.Layer(selection="index 0:4")])
        assert not book.ready and book.plans(params, topo.n_atoms, pos, 1) is None
        for _ in range(200):
            if ready:
                break
            await asyncio.sleep(0.01)
        assert ready, "the universe was never reported ready"
        assert book.ready
        plans = book.plans(params, topo.n_atoms, pos, 1)
        assert plans is not None
        assert plans[0].atoms is not None and len(plans[0].atoms) == 5
        assert book.plans(p.RenderParams(), topo.n_atoms, pos, 1) is None  # no layers

    run_on_own_loop(main)


def test_hiding_every_layer_draws_nothing_rather_than_waiting() -> None:
    topo, pos = molecule(24)

    async def main() -> None:
        book = LayerBook(lambda: None)
        book.topology(topo, 1)
        hidden = p.RenderParams(layers=[p.Layer(selection="all", visible=False)])
        assert book.ready and book.plans(hidden, topo.n_atoms, pos, 1) == ()
        # a selection that fails on this topology is drawn as nothing, and the others still are
        params = p.RenderParams(
            layers=[p.Layer(selection="smarts c1ccccc1"), p.Layer(selection="index 0:3")]
        )
        plans = book.plans(params, topo.n_atoms, pos, 1)
        assert plans is not None and len(plans) == 1 and len(plans[0].atoms) == 4  # type: ignore[arg-type]

    run_on_own_loop(main)
