"""Layer selections for renders outside a live session (REST renders, jobs, Ray chunks).

Selections are evaluated by a selection worker (`structures.selection_pool`: priced before they
run, bounded in time and memory), or in this process for a user's own files (`InProcess`, for
`scalesteer render`). Static selections are evaluated once per topology; distance-based ones on
every frame, since a batch job sees each frame once and in order. The selections one frame
needs are evaluated together, under one budget.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Hashable, Sequence
from concurrent.futures import Future
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

import protocol as p
from server.render.layerplan import LayerPlan, plan_layers
from structures.selection import (
    SelectionError,
    SelectionSkippedError,
    check_syntax,
    is_dynamic,
)
from structures.selection_cost import SelectionLimits
from structures.selection_pool import Result

log = logging.getLogger("scalesteer.pipeline")


class LayerError(ValueError):
    """A layer that cannot be drawn: `path` names its selection (`layers.2.selection`),
    `error` says why (and `error.limit` names a limit it would cross)."""

    def __init__(self, path: str, error: SelectionError) -> None:
        self.path = path
        self.error = error
        super().__init__(f"{path}: {error}")


def check_layers(params: p.RenderParams, limits: SelectionLimits | None = None) -> None:
    """Raise LayerError naming the first layer whose selection does not parse (or, with
    `limits`, is too long or nested too deeply): checked here, before any topology."""
    for i, layer in enumerate(params.layers):
        try:
            check_syntax(layer.selection, limits)
        except SelectionError as exc:
            raise LayerError(f"layers.{i}.selection", exc) from None


def opening_params(params: p.RenderParams, topology: p.Topology) -> p.RenderParams:
    """The one rule for what a system opens on, for every entry point (sessions, REST renders
    and jobs, `scalesteer render` and `batch`, movies): parameters that do not name `layers`
    get the default layers (`structures.selection.default_layers`: solvent and ions hidden, a
    ligand at a finer scale, at these parameters' sigma); parameters that name them, even as
    an empty list (every atom), keep them."""
    if "layers" in params.model_fields_set:
        return params
    from structures.selection import default_layers

    defaults = [p.Layer(**fields) for fields in default_layers(topology, params.sigma_A)]
    return params.model_copy(update={"layers": defaults})


class Selections(Protocol):
    """Where selections are evaluated: `structures.selection_pool.Held` (a worker) or
    `InProcess`."""

    def submit(
        self,
        texts: Sequence[str],
        positions: npt.NDArray[np.float32] | None = None,
        box: npt.NDArray[np.float32] | None = None,
        *,
        positions_key: Hashable | None = None,
        counts: bool = False,
        strict: bool = False,
        owner: Hashable | None = None,
    ) -> Future[list[Result]]: ...

    def submit_secondary(
        self, positions: npt.NDArray[np.float32], positions_key: Hashable | None = None
    ) -> Future[npt.NDArray[np.uint8]]: ...


class FrameLayers:
    """The layer plans of one parameter set on one topology, frame after frame."""

    def __init__(
        self,
        params: p.RenderParams,
        topology: p.Topology,
        selections: Selections | None,
        reference: npt.NDArray[np.float32] | None = None,
        owner: Hashable | None = None,
    ) -> None:
        """`selections`: where they are evaluated (None only for parameters without layers).
        `reference`: the positions secondary structure is assigned at (the job's reference
        frame, so every chunk of a distributed job draws the same helices); else the first
        frame asked for. `owner`: the client whose selection-worker time the layers use."""
        self.params = params
        self.topology = topology
        self.selections = selections
        self.owner = owner
        self._reference = reference
        self._codes: npt.NDArray[np.uint8] | None = None
        self._static: dict[str, npt.NDArray[np.int32]] = {}
        self._layers = [layer for layer in params.layers if layer.visible and layer.opacity > 0]
        self._texts = list(dict.fromkeys(layer.selection for layer in self._layers))

    def plans(
        self,
        positions: npt.NDArray[np.float32],
        frame_key: Any,
        box: npt.NDArray[np.float32] | None = None,
    ) -> tuple[LayerPlan, ...] | None:
        """The visible layers at this frame (None: no layers), waiting for the evaluation;
        raises LayerError naming the layer that cannot be drawn."""
        if not self.params.layers:
            return None
        texts = self._due()
        found = self._wait(self._submit(texts, positions, box, frame_key)) if texts else []
        if self._tubes() and self._codes is None:
            self._codes = self._wait_codes(self._submit_codes(positions))
        return self._plan(texts, found, frame_key)

    async def plans_async(
        self,
        positions: npt.NDArray[np.float32],
        frame_key: Any,
        box: npt.NDArray[np.float32] | None = None,
    ) -> tuple[LayerPlan, ...] | None:
        """`plans`, awaited on the event loop (the evaluation runs in a worker)."""
        if not self.params.layers:
            return None
        texts = self._due()
        found: list[Result] = []
        if texts:
            found = await self._await(self._submit(texts, positions, box, frame_key))
        if self._tubes() and self._codes is None:
            self._codes = await self._await_codes(self._submit_codes(positions))
        return self._plan(texts, found, frame_key)

    def _due(self) -> list[str]:
        return [t for t in self._texts if is_dynamic(t) or t not in self._static]

    def _tubes(self) -> bool:
        return any(layer.mode == "tube" for layer in self._layers)

    def _submit(
        self,
        texts: list[str],
        positions: npt.NDArray[np.float32],
        box: npt.NDArray[np.float32] | None,
        frame_key: Any,
    ) -> Future[list[Result]]:
        assert self.selections is not None, "layers need somewhere to evaluate them"
        key = frame_key if isinstance(frame_key, Hashable) else None
        # a frame is drawn whole or not at all: nothing runs if any layer is refused
        return self.selections.submit(
            texts, positions, box, positions_key=key, strict=True, owner=self.owner
        )

    def _submit_codes(self, positions: npt.NDArray[np.float32]) -> Future[npt.NDArray[np.uint8]]:
        assert self.selections is not None
        at = positions if self._reference is None else self._reference
        return self.selections.submit_secondary(at)

    def _failed(self, texts: list[str], exc: BaseException) -> LayerError:
        """A request that failed as a whole (its time or memory): the layer it was, when one."""
        error = exc if isinstance(exc, SelectionError) else SelectionError(None, str(exc), 0)
        if len(texts) == 1:
            return self._error(texts[0], error)
        return LayerError("layers", error)

    def _error(self, text: str, error: SelectionError) -> LayerError:
        i = next(i for i, layer in enumerate(self.params.layers) if layer.selection == text)
        return LayerError(f"layers.{i}.selection", error)

    def _wait(self, future: Future[list[Result]]) -> list[Result]:
        try:
            return future.result()
        except SelectionError as exc:
            raise self._failed(self._due(), exc) from None

    async def _await(self, future: Future[list[Result]]) -> list[Result]:
        try:
            return await asyncio.wrap_future(future)
        except SelectionError as exc:
            raise self._failed(self._due(), exc) from None

    def _coil(self, exc: BaseException) -> npt.NDArray[np.uint8]:
        log.warning("tube layers drawn without secondary structure: %s", exc)
        return np.zeros(self.topology.n_atoms, dtype=np.uint8)

    def _wait_codes(self, future: Future[npt.NDArray[np.uint8]]) -> npt.NDArray[np.uint8]:
        try:
            return future.result()
        except SelectionError as exc:
            return self._coil(exc)

    async def _await_codes(self, future: Future[npt.NDArray[np.uint8]]) -> npt.NDArray[np.uint8]:
        try:
            return await asyncio.wrap_future(future)
        except SelectionError as exc:
            return self._coil(exc)

    def _plan(
        self, texts: list[str], found: list[Result], frame_key: Any
    ) -> tuple[LayerPlan, ...] | None:
        for text, result in zip(texts, found, strict=True):
            if isinstance(result, SelectionError) and not isinstance(result, SelectionSkippedError):
                raise self._error(text, result)
        atoms: dict[str, npt.NDArray[np.int32]] = {}
        for text, result in zip(texts, found, strict=True):
            if isinstance(result, SelectionError):
                raise self._error(text, result)
            atoms[text] = np.asarray(result, dtype=np.int32)
            if not is_dynamic(text):  # kept for the job
                self._static[text] = atoms[text]

        def select(text: str) -> tuple[npt.NDArray[np.int32], Any]:
            if text in atoms:
                return atoms[text], ((text, frame_key) if is_dynamic(text) else text)
            return self._static[text], text

        def secondary() -> npt.NDArray[np.uint8]:
            assert self._codes is not None
            return self._codes

        return plan_layers(self.params, self.topology.n_atoms, select, secondary)
