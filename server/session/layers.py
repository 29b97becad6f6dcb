"""A session's layers: selections evaluated on its topology, kept current as frames arrive.

Selections never run on the event loop: the server's selection workers
(`structures.selection_pool`) evaluate them, each priced first and bounded in time and memory.
A layer's first evaluation is asked for when a render needs it; until every visible layer has
its atoms the session does not render (`ready` is False), and the answer triggers the render.
Static selections are evaluated once per topology. Distance-based ones (`around 5 resname LIG`)
are re-evaluated as frames arrive, at most every `REFRESH_S` (and keeping their worker busy a
fifth of the time at most: a selection that took 0.4 s waits 1.6 s), while the last result
keeps being drawn. The
plans handed to the GPU are rebuilt only when the parameters or an atom set change, so a
renderer sees the same parameter objects frame after frame.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.render.layerplan import LayerPlan, plan_layers
from structures.selection import SelectionError, default_layers, is_dynamic
from structures.selection_pool import Held, Result, SelectionBusyError, SelectionPool

log = logging.getLogger("scalesteer.session")

REFRESH_S = 0.1
"""Distance-based selections follow the simulation at up to 10 evaluations a second."""
REFRESH_DUTY = 4.0
"""A re-evaluation waits at least this many times the last one's duration: a costly
selection keeps its worker busy a fifth of the time at most."""
RETRY_S = 0.5
"""After the workers were busy, a first evaluation is asked for again this much later."""


@dataclass
class _Entry:
    """One selection's atoms on this topology (None until its first evaluation)."""

    dynamic: bool
    atoms: npt.NDArray[np.int32] | None = None
    failed: str = ""
    """Why it cannot be drawn (reported once; drawn as nothing)."""
    positions_id: int = -1
    evaluated: float = 0.0
    duration: float = 0.0
    count: int = 0
    running: bool = False


def _visible(layer: p.Layer) -> bool:
    return layer.visible and layer.opacity > 0.0  # as plan_layers draws them


class LayerBook:
    """Selections of one session's topology and the layer plans built from them."""

    def __init__(self, on_refresh: Callable[[], None], pool: SelectionPool) -> None:
        self._on_refresh = on_refresh
        self._pool = pool
        self._held: Held | None = None
        self._topology_id = -1
        self._entries: dict[str, _Entry] = {}
        self._codes: npt.NDArray[np.uint8] | None = None
        self._codes_running = False
        self._plans: tuple[Any, tuple[LayerPlan, ...] | None] | None = None
        self._missing = False
        self.auto = True
        """Layers still follow the topology's defaults (no steerer has set them)."""

    def topology(self, topology: p.Topology, topology_id: int, prepare: bool = False) -> None:
        """A new topology: earlier selection results no longer apply. `prepare`: build its
        universe in the worker now (layers will be asked for)."""
        if self._held is not None:
            self._held.release()
        self._held = self._pool.hold(topology)
        self._topology_id = topology_id
        self._entries.clear()
        self._plans = None
        self._codes = None
        self._codes_running = False
        self._missing = False
        if prepare:
            self._held.prepare()

    def close(self) -> None:
        """The session ends: its topology leaves the worker."""
        if self._held is not None:
            self._held.release()
            self._held = None

    @property
    def held(self) -> Held | None:
        """The session's topology in its selection worker (None before one arrives)."""
        return self._held

    @property
    def ready(self) -> bool:
        """False while a layer the last `plans` call needed has no atoms yet (its first
        evaluation is under way); its answer calls `on_refresh`."""
        return not self._missing

    def defaults(self, topology: p.Topology, sigma_A: float) -> list[p.Layer]:
        """The layers this topology opens with (structures.selection.default_layers)."""
        return [p.Layer(**fields) for fields in default_layers(topology, sigma_A)]

    async def count(
        self,
        text: str,
        positions: npt.NDArray[np.float32] | None,
        positions_id: int,
        box: npt.NDArray[np.float32] | None = None,
        owner: Hashable | None = None,
    ) -> int:
        """How many atoms `text` selects now (raises SelectionError): for `select`, as a
        selection is typed; its worker time is charged to `owner`."""
        held = self._held
        if held is None:
            raise SelectionError(text, "no topology yet", 0)
        known = self._entries.get(text.strip())
        if known is not None and not known.dynamic and known.atoms is not None:
            return len(known.atoms)
        moving = positions if is_dynamic(text) else None  # a frame is sent only when it counts
        future = held.submit(
            [text], moving, box, positions_key=positions_id, counts=True, owner=owner
        )
        found = (await asyncio.wrap_future(future))[0]
        if isinstance(found, SelectionError):
            raise found
        return found if isinstance(found, int) else len(found)

    async def check(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None,
        positions_id: int,
        box: npt.NDArray[np.float32] | None = None,
    ) -> list[SelectionError | None]:
        """Evaluate `texts` together (the layers a steerer sets, under one budget): why each
        cannot be drawn, or None. Raises SelectionError when the request as a whole failed
        (its time or memory). What was found is kept for the first render."""
        found = await self.evaluate(texts, positions, positions_id, box)
        return [r if isinstance(r, SelectionError) else None for r in found]

    async def evaluate(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None,
        positions_id: int,
        box: npt.NDArray[np.float32] | None = None,
    ) -> list[SelectionError | npt.NDArray[np.int32]]:
        """`check`, with the atoms each text selects where it can be drawn."""
        held = self._held
        if held is None:
            raise SelectionError(None, "no topology yet", 0)
        future = held.submit(texts, positions, box, positions_key=positions_id)
        found = await asyncio.wrap_future(future)
        if held is self._held:
            now = time.monotonic()
            for text, result in zip(texts, found, strict=True):
                if isinstance(result, np.ndarray) and text.strip() not in self._entries:
                    self._entries[text.strip()] = _Entry(
                        is_dynamic(text), result, positions_id=positions_id, evaluated=now
                    )
        return [r if isinstance(r, SelectionError) else np.asarray(r, np.int32) for r in found]

    def plans(
        self,
        params: p.RenderParams,
        n_atoms: int,
        positions: npt.NDArray[np.float32] | None,
        positions_id: int,
        box: npt.NDArray[np.float32] | None = None,
    ) -> tuple[LayerPlan, ...] | None:
        """The visible layers of `params` with their atoms (None: no layers). Asks the worker
        for what is missing or due; while a layer has no atoms yet this answers None and
        `ready` is False."""
        held = self._held
        if not params.layers or held is None or positions is None:
            self._missing = False
            return None
        layers = [layer for layer in params.layers if _visible(layer)]
        texts = list(dict.fromkeys(layer.selection.strip() for layer in layers))
        now = time.monotonic()
        due: list[str] = []
        for text in texts:
            entry = self._entries.get(text)
            if entry is None:
                entry = self._entries[text] = _Entry(is_dynamic(text))
            if entry.failed or entry.running:
                continue
            if entry.atoms is None or (
                entry.dynamic
                and entry.positions_id != positions_id
                and now - entry.evaluated >= max(REFRESH_S, REFRESH_DUTY * entry.duration)
            ):
                due.append(text)
        if due:
            self._ask(held, due, positions, positions_id, box)
        tubes = any(layer.mode == "tube" for layer in layers)
        if tubes and self._codes is None and not self._codes_running:
            self._ask_codes(held, positions, positions_id)
        self._missing = (tubes and self._codes is None) or any(
            self._entries[t].atoms is None and not self._entries[t].failed for t in texts
        )
        if self._missing:
            return None

        def select(text: str) -> tuple[npt.NDArray[np.int32], Any]:
            entry = self._entries[text.strip()]
            if entry.atoms is None:
                return np.zeros(0, dtype=np.int32), (self._topology_id, text, "invalid")
            return entry.atoms, (self._topology_id, text, entry.count)

        keys = tuple(select(text)[1] for text in texts)
        cached = self._plans
        if cached is not None and cached[0][0] is params and cached[0][1] == keys:
            return cached[1]

        def secondary() -> npt.NDArray[np.uint8]:
            assert self._codes is not None
            return self._codes

        plans = plan_layers(params, n_atoms, select, secondary)
        self._plans = ((params, keys), plans)
        return plans

    def _ask(
        self,
        held: Held,
        texts: list[str],
        positions: npt.NDArray[np.float32],
        positions_id: int,
        box: npt.NDArray[np.float32] | None,
    ) -> None:
        """Evaluate `texts` in the worker; the answer updates them and, if an atom set
        changed (or a first one arrived), calls `on_refresh`."""
        for text in texts:
            self._entries[text].running = True
        dynamic = any(self._entries[t].dynamic for t in texts)
        started = time.monotonic()
        future = held.submit(texts, positions if dynamic else None, box, positions_key=positions_id)

        def answered(done: asyncio.Future[list[Result]]) -> None:
            if held is not self._held:
                return  # another topology arrived meanwhile
            if done.cancelled():
                found: list[Result] = [SelectionBusyError(None, "the request was cancelled", 0)]
            elif (error := done.exception()) is not None:
                reason = (
                    error
                    if isinstance(error, SelectionError)
                    else SelectionError(None, str(error), 0)
                )
                found = [reason] * len(texts)
            else:
                found = done.result()
            self._answered(texts, found, positions_id, started)

        asyncio.wrap_future(future).add_done_callback(answered)

    def _answered(
        self, texts: list[str], found: list[Result], positions_id: int, started: float
    ) -> None:
        now = time.monotonic()
        changed = retry = False
        for text, result in zip(texts, found, strict=False):
            entry = self._entries.get(text)
            if entry is None:
                continue
            entry.running = False
            entry.evaluated = now
            if entry.atoms is not None:  # a refresh (a first one may wait for its universe)
                entry.duration = now - started
            if isinstance(result, SelectionError):
                if isinstance(result, SelectionBusyError):
                    retry = retry or entry.atoms is None
                elif entry.atoms is None:  # drawn as nothing, and said once
                    entry.failed = result.reason
                    log.warning("layer %r not drawn: %s", text, result.reason)
                    changed = True
                else:  # the last atoms are kept
                    log.warning("re-evaluating %r failed: %s", text, result.reason)
                continue
            atoms = np.asarray(result, dtype=np.int32)
            entry.positions_id = positions_id
            if entry.atoms is None or not np.array_equal(atoms, entry.atoms):
                entry.atoms = atoms
                entry.count += 1
                changed = True
        if changed:
            self._on_refresh()
        if retry:
            asyncio.get_running_loop().call_later(RETRY_S, self._on_refresh)

    def _ask_codes(self, held: Held, positions: npt.NDArray[np.float32], positions_id: int) -> None:
        """Every atom's secondary structure, assigned once per topology (at the first frame a
        tube layer draws); all coil when DSSP cannot say or the protein is too large."""
        self._codes_running = True
        future = held.submit_secondary(positions, positions_key=positions_id)

        def answered(done: asyncio.Future[npt.NDArray[np.uint8]]) -> None:
            if held is not self._held:
                return
            self._codes_running = False
            error = done.exception() if not done.cancelled() else None
            if done.cancelled() or error is not None:
                log.warning("tube layers drawn without secondary structure: %s", error)
                self._codes = np.zeros(held.n_atoms, dtype=np.uint8)
            else:
                self._codes = done.result()
            self._on_refresh()

        asyncio.wrap_future(future).add_done_callback(answered)
