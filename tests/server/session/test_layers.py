"""A session's layer book: selections evaluated by a worker process (never on the event loop),
static ones once per topology, distance-based ones following the frames (at most every
REFRESH_S), plans reused while nothing changes, a render held back only until a layer's first
atoms arrive."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

import protocol as p
from server.session.layers import REFRESH_S, LayerBook
from structures.selection_cost import SelectionLimits
from structures.selection_pool import PoolLimits, SelectionPool
from tests.server.peers import molecule
from tests.server.session.fakes import run_on_own_loop

pytest.importorskip("MDAnalysis")


@pytest.fixture(scope="module")
def pool() -> Iterator[SelectionPool]:
    pool = SelectionPool(PoolLimits(workers=1, selection=SelectionLimits(max_pairs=50_000)))
    yield pool
    pool.close()


async def until(predicate: Callable[[], bool], timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < end, "condition not met"
        await asyncio.sleep(0.01)


def test_distance_selections_follow_the_frames(pool: SelectionPool) -> None:
    topo, pos = molecule(24)
    moved: list[float] = []

    async def main() -> None:
        book = LayerBook(lambda: moved.append(time.monotonic()), pool)
        book.topology(topo, 1, prepare=True)
        params = p.RenderParams(
            layers=[
                p.Layer(name="core", selection="index 0:3"),
                p.Layer(name="near", selection="around 3 index 0"),
            ]
        )
        # the first evaluation is asked for; nothing is drawn until it answers
        assert book.plans(params, topo.n_atoms, pos, 1) is None and not book.ready
        await until(lambda: bool(moved))
        first = book.plans(params, topo.n_atoms, pos, 1)
        assert book.ready and first is not None and [x.name for x in first] == ["core", "near"]
        near0 = first[1].atoms
        assert near0 is not None
        d = np.linalg.norm(pos - pos[0], axis=1)
        assert np.array_equal(near0, np.flatnonzero((d < 3) & (d > 0)))
        # nothing changed: the same plans (and parameter objects) again
        assert book.plans(params, topo.n_atoms, pos, 1) is first
        # atom 0 moves next to the chain's far end: the selection follows, in the worker
        later = pos.copy()
        later[0] = pos[-1] + np.float32(1.0)
        await asyncio.sleep(REFRESH_S)
        assert book.plans(params, topo.n_atoms, later, 2) is first  # the last result, meanwhile
        await until(lambda: book.plans(params, topo.n_atoms, later, 2) is not first)
        again = book.plans(params, topo.n_atoms, later, 2)
        assert again is not None and again is not first
        d = np.linalg.norm(later - later[0], axis=1)
        assert np.array_equal(again[1].atoms, np.flatnonzero((d < 3) & (d > 0)))
        assert again[0].atoms_key == first[0].atoms_key  # the static layer did not change
        book.close()

    run_on_own_loop(main)


def test_a_new_topology_forgets_old_results(pool: SelectionPool) -> None:
    topo, pos = molecule(24)
    small, small_pos = molecule(10)
    moved: list[bool] = []

    async def main() -> None:
        book = LayerBook(lambda: moved.append(True), pool)
        book.topology(topo, 1)
        params = p.RenderParams(layers=[p.Layer(selection="index 0:14")])
        book.plans(params, topo.n_atoms, pos, 1)
        await until(lambda: book.plans(params, topo.n_atoms, pos, 1) is not None)
        plans = book.plans(params, topo.n_atoms, pos, 1)
        assert plans is not None and len(plans[0].atoms) == 15  # type: ignore[arg-type]
        book.topology(small, 2)
        assert book.plans(params, small.n_atoms, small_pos, 1) is None and not book.ready
        await until(lambda: book.plans(params, small.n_atoms, small_pos, 1) is not None)
        plans = book.plans(params, small.n_atoms, small_pos, 1)
        assert plans is not None and plans[0].atoms is None  # every atom of the smaller system
        assert book.plans(p.RenderParams(), small.n_atoms, small_pos, 1) is None  # no layers
        assert book.ready
        book.close()

    run_on_own_loop(main)


def test_hiding_every_layer_draws_nothing_rather_than_waiting(pool: SelectionPool) -> None:
    topo, pos = molecule(24)

    async def main() -> None:
        book = LayerBook(lambda: None, pool)
        book.topology(topo, 1)
        hidden = p.RenderParams(layers=[p.Layer(selection="all", visible=False)])
        assert book.plans(hidden, topo.n_atoms, pos, 1) == () and book.ready
        book.close()

    run_on_own_loop(main)


def test_a_layer_that_fails_or_costs_too_much_is_drawn_as_nothing(pool: SelectionPool) -> None:
    """A selection that fails on this topology, or one past the selection limits, is drawn as
    nothing (and logged once); the other layers still are."""
    topo, pos = molecule(400)
    moved: list[bool] = []

    async def main() -> None:
        book = LayerBook(lambda: moved.append(True), pool)
        book.topology(topo, 1)
        params = p.RenderParams(
            layers=[
                p.Layer(selection="smarts c1ccccc1"),  # no RDKit here: an error of its own
                p.Layer(selection="around 500 all"),  # 400 x 400 pairs, past 50,000
                p.Layer(selection="index 0:3"),
            ]
        )
        assert book.plans(params, topo.n_atoms, pos, 1) is None
        await until(lambda: book.plans(params, topo.n_atoms, pos, 1) is not None)
        plans = book.plans(params, topo.n_atoms, pos, 1)
        assert plans is not None and len(plans) == 1 and len(plans[0].atoms) == 4  # type: ignore[arg-type]
        book.close()

    run_on_own_loop(main)


def test_counting_and_checking_run_in_the_worker(pool: SelectionPool) -> None:
    topo, pos = molecule(400)

    async def main() -> None:
        book = LayerBook(lambda: None, pool)
        book.topology(topo, 1)
        assert await book.count("index 0:9", pos, 1) == 10
        d = np.linalg.norm(pos - pos[0], axis=1)
        assert await book.count("around 3 index 0", pos, 1) == int(((d < 3) & (d > 0)).sum())
        found = await book.check(["index 0:9", "around 500 all", "name X"], pos, 1)
        assert found[0] is None and found[2] is None
        costly = found[1]
        assert costly is not None and costly.limit == "selection_max_pairs"
        assert "50,000" in costly.reason
        book.close()

    run_on_own_loop(main)
