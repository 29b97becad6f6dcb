"""Layer plans: which atoms each layer draws and with which parameters (plain numpy; the
compositing renderer is `server.render.layers`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Layer, RenderParams, Topology, WireArray


@dataclass(frozen=True, eq=False)
class LayerPlan:
    """One layer of an image: its atoms (sorted indices into the system; None: every atom),
    the parameters it is drawn with (the session's, with the layer's own fields) and its
    opacity. `atoms_key` changes whenever the atom set does (a re-evaluated selection)."""

    name: str
    atoms: npt.NDArray[np.int32] | None
    params: RenderParams
    opacity: float = 1.0
    atoms_key: Any = None
    style: str = "density"
    """`density` (the parameters' iso or volume), `licorice` or `tube`."""
    radius_A: float | None = None
    secondary: npt.NDArray[np.uint8] | None = None
    """For a tube: each of the layer's atoms' secondary structure (0 coil, 1 helix, 2 strand)."""


def layer_params(base: RenderParams, layer: Layer) -> RenderParams:
    """The parameters `layer` is drawn with: the session's, with the fields it sets itself."""
    own = layer.overrides()
    if "tf_preset" in own and "transfer_function" not in own:
        own["transfer_function"] = []  # the layer's preset, not the session's own points
    return base.model_copy(update={**own, "layers": []})


def plan_layers(
    params: RenderParams,
    n_atoms: int,
    select: Callable[[str], tuple[npt.NDArray[np.int32], Any]],
    secondary: Callable[[], npt.NDArray[np.uint8] | None] | None = None,
) -> tuple[LayerPlan, ...] | None:
    """The visible layers of `params` in order (None: no layers, draw every atom the single
    way). `select(text)` returns a selection's sorted atom indices and a key that changes
    when they do; it raises for an invalid selection. `secondary()` gives every atom's
    secondary structure, asked for only when a tube layer is drawn."""
    if not params.layers:
        return None
    plans: list[LayerPlan] = []
    for layer in params.layers:
        if not layer.visible or layer.opacity <= 0.0:
            continue
        atoms, key = select(layer.selection)
        if len(atoms) == 0:
            continue
        whole = len(atoms) == n_atoms
        codes = secondary() if secondary is not None and layer.mode == "tube" else None
        if codes is not None and not whole:
            codes = codes[atoms]
        plans.append(
            LayerPlan(
                name=layer.name,
                atoms=None if whole else np.asarray(atoms, dtype=np.int32),
                params=layer_params(params, layer),
                opacity=float(layer.opacity),
                atoms_key="all" if whole else key,
                style=layer.mode if layer.mode in ("licorice", "tube") else "density",
                radius_A=layer.radius_A,
                secondary=codes,
            )
        )
    return tuple(plans)


def visible_atoms(plans: Sequence[LayerPlan] | None, n_atoms: int) -> npt.NDArray[np.int32]:
    """Every atom some visible layer draws (what a camera fit should frame)."""
    if plans is None or any(p.atoms is None for p in plans):
        return np.arange(n_atoms, dtype=np.int32)
    if not plans:
        return np.zeros(0, dtype=np.int32)
    return np.unique(np.concatenate([p.atoms for p in plans if p.atoms is not None]))


def subset_topology(topology: Topology, atoms: npt.NDArray[np.int32]) -> Topology:
    """The topology of `atoms` alone: their fields in that order, and the bonds between them
    renumbered. Built without validation: a part of a topology already held is valid, and a
    part of a system larger than a message may carry (a sort-last slab of 100M atoms) must not
    be refused by the wire's limits."""
    idx = np.asarray(atoms, dtype=np.int64)
    n = len(idx)
    remap = np.full(topology.n_atoms, -1, dtype=np.int64)
    remap[idx] = np.arange(n)
    bonds = topology.bonds.to_numpy().reshape(-1, 2).astype(np.int64)
    if len(bonds):
        ends = remap[bonds]
        bonds = ends[(ends >= 0).all(axis=1)]

    def pick(values: list[str]) -> list[str]:
        if 4 * n < len(values):  # a few atoms of many: converting the whole list costs more
            return [values[int(i)] for i in idx]
        picked: list[str] = np.asarray(values, dtype=object)[idx].tolist()
        return picked

    def floats(arr: WireArray | None) -> WireArray | None:
        return None if arr is None else WireArray.from_numpy(arr.to_numpy()[idx], "<f4")

    return Topology.model_construct(
        n_atoms=n,
        elements=pick(topology.elements),
        names=pick(topology.names),
        residue_ids=WireArray.from_numpy(topology.residue_ids.to_numpy()[idx], "<i4"),
        residue_names=pick(topology.residue_names),
        chain_ids=pick(topology.chain_ids),
        bonds=WireArray.from_numpy(bonds.astype(np.int32).reshape(-1, 2), "<i4"),
        radii=floats(topology.radii),
        charges=floats(topology.charges),
        bfactors=floats(topology.bfactors),
        title=topology.title,
        engine=topology.engine,
    )
