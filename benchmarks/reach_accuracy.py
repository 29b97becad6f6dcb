"""How far each Gaussian must reach for the surface to stay in place: for every sigma, the least
cutoff k (in sigmas, tapered as the renderer tapers) at which the iso-surface of the default
relative level moves by at most max(0.05 A, 1 % of sigma) against the untruncated density, on
real proteins (float64, crossings along rays from each protein's centre).

    python benchmarks/reach_accuracy.py --out benchmarks/results/reach_accuracy.json

The renderer's accuracy reach (`server/render/reach.py`) is this table with a margin; the test
`tests/render/test_reach.py` holds the bound at the table's reach.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from server.render.reach import surface_shift

SIGMAS = (0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.5, 6.0, 9.0, 12.0)
CUTOFFS = (2.5, 2.75, 3.0, 3.25, 3.5, 3.75, 4.0, 4.5)


def proteins() -> dict[str, np.ndarray]:
    """villin (the demo's, with hydrogens) and adenylate kinase (MDAnalysisTests, 3341 atoms)."""
    out = {"villin": np.load(ROOT / "tests" / "render" / "data" / "villin.npz")["positions"]}
    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import DCD, PSF

    out["adk"] = mda.Universe(PSF, DCD).atoms.positions.copy()
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows: list[dict[str, Any]] = []
    mols = proteins()
    for sigma in SIGMAS:
        bound = max(0.05, 0.01 * sigma)
        row: dict[str, Any] = {"sigma": sigma, "bound_A": bound, "shift_A": {}, "least_k": {}}
        for name, pos in mols.items():
            shifts = {k: surface_shift(pos, sigma, k) for k in CUTOFFS}
            row["shift_A"][name] = {f"{k:g}": v for k, v in shifts.items()}
            ok = [k for k in CUTOFFS if shifts[k] <= bound]
            row["least_k"][name] = min(ok) if ok else None
        rows.append(row)
        print(sigma, row["least_k"], flush=True)
        args.out.write_text(json.dumps({"benchmark": "reach_accuracy", "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
