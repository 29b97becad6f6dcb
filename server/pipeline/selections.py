"""Layer selections for renders outside a live session (REST renders, jobs, Ray chunks).

Static selections are evaluated once per topology; distance-based ones on every frame, since a
batch job sees each frame once and in order.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.render.layerplan import LayerPlan, plan_layers
from structures.selection import SelectionError, Selector, check_syntax, is_dynamic


def check_layers(params: p.RenderParams) -> None:
    """Raise ValueError naming the first layer whose selection does not parse."""
    for i, layer in enumerate(params.layers):
        try:
            check_syntax(layer.selection)
        except SelectionError as exc:
            raise ValueError(f"layers.{i}.selection: {exc}") from None


class FrameLayers:
    """The layer plans of one parameter set on one topology, frame after frame."""

    def __init__(
        self,
        params: p.RenderParams,
        topology: p.Topology,
        reference: npt.NDArray[np.float32] | None = None,
    ) -> None:
        """`reference`: the positions secondary structure is assigned at (the job's reference
        frame, so every chunk of a distributed job draws the same helices); else the first
        frame asked for."""
        self.params = params
        self.topology = topology
        self._selector = Selector(topology) if params.layers else None
        self._reference = reference
        self._codes: npt.NDArray[np.uint8] | None = None

    def plans(
        self,
        positions: npt.NDArray[np.float32],
        frame_key: Any,
        box: npt.NDArray[np.float32] | None = None,
    ) -> tuple[LayerPlan, ...] | None:
        """The visible layers at this frame (None: no layers); raises SelectionError."""
        selector = self._selector
        if selector is None:
            return None

        def select(text: str) -> tuple[npt.NDArray[np.int32], Any]:
            atoms = selector.select(text, positions, box)
            return atoms, ((text, frame_key) if is_dynamic(text) else text)

        def secondary() -> npt.NDArray[np.uint8]:
            if self._codes is None:  # assigned once, kept for the job
                at = positions if self._reference is None else self._reference
                self._codes = selector.secondary(at)
            return self._codes

        return plan_layers(self.params, self.topology.n_atoms, select, secondary)
