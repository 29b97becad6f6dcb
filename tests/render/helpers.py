"""Glue between renderer inputs and the numpy oracle."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from protocol import Camera, RenderParams, Topology
from server.render import colors
from server.render.density import GAUSSIAN
from server.render.reach import reach_sigmas
from server.render.renderer import MEAN_SAMPLES, Renderer
from server.render.skeleton import Skeleton, carved_density
from server.render.tuning import Tuning
from tests.render import oracle
from tests.render.oracle import Molecule, density


def oracle_molecule(topology: Topology, positions: np.ndarray, params: RenderParams) -> Molecule:
    """The documented density of these inputs: w_i = 1, s_i = sigma (or sigma r_i / 1.7)."""
    n = topology.n_atoms
    if params.radius_mode == "vdw":
        sig = params.sigma_A * colors.atom_radii(topology).astype(np.float64) / colors.R_REF
    else:
        sig = np.full(n, params.sigma_A)
    rgb = colors.unpack_rgba(colors.atom_colors(topology, params.color_by, params.uniform_color))
    raw = Molecule(
        positions=np.asarray(positions, dtype=np.float64),
        weights=colors.atom_weights(topology, params.density_weights).astype(np.float64),
        sigmas=sig,
        k=reach_sigmas(params.sigma_A, params.cutoff_sigmas),
        colors=rgb,
    )
    if params.level_scale == "absolute" or n == 0:
        return raw
    return replace(raw, weights=raw.weights / density_scale(raw))


def density_scale(mol: Molecule) -> float:
    """The documented scale of relative levels: the mean density at every (n // 4096)-th atom
    (all atoms up to 4096)."""
    n = len(mol.positions)
    samples = min(n, MEAN_SAMPLES)
    at = mol.positions[np.arange(samples) * (n // samples)]
    return float(density(mol, at)[0].mean())


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
    density = kw.pop("density", GAUSSIAN)
    r = Renderer(device, density=density, tuning=Tuning.of(kw) if kw else None)  # type: ignore[arg-type]
    r.set_topology(topology)
    if topology.n_atoms:
        r.set_positions(positions)
    r.render(params, camera, width, height)
    return r


def carved_reference(
    topology: Topology, positions: np.ndarray, params: RenderParams
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The documented carved density of these inputs (float64, every atom), with the same
    relative-level scale as the renderer: (S, grad S) at (m, 3) points."""
    skeleton = Skeleton.of(topology)
    dens = colors.atom_weights(topology, params.density_weights).astype(np.float64)
    pos = np.asarray(positions, dtype=np.float64)
    strength = params.warp_strength if params.scale_space in ("carved", "warped") else 0.0

    def raw(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return carved_density(
            points, pos, dens, skeleton, params.sigma_A, strength, params.cutoff_sigmas
        )

    scale = 1.0
    n = topology.n_atoms
    if params.level_scale == "mean" and n:
        samples = min(n, MEAN_SAMPLES)
        scale = float(raw(pos[np.arange(samples) * (n // samples)])[0].mean())

    def density_at(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s, g = raw(points)
        return s / scale, g / scale

    return density_at


def oracle_light(params: RenderParams, frame: Any, r: Renderer) -> oracle.Light:
    """The oracle's lighting for `params` as the caster applies it to `frame` (the key light
    fixed to the camera, the depth cue across the last grid's box)."""
    from server.render import raycast

    info = r.grid_info()
    lo = np.asarray(info["origin"], dtype=np.float64)
    hi = np.asarray(info["box_hi"], dtype=np.float64)
    center, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    dc = float((center - frame.eye) @ frame.forward)
    light = params.lighting
    return oracle.Light(
        ambient=light.ambient,
        diffuse=light.diffuse,
        specular=light.specular,
        shininess=light.shininess,
        head_weight=0.6 if light.key_light else 1.0,
        key_weight=0.55 if light.key_light else 0.0,
        key_dir=raycast.key_light_direction(frame),
        background=np.array(params.background),
        depth_cue=light.depth_cue,
        fog_near=max(dc - radius, 0.0),
        fog_far=dc + radius,
    )
