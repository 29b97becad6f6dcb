"""Layers on a solvated system: what hiding the solvent and adding a layer cost.

A 1M-atom system, about 10 % protein (adenylate kinase copies, `render_bench.build_system`) in a
box of water at liquid density, with a ligand (one ring-rich residue of 40 atoms) in the
protein. Every timed frame gets new positions for every atom (a small random displacement, as a
simulation sends) and draws at 1920x1080 with the grid of every layer rebuilt; the frame time is
the host wall clock of the render, which synchronises. In the same run:

* `protein_only`: the protein's atoms alone, one plain renderer (what a dry system costs);
* `protein_layer`: the whole solvated system with one layer, `protein` (the water hidden);
* `protein_ligand`: the same plus the ligand as a second, finer layer (sigma 0.6 A);
* `protein_licorice`: the protein surface at half opacity with the ligand as sticks.

Targets (issue: selections and layers): protein layer <= 1.3x protein only; two layers <= 1.5x
one layer.

    python benchmarks/layers_bench.py --device cuda:0 --out benchmarks/results/layers_h100.json
    python benchmarks/layers_bench.py --quick --device cpu --out /tmp/layers_quick.json
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import warp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.render_bench import build_system, topology_of
from protocol import Layer, RenderParams
from server.render import device as devmod
from server.render.camera import fit_camera
from server.render.layerplan import plan_layers, visible_atoms
from server.render.layers import LayeredRenderer
from server.render.renderer import Renderer

wp: Any = warp

WATER_PER_A3 = 0.0334
"""Water molecules per cubic angstrom at 300 K."""


def solvated(n_total: int, protein_share: float, seed: int = 0) -> dict[str, Any]:
    """Positions, elements and the atom sets of a protein (with a ligand) in water."""
    rng = np.random.default_rng(seed)
    n_protein = int(n_total * protein_share)
    ppos, pel, pbonds = build_system(n_protein, seed)
    lo, hi = ppos.min(axis=0) - 6.0, ppos.max(axis=0) + 6.0
    n_water = (n_total - n_protein) // 3
    side = max(float((n_water / WATER_PER_A3) ** (1 / 3)), float((hi - lo).max()))
    centre = 0.5 * (lo + hi)
    oxygens = centre + (rng.random((n_water, 3)) - 0.5) * side
    hydrogens = oxygens[:, None, :] + rng.normal(size=(n_water, 2, 3)) * 0.55
    water = np.concatenate([oxygens[:, None, :], hydrogens], axis=1).reshape(-1, 3)
    wel = np.tile(np.array(["O", "H", "H"]), n_water)
    pos = np.concatenate([ppos, water]).astype(np.float32)
    el = np.concatenate([pel, wel])
    n = len(pos)
    # the ligand: the 40 protein atoms nearest the protein's centre of mass
    d = np.linalg.norm(ppos - ppos.mean(axis=0), axis=1)
    ligand = np.sort(np.argsort(d)[:40]).astype(np.int32)
    protein = np.setdiff1d(np.arange(n_protein, dtype=np.int32), ligand)
    return {
        "positions": pos,
        "elements": el,
        "bonds": pbonds,
        "n": n,
        "protein": protein,
        "ligand": ligand,
    }


def frames_of(pos: np.ndarray, count: int, seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [pos + rng.normal(size=pos.shape).astype(np.float32) * 0.05 for _ in range(count)]


def timed(step: Any, frames: int, warmup: int) -> dict[str, float]:
    walls = []
    for i in range(warmup + frames):
        t0 = time.perf_counter()
        step(i)
        if i >= warmup:
            walls.append((time.perf_counter() - t0) * 1e3)
    a = np.asarray(walls)
    return {
        "median_ms": float(np.median(a)),
        "p90_ms": float(np.percentile(a, 90)),
        "fps": float(1e3 / np.median(a)),
        "frames": len(walls),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--atoms", type=int, default=1_000_000)
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--quick", action="store_true", help="a small system, a few frames")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.quick:
        args.atoms, args.size, args.frames = min(args.atoms, 20_000), "320x180", 3
    w, h = (int(v) for v in args.size.split("x"))
    device = devmod.resolve(args.device)
    sysm = solvated(args.atoms, 0.1)
    pos, el, n = sysm["positions"], sysm["elements"], sysm["n"]
    protein, ligand = sysm["protein"], sysm["ligand"]
    top = topology_of(el, sysm["bonds"])
    frames = frames_of(pos, 4)
    sets = {"protein": protein, "ligand": ligand}
    warmup = 3 if not args.quick else 1
    cam = fit_camera(pos[np.union1d(protein, ligand)], w, h)
    base = RenderParams()
    results: dict[str, Any] = {}

    # the protein alone: a dry system of the same atoms
    dry = Renderer(device, max_atoms=max(len(protein), 1))
    dry.set_topology(topology_of(el[protein]))
    dry_frames = [f[protein] for f in frames]

    def dry_step(i: int) -> None:
        dry.set_positions(dry_frames[i % len(dry_frames)], check_finite=False)
        dry.render(base, cam, w, h)  # synchronises: the image is done

    results["protein_only"] = timed(dry_step, args.frames, warmup)

    cases = {
        "protein_layer": [Layer(name="protein", selection="protein")],
        "protein_ligand": [
            Layer(name="protein", selection="protein"),
            Layer(name="ligand", selection="ligand", sigma_A=0.6, color_by="element"),
        ],
        "protein_licorice": [
            Layer(name="protein", selection="protein", opacity=0.5),
            Layer(name="ligand", selection="ligand", mode="licorice"),
        ],
    }
    for name, layers in cases.items():
        params = base.model_copy(update={"layers": layers})
        plans = plan_layers(params, n, lambda t: (sets[t], t))
        assert plans is not None
        lr = LayeredRenderer(lambda: Renderer(device, max_atoms=max(len(protein), 1)))

        def step(i: int, lr: LayeredRenderer = lr, plans: Any = plans) -> None:
            lr.render(plans, top, 1, frames[i % len(frames)], i + 1, cam, w, h)

        results[name] = timed(step, args.frames, warmup)
        results[name]["stages_last_ms"] = dict(lr.timings)
        shown = visible_atoms(plans, n)
        results[name]["atoms_drawn"] = len(shown)
    one = results["protein_layer"]["median_ms"]
    ratios = {
        "protein_layer_over_protein_only": one / results["protein_only"]["median_ms"],
        "two_layers_over_one": results["protein_ligand"]["median_ms"] / one,
        "licorice_pair_over_one": results["protein_licorice"]["median_ms"] / one,
    }
    doc = {
        "device": device,
        "gpu": str(wp.get_device(device).name),
        "host": platform.node(),
        "atoms": n,
        "protein_atoms": len(protein),
        "ligand_atoms": len(ligand),
        "size": [w, h],
        "results": results,
        "ratios": ratios,
        "targets": {"protein_layer_over_protein_only": 1.3, "two_layers_over_one": 1.5},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2))
    for key, value in results.items():
        print(f"{key:18s} {value['median_ms']:8.2f} ms  ({value['fps']:.0f} fps)")
    for key, value in ratios.items():
        print(f"{key:34s} {value:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
