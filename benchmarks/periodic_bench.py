"""Periodic frames on the render device: what making molecules whole, centring, wrapping,
following and fitting cost per frame, beside copying the same frame to the device.

A solvated system of N atoms (a protein-like chain of 2 % of the atoms, a random walk of 1.5 A
bonds, and three-atom waters) sits in a rhombic dodecahedron (the adenylate kinase box of
MDAnalysisTests) with every atom wrapped into it, so the chain and some waters are cut by the
box. Each mode runs on frames that move every atom a little, and three figures are taken:

* `device_ms`: the kernels alone, the frame already on the device (what a renderer that holds
  the positions pays), with a device synchronisation around them;
* `round_trip_ms`: the frame copied to the device, transformed, and read back to the host (what
  the server pays today: every consumer of the frame gets the displayed positions);
* `upload_ms`: the baseline in the same run, the frame copied to the device alone;
  `device_per_upload` = device_ms / upload_ms.

With `--live`, the same system goes through the server's GPU queue as a live session's frames
do, each frame drawn at 1920x1080 after it arrives, three ways in one run: `plain_ms` (no box
steps: the frame staged in page-locked memory and uploaded, the baseline), `on_device_ms` (the
frame displayed on the device and drawn from there) and `host_copy_ms` (the control: displayed,
then drawn from a host copy, so uploaded again as before). `overhead_ms` = on_device - plain is
what the box steps add to a live frame.

With `--mdanalysis`, MDAnalysisTests' adenylate kinase (47,681 atoms, GROMACS TPR/XTC) is also
transformed by MDAnalysis' own transformations (unwrap, center_in_box, wrap of fragments) and by
this device's kernels, frame for frame: `mdanalysis_per_device` is their ratio.

    python benchmarks/periodic_bench.py --device cuda:0 --out benchmarks/results/periodic_h200.json
    python benchmarks/periodic_bench.py --quick --device cpu --out /tmp/periodic_quick.json
    python benchmarks/periodic_bench.py --device cuda:0 --sizes 1000000 --live --out ...
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import warp as wp

from protocol import Topology, WireArray
from server.render import device as render_device
from server.render.boxes import Options
from server.render.periodic import PeriodicTransform

MODES: dict[str, dict[str, Any]] = {
    "whole": {"mode": "whole"},
    "molecules+centre": {"mode": "molecules", "centre": True},
    "unwrap+centre": {"mode": "unwrap", "centre": True},
    "molecules+centre+fit": {"mode": "molecules", "centre": True, "fit": "rotation"},
}


def median(xs: list[float]) -> float:
    return float(np.median(xs)) if xs else float("nan")


def dodecahedron(side: float) -> npt.NDArray[np.float64]:
    """A rhombic dodecahedron's box vectors (rows), as GROMACS writes them."""
    return np.array([[side, 0.0, 0.0], [0.0, side, 0.0], [side / 2, side / 2, side / np.sqrt(2.0)]])


def build_system(n: int, seed: int = 3) -> tuple[Topology, npt.NDArray[np.float32], Any]:
    """A chain of 2 % of the atoms and waters, wrapped into a box of water's density."""
    rng = np.random.default_rng(seed)
    chain = max(100, n // 50)
    waters = (n - chain) // 3
    n = chain + 3 * waters
    volume = n / 0.1  # 0.1 atoms per cubic angstrom, as liquid water
    box = dodecahedron((volume / (1 / np.sqrt(2.0))) ** (1 / 3))
    steps = rng.normal(size=(chain, 3))
    steps *= 1.5 / np.linalg.norm(steps, axis=1, keepdims=True)
    walk = np.cumsum(steps, axis=0)
    walk -= walk.mean(axis=0)
    walk += box.sum(axis=0) / 2 - box[0] * 0.45  # near a face: the box cuts it
    oxygens = rng.random((waters, 3)) @ box
    h1 = oxygens + rng.normal(size=(waters, 3)) * 0.55
    h2 = oxygens + rng.normal(size=(waters, 3)) * 0.55
    water = np.stack([oxygens, h1, h2], axis=1).reshape(-1, 3)
    pos = np.concatenate([walk, water])
    frac = pos @ np.linalg.inv(box)
    pos = (frac - np.floor(frac)) @ box
    chain_bonds = np.stack([np.arange(chain - 1), np.arange(1, chain)], axis=1)
    first = chain + 3 * np.arange(waters)
    water_bonds = np.concatenate(
        [np.stack([first, first + 1], axis=1), np.stack([first, first + 2], axis=1)]
    )
    bonds = np.concatenate([chain_bonds, water_bonds]).astype(np.int32)
    elements = ["C"] * chain + ["O", "H", "H"] * waters
    topology = Topology(
        n_atoms=n,
        elements=elements,
        names=["CA"] * chain + ["OW", "HW1", "HW2"] * waters,
        residue_ids=WireArray.from_numpy(
            np.concatenate([np.arange(chain) + 1, np.repeat(np.arange(waters), 3) + chain + 1]),
            "<i4",
        ),
        residue_names=["ALA"] * chain + ["SOL"] * (3 * waters),
        chain_ids=["A"] * n,
        bonds=WireArray.from_numpy(bonds, "<i4"),
    )
    return topology, pos.astype(np.float32), box


def options_for(spec: dict[str, Any], chain: npt.NDArray[np.int32]) -> Options:
    return Options(
        mode=spec["mode"],
        centre=chain if spec.get("centre") else None,
        fit=spec.get("fit", "off"),
        fit_atoms=chain if spec.get("fit") else None,
    )


def bench_size(device: str, n: int, frames: int) -> dict[str, Any]:
    topology, pos, box = build_system(n)
    chain = np.flatnonzero(np.asarray(topology.residue_names) != "SOL").astype(np.int32)
    rng = np.random.default_rng(1)
    jitter = [rng.normal(scale=0.05, size=pos.shape).astype(np.float32) for _ in range(4)]
    out: dict[str, Any] = {"atoms": topology.n_atoms, "chain_atoms": len(chain), "modes": []}
    transform = PeriodicTransform(device)
    t0 = time.perf_counter()
    transform.set_topology(topology)
    out["topology_ms"] = (time.perf_counter() - t0) * 1e3
    mol = transform.molecules
    assert mol is not None
    out["molecules"] = mol.n_molecules
    out["pointer_rounds"] = mol.rounds
    out["device_bytes_per_atom"] = transform.nbytes() / topology.n_atoms
    frame = [pos + j for j in jitter]
    uploads = []
    for i in range(frames + 2):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        transform.upload(frame[i % len(frame)])
        wp.synchronize_device(device)
        if i >= 2:
            uploads.append((time.perf_counter() - t0) * 1e3)
    out["upload_ms"] = median(uploads)
    for name, spec in MODES.items():
        options = options_for(spec, chain)
        transform.restart()
        transform.apply(frame[0], box, options)  # compile, reference, first frame
        device_times, round_trips = [], []
        for i in range(frames):
            transform.upload(frame[i % len(frame)])
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            transform.run(box, options)
            wp.synchronize_device(device)
            device_times.append((time.perf_counter() - t0) * 1e3)
        for i in range(frames):
            t0 = time.perf_counter()
            transform.apply(frame[i % len(frame)], box, options)
            round_trips.append((time.perf_counter() - t0) * 1e3)
        row = {
            "mode": name,
            "device_ms": median(device_times),
            "round_trip_ms": median(round_trips),
        }
        row["device_per_upload"] = row["device_ms"] / out["upload_ms"]
        out["modes"].append(row)
        print(f"  {topology.n_atoms} atoms {name}: {row}", flush=True)
    return out


def bench_live(device: str, n: int, frames: int, size: tuple[int, int]) -> dict[str, Any]:
    """Live frames through `GpuQueue`: plain, displayed on the device, displayed then drawn from
    a host copy (one slot each, the variants taking turns frame by frame)."""
    from protocol import Camera, RenderParams
    from server.pipeline.gpu import DisplayRequest, GpuQueue, RenderRequest, Snapshot

    topology, pos, box = build_system(n)
    chain = np.flatnonzero(np.asarray(topology.residue_names) != "SOL").astype(np.int32)
    options = options_for(MODES["molecules+centre"], chain)
    rng = np.random.default_rng(2)
    frame = [pos + rng.normal(scale=0.05, size=pos.shape).astype(np.float32) for _ in range(4)]
    centre = tuple(float(c) for c in box.sum(axis=0) / 2)
    camera = Camera(target=centre, distance=float(2.2 * np.linalg.norm(box[0])))
    params = RenderParams()
    width, height = size
    queue = GpuQueue(device=device)
    ids = {"plain": 0, "on_device": 0, "host_copy": 0}

    def one(variant: str, i: int) -> float:
        slot = f"session:{variant}"
        raw = frame[i % len(frame)]
        t0 = time.perf_counter()
        ids[variant] += 1
        if variant == "plain":
            shown = raw
        else:
            request = DisplayRequest(slot, topology, raw, box, options)
            shown = queue.display_sync(request).positions
            if variant == "host_copy":
                shown = shown.copy()
        queue.stage(slot, ids[variant], shown)
        snap = Snapshot(topology, shown, positions_id=ids[variant])
        queue.render_sync(RenderRequest(slot, snap, params, camera, width, height))
        return (time.perf_counter() - t0) * 1e3

    times: dict[str, list[float]] = {k: [] for k in ids}
    try:
        for i in range(frames + 5):
            for variant in ids:
                ms = one(variant, i)
                if i >= 5:
                    times[variant].append(ms)
        froms = {v: queue._slots[f"session:{v}"].renderer.uploaded_from for v in ids}
    finally:
        queue.close()
    out: dict[str, Any] = {"atoms": topology.n_atoms, "image": f"{width}x{height}"}
    for variant, ms in times.items():
        out[f"{variant}_ms"] = median(ms)
    out["uploaded_from"] = froms
    out["overhead_ms"] = out["on_device_ms"] - out["plain_ms"]
    out["host_copy_overhead_ms"] = out["host_copy_ms"] - out["plain_ms"]
    print(f"  live {topology.n_atoms} atoms: {out}", flush=True)
    return out


def bench_mdanalysis(device: str, frames: int) -> dict[str, Any]:
    """MDAnalysis' transformations against this device's kernels on adenylate kinase."""
    import MDAnalysis as mda
    from MDAnalysis import transformations as trans
    from MDAnalysisTests.datafiles import TPR, XTC

    from structures.reader import topology_of

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe(TPR, XTC)
        ref = mda.Universe(TPR, XTC)
    topology = topology_of(u, guess_bonds=False)
    protein = ref.select_atoms("protein")

    def wrap_fragments(ts: Any) -> Any:
        ref.atoms.wrap(compound="fragments", center="cog")
        return ts

    ref.trajectory.add_transformations(
        trans.unwrap(ref.atoms), trans.center_in_box(protein), wrap_fragments
    )
    count = min(frames, len(u.trajectory))
    mda_times = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(count):
            t0 = time.perf_counter()
            ref.trajectory[i]
            mda_times.append((time.perf_counter() - t0) * 1e3)
        raw = [(ts.positions.copy(), ts.triclinic_dimensions.copy()) for ts in u.trajectory[:count]]
    transform = PeriodicTransform(device)
    transform.set_topology(topology)
    options = Options(mode="molecules", centre=np.asarray(protein.indices, dtype=np.int32))
    transform.apply(*raw[0], options)
    times = []
    for positions, box in raw:
        t0 = time.perf_counter()
        transform.apply(positions, box, options)
        times.append((time.perf_counter() - t0) * 1e3)
    out = {
        "atoms": topology.n_atoms,
        "mdanalysis_ms": median(mda_times),
        "round_trip_ms": median(times),
    }
    out["mdanalysis_per_device"] = out["mdanalysis_ms"] / out["round_trip_ms"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--sizes", default="100000,1000000", help="atom counts, comma-separated")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="one small size, few frames")
    ap.add_argument("--mdanalysis", action="store_true", help="also time MDAnalysis on adk")
    ap.add_argument("--live", action="store_true", help="also time live frames, GPU queue")
    ap.add_argument("--image", default="1920x1080", help="the live frames' image, WxH")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    device = render_device.resolve(args.device)
    sizes = [20_000] if args.quick else [int(s) for s in args.sizes.split(",")]
    frames = 3 if args.quick else args.frames
    result: dict[str, Any] = {
        "device": device,
        "device_name": str(wp.get_device(device).name),
        "gpu": str(wp.get_device(device).name) if device.startswith("cuda") else "cpu",
        "host": platform.node(),
        "host_cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "warp": wp.config.version,
        "frames": frames,
        "sizes": [bench_size(device, n, frames) for n in sizes],
    }
    if args.live:
        w, h = (int(v) for v in args.image.lower().split("x"))
        result["live"] = [bench_live(device, n, frames, (w, h)) for n in sizes]
    if args.mdanalysis:
        result["mdanalysis"] = bench_mdanalysis(device, frames)
        print(f"  adk vs MDAnalysis: {result['mdanalysis']}", flush=True)
    text = json.dumps(result, indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
