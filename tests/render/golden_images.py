"""Golden-image helpers: the molecule they show (gramicidin A, PDB 1GRM, 272 atoms; the
coordinates travel with the tests, read once from MDAnalysisTests' 1grm_single.pdb), the
comparison with tolerance and the `--regen-golden` rewrite."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from protocol import Topology, WireArray
from tests.render.conftest import GOLDEN_DIR, bonds_by_distance, make_topology

W, H = 160, 120


def gramicidin() -> tuple[Topology, np.ndarray]:
    """Gramicidin A with its atom names, residue numbers, chains and B-factors."""
    d = np.load(Path(__file__).parent / "data" / "gramicidin_1grm.npz")
    elements = [str(e) for e in d["elements"]]
    pos = d["positions"].astype(np.float32)
    top = make_topology(
        len(pos),
        elements=elements,
        chains=[str(c) for c in d["chains"]],
        residues=[str(r) for r in d["residues"]],
        bfactors=d["bfactors"].astype(np.float32),
        bonds=bonds_by_distance(pos, elements),
    )
    names = [str(x) for x in d["names"]]
    resids = WireArray.from_numpy(d["resids"], "<i4")
    return top.model_copy(update={"names": names, "residue_ids": resids}), pos


def assert_image_approx_equal(got: np.ndarray, want: np.ndarray, name: str) -> None:
    """Small differences (float order on another device) pass; a changed picture does not."""
    assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
    diff = np.abs(got.astype(np.int32) - want.astype(np.int32)).max(axis=-1)
    mean = float(diff.mean())
    far = float((diff > 24).mean())
    assert mean <= 1.0 and far <= 0.01, f"{name}: mean diff {mean:.2f}, {far:.2%} pixels off"


def check_golden(got: np.ndarray, name: str, device: str, regen: bool) -> None:
    """Compare an RGB image with golden/<name>.png (rewritten first with --regen-golden, from
    the CPU device only)."""
    path = GOLDEN_DIR / f"{name}.png"
    if regen and device == "cpu":
        GOLDEN_DIR.mkdir(exist_ok=True)
        Image.fromarray(got).save(path)
    want = np.asarray(Image.open(path).convert("RGB"))
    assert_image_approx_equal(got, want, name)
