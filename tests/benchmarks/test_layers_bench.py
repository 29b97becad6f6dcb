"""The layers benchmark runs end to end on the CPU (a small system) and reports its ratios."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.layers_bench import main


def test_layers_bench_quick(tmp_path: Path) -> None:
    out = tmp_path / "layers.json"
    assert main(["--quick", "--device", "cpu", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["results"]) == {
        "protein_only",
        "protein_layer",
        "protein_ligand",
        "protein_licorice",
    }
    assert doc["results"]["protein_layer"]["atoms_drawn"] == doc["protein_atoms"]
    assert all(r["median_ms"] > 0 for r in doc["results"].values())
    assert set(doc["ratios"]) >= {"protein_layer_over_protein_only", "two_layers_over_one"}
