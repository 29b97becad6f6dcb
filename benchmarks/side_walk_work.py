"""How much of the geodesic density's route work a march needs when it asks only for each
sample's side of the level (`geodesic_field.geodesic_side4`): float64, on villin, strength 1,
every sample along orthographic rays where the classical density times the gate
(`Routes.gate`) reaches the level, up to each ray's first geodesic crossing. The atoms are
walked in one of three orders and the walk stops once the geodesic terms reach the level or
can no longer (the classical terms of the atoms left, times the gate, bound theirs); the
control is the whole walk, every route of every atom within reach. Also counted: the samples
the classical density alone would gate (the gate's control), and per ray how many gated
samples a ray that crosses takes and how many lattice steps lie between its first one and its
crossing (the gate's lead: how far outside the surface the bound lets costly samples begin).
And what a gated sample's routes share (`sharing`): the classical density's Gaussians there
(its atoms within reach, the control), the (atom, bond) entries of their route tables that the
route loop evaluates one by one, the distinct bonds and the distinct bond ends (nodes) among
them, and the (atom, node) pairs: a bond's geometry at a sample is the same for every atom
whose table holds it, so these bound what an evaluation that computed each bond once would do.

    python benchmarks/side_walk_work.py --out benchmarks/results/side_walk_work.json

Orders: `cells`, the renderer's cell rows (z, then y, then x); `bands`, the renderer's
SIDE_BANDS of e = r^2 / 2 s^2, nearest band first, cell rows within a band; `nearest`, atom by
atom by distance (the least any order can walk, and no walk over cells gives it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scipy.spatial import cKDTree

from server.render.geodesic import BondGraph, Geodesic, classical_density, taper
from server.render.geodesic_field import SIDE_BANDS, SIDE_SLACK
from server.render.reach import reach_sigmas
from tests.render.molecules import villin

ORDERS = ("cells", "bands", "nearest")


def study(sigma: float, rays: int, smoothing: float = 0.6) -> dict[str, Any]:
    mol = villin()
    pos = mol.positions.astype(np.float64)
    ones = np.ones(len(pos))
    k = reach_sigmas(sigma, 4.0)
    reach = k * sigma
    tau = smoothing * sigma
    geo = Geodesic.build(pos, ones, BondGraph.of(mol.topology), reach)
    gate = math.exp(-(tau**2) / (2.0 * sigma * sigma))
    level = 0.25 * float(geo.density(pos, sigma, smoothing=smoothing, cutoff_sigmas=k).mean())
    routes = np.diff(geo.routes.start)
    cell = np.floor((pos - pos.min(axis=0)) / (reach / 2.0)).astype(np.int64)
    cell_key = (cell[:, 2] * 1000 + cell[:, 1]) * 1000 + cell[:, 0]
    tree = cKDTree(pos)
    lo, hi = pos.min(axis=0) - 4.0, pos.max(axis=0) + 4.0
    xs, ys = np.linspace(lo[0], hi[0], rays), np.linspace(lo[1], hi[1], rays)
    zs = np.arange(hi[2], lo[2], -0.25 * sigma)
    whole = 0
    walked = dict.fromkeys(ORDERS, 0)
    samples = 0
    classically_gated = 0
    per_hit: list[int] = []  # gated samples of each ray that crosses, up to its crossing
    per_miss: list[int] = []  # gated samples of each ray that never crosses
    lead: list[int] = []  # lattice steps from a ray's first gated sample to its crossing
    shared: dict[str, list[int]] = {key: [] for key in SHARED}
    for x in xs:
        pts = np.stack(np.broadcast_arrays(x, ys[:, None], zs[None, :]), -1).reshape(-1, 3)
        cls = classical_density(pts, pos, ones, sigma, k).reshape(len(ys), len(zs))
        gated = cls * gate >= level
        val = np.zeros_like(cls)
        if gated.any():
            inside = pts[gated.ravel()]
            val[gated] = geo.density(inside, sigma, smoothing=smoothing, cutoff_sigmas=k)
        for i in range(len(ys)):
            crossing = np.nonzero(val[i] >= level)[0]
            end = crossing[0] + 1 if len(crossing) else len(zs)
            if len(crossing):
                per_hit.append(int(gated[i, :end].sum()))
                lead.append(int(crossing[0] - np.nonzero(gated[i])[0][0]))
            elif gated[i].any():
                per_miss.append(int(gated[i].sum()))
            classically_gated += int((cls[i, :end] >= level).sum())
            for z in zs[:end][gated[i, :end]]:
                p = np.array([x, ys[i], z])
                near = np.asarray(tree.query_ball_point(p, reach), dtype=np.int64)
                e = ((pos[near] - p) ** 2).sum(axis=1) / (2.0 * sigma * sigma)
                ct = taper(e, k)
                m = geo.routes_of(np.repeat(p[None], len(near), axis=0), near, tau)
                gt = taper(m * m / (2.0 * sigma * sigma), k)
                c0 = ct.sum()
                samples += 1
                for key, value in _shared(geo, near).items():
                    shared[key].append(value)
                whole += int(routes[near].sum())
                band = np.searchsorted(np.asarray(SIDE_BANDS), e, side="right")
                keys = {
                    "cells": cell_key[near],
                    "bands": band * 10**12 + cell_key[near],
                    "nearest": e,
                }
                for name, key in keys.items():
                    order = np.argsort(key, kind="stable")
                    g = np.cumsum(gt[order])
                    rest = c0 - np.cumsum(ct[order])
                    decided = (g >= level) | (g + (rest + SIDE_SLACK * c0) * gate < level)
                    stop = int(np.argmax(decided)) if decided.any() else len(order) - 1
                    walked[name] += int(routes[near][order][: stop + 1].sum())
    return {
        "sigma_A": sigma,
        "smoothing": smoothing,
        "level": level,
        "rays": rays * rays,
        "gate": gate,
        "gated_samples": samples,
        "classically_gated_samples": classically_gated,
        "routes_whole_walk": whole,
        "fraction_walked": {name: walked[name] / whole for name in ORDERS},
        "rays_crossing": len(per_hit),
        "gated_samples_per_crossing_ray": _spread(per_hit),
        "steps_from_gate_to_crossing": _spread(lead),
        "rays_gated_not_crossing": len(per_miss),
        "gated_samples_per_ray_not_crossing": _spread(per_miss),
        "sharing": {key: _spread(values) for key, values in shared.items()},
    }


SHARED = ("atoms", "table_entries", "bonds", "nodes", "atom_nodes")


def _shared(geo: Geodesic, near: npt.NDArray[np.int64]) -> dict[str, int]:
    """At one sample: the atoms within reach, their route tables' (atom, bond) entries, the
    distinct bonds and bond ends (nodes within the tables' reach) among them, and the
    (atom, node) pairs."""
    t = geo.routes
    ends = geo.graph.ends
    bonds: list[npt.NDArray[np.int32]] = []
    nodes: list[npt.NDArray[np.int32]] = []
    pairs = 0
    for a in near:
        b, gi, gj = t.of_atom(int(a))
        bonds.append(b)
        reached = np.unique(
            np.concatenate([ends[b[np.isfinite(gi)], 0], ends[b[np.isfinite(gj)], 1]])
        )
        nodes.append(reached)
        pairs += len(reached)
    every = np.concatenate(bonds) if bonds else np.zeros(0, np.int32)
    return {
        "atoms": len(near),
        "table_entries": len(every),
        "bonds": len(np.unique(every)),
        "nodes": len(np.unique(np.concatenate(nodes))) if nodes else 0,
        "atom_nodes": pairs,
    }


def _spread(values: list[int]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64) if values else np.zeros(1)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sigmas", default="1.5", help="comma-separated sigmas in A")
    p.add_argument("--rays", type=int, default=40, help="rays along each side of the grid")
    p.add_argument("--out", default="")
    args = p.parse_args(argv)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    rows = []
    for s in (float(v) for v in args.sigmas.split(",")):
        row = study(s, args.rays)
        rows.append(row)
        print(json.dumps(row))
    res = {
        "benchmark": "side_walk_work",
        "gpu": "cpu",
        "device": "float64 on the CPU",
        "date": started,
        "system": "villin (the demo's, with hydrogens)",
        "side_bands_e": list(SIDE_BANDS),
        "rows": rows,
    }
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
