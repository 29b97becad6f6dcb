"""A session's layers: selections evaluated on its topology, kept current as frames arrive.

Static selections are evaluated once per topology. Distance-based ones (`around 5 resname LIG`)
are re-evaluated on the positions at most `REFRESH_S` apart, in a worker thread, while the last
result keeps being drawn; the first evaluation of one runs at once. The plans handed to the GPU
are rebuilt only when the parameters or an atom set change, so a renderer sees the same
parameter objects frame after frame.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.render.layerplan import LayerPlan, plan_layers
from structures.selection import SelectionError, Selector, default_layers, is_dynamic

log = logging.getLogger("scalesteer.session")

REFRESH_S = 0.1
"""Distance-based selections follow the simulation at up to 10 evaluations a second."""
BUILD_AWAY_ATOMS = 100_000
"""From this size the selection universe (about a second per million atoms) is built in a
worker thread; the session draws nothing until it is ready rather than stall every session."""


@dataclass
class _Dynamic:
    atoms: npt.NDArray[np.int32]
    positions_id: int
    evaluated: float
    count: int = 0
    running: bool = False


class LayerBook:
    """Selections of one session's topology and the layer plans built from them."""

    def __init__(self, on_refresh: Callable[[], None]) -> None:
        self._on_refresh = on_refresh
        self._ready = True
        self._invalid: set[str] = set()
        """Selections that failed on this topology (reported once, drawn as nothing)."""
        self._codes: npt.NDArray[np.uint8] | None = None
        self._selector: Selector | None = None
        self._topology_id = -1
        self._lock = threading.Lock()
        self._dynamic: dict[str, _Dynamic] = {}
        self._plans: tuple[Any, tuple[LayerPlan, ...] | None] | None = None
        self.auto = True
        """Layers still follow the topology's defaults (no steerer has set them)."""

    def topology(self, topology: p.Topology, topology_id: int) -> None:
        """A new topology: earlier selection results no longer apply."""
        with self._lock:
            selector = self._selector = Selector(topology)
            self._topology_id = topology_id
            self._dynamic.clear()
            self._invalid.clear()
            self._plans = None
            self._codes = None
            self._ready = topology.n_atoms < BUILD_AWAY_ATOMS
        if self._ready:
            return

        def build() -> None:
            with self._lock:
                selector.universe  # noqa: B018 (built once, here)

        def done(future: asyncio.Future[None]) -> None:
            if selector is not self._selector:
                return  # another topology arrived meanwhile
            if future.exception() is not None:
                log.error(
                    "selections of a %d-atom topology: %s", topology.n_atoms, future.exception()
                )
            self._ready = True
            self._on_refresh()

        asyncio.get_running_loop().run_in_executor(None, build).add_done_callback(done)

    @property
    def ready(self) -> bool:
        """False while the selection universe of a large topology is still being built."""
        return self._ready

    def defaults(self, topology: p.Topology, sigma_A: float) -> list[p.Layer]:
        """The layers this topology opens with (structures.selection.default_layers)."""
        return [p.Layer(**fields) for fields in default_layers(topology, sigma_A)]

    def select(
        self,
        text: str,
        positions: npt.NDArray[np.float32] | None,
        box: npt.NDArray[np.float32] | None = None,
    ) -> npt.NDArray[np.int32]:
        """Evaluate `text` now (raises SelectionError); for checks and counts. A static
        selection answered before is read without waiting for a worker's evaluation."""
        selector = self._selector
        if selector is None:
            raise SelectionError(text, "no topology yet", 0)
        known = selector.cached(text)
        if known is not None:
            return known
        if not self._ready:
            raise SelectionError(text, "the system's selections are still being prepared", 0)
        with self._lock:
            return selector.select(text, positions, box)

    def _current(
        self,
        text: str,
        positions: npt.NDArray[np.float32],
        positions_id: int,
        box: npt.NDArray[np.float32] | None,
    ) -> tuple[npt.NDArray[np.int32], Any]:
        """A selection's atoms for drawing and a key that changes when they do; an invalid
        one draws nothing and is reported once (a layer set before the topology arrived)."""
        if text in self._invalid:
            return np.zeros(0, dtype=np.int32), (self._topology_id, text, "invalid")
        try:
            if not is_dynamic(text):
                return self.select(text, None), (self._topology_id, text)
            entry = self._dynamic.get(text)
            if entry is None:
                atoms = self.select(text, positions, box)
                entry = self._dynamic[text] = _Dynamic(atoms, positions_id, time.monotonic())
            elif (
                not entry.running
                and entry.positions_id != positions_id
                and time.monotonic() - entry.evaluated >= REFRESH_S
            ):
                self._refresh(text, entry, positions, positions_id, box)
            return entry.atoms, (self._topology_id, text, entry.count)
        except Exception as exc:  # a layer that cannot be drawn must not stop the others
            log.warning("layer %r not drawn: %s", text, exc)
            self._invalid.add(text)
            return np.zeros(0, dtype=np.int32), (self._topology_id, text, "invalid")

    def _refresh(
        self,
        text: str,
        entry: _Dynamic,
        positions: npt.NDArray[np.float32],
        positions_id: int,
        box: npt.NDArray[np.float32] | None,
    ) -> None:
        entry.running = True
        topology_id = self._topology_id
        loop = asyncio.get_running_loop()

        def done(future: asyncio.Future[npt.NDArray[np.int32]]) -> None:
            entry.running = False
            entry.evaluated = time.monotonic()
            if future.cancelled() or future.exception() is not None:
                log.warning("re-evaluating %r failed: %s", text, future.exception())
                return
            if topology_id != self._topology_id:
                return
            atoms = future.result()
            entry.positions_id = positions_id
            if not np.array_equal(atoms, entry.atoms):
                entry.atoms = atoms
                entry.count += 1
                self._on_refresh()

        future = loop.run_in_executor(None, self.select, text, positions, box)
        future.add_done_callback(done)

    def plans(
        self,
        params: p.RenderParams,
        n_atoms: int,
        positions: npt.NDArray[np.float32] | None,
        positions_id: int,
        box: npt.NDArray[np.float32] | None = None,
    ) -> tuple[LayerPlan, ...] | None:
        """The visible layers of `params` with their atoms (None: no layers; ask `ready`
        first: while a large topology's selections are prepared this also answers None)."""
        if not params.layers or self._selector is None or positions is None or not self._ready:
            return None
        chosen: dict[str, tuple[npt.NDArray[np.int32], Any]] = {}

        def select(text: str) -> tuple[npt.NDArray[np.int32], Any]:
            if text not in chosen:
                chosen[text] = self._current(text, positions, positions_id, box)
            return chosen[text]

        keys = tuple(select(layer.selection)[1] for layer in params.layers if layer.visible)
        cached = self._plans
        if cached is not None and cached[0][0] is params and cached[0][1] == keys:
            return cached[1]

        def secondary() -> npt.NDArray[np.uint8]:
            return self._secondary(positions)

        plans = plan_layers(params, n_atoms, select, secondary)
        self._plans = ((params, keys), plans)
        return plans

    def _secondary(self, positions: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:
        """Every atom's secondary structure, assigned once per topology (at the first frame a
        tube layer draws); all coil when DSSP cannot say."""
        if self._codes is None:
            assert self._selector is not None
            try:
                with self._lock:
                    self._codes = self._selector.secondary(positions)
            except Exception as exc:  # drawn as a plain tube rather than not at all
                log.warning("tube layers drawn without secondary structure: %s", exc)
                self._codes = np.zeros(self._selector.topology.n_atoms, dtype=np.uint8)
        codes: npt.NDArray[np.uint8] = self._codes
        return codes
