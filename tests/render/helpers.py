"""Glue between renderer inputs and the numpy oracle."""

from __future__ import annotations

import numpy as np

from protocol import Camera, RenderParams, Topology
from server.render import colors
from server.render.renderer import Renderer
from tests.render.oracle import Molecule


def oracle_molecule(topology: Topology, positions: np.ndarray, params: RenderParams) -> Molecule:
    """The documented density of these inputs: w_i = 1, s_i = sigma (or sigma r_i / 1.7)."""
    n = topology.n_atoms
    if params.radius_mode == "vdw":
        sig = params.sigma_A * colors.atom_radii(topology).astype(np.float64) / colors.R_REF
    else:
        sig = np.full(n, params.sigma_A)
    rgb = colors.unpack_rgba(colors.atom_colors(topology, params.color_by, params.uniform_color))
    return Molecule(
        positions=np.asarray(positions, dtype=np.float64),
        weights=np.ones(n),
        sigmas=sig,
        k=params.cutoff_sigmas,
        colors=rgb,
    )


def render(
    device: str,
    topology: Topology,
    positions: np.ndarray,
    params: RenderParams,
    camera: Camera,
    width: int,
    height: int,
    **kw: object,
) -> Renderer:
    r = Renderer(device, **kw)  # type: ignore[arg-type]
    r.set_topology(topology)
    if topology.n_atoms:
        r.set_positions(positions)
    r.render(params, camera, width, height)
    return r
