"""The sort-last benchmark runs end to end on CPU devices: one device the control in the same
run, where the frame goes, the parts' shares, and the image against one device's."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.sort_last_bench import main


def test_sort_last_bench_on_two_cpu_devices(tmp_path: Path) -> None:
    out = tmp_path / "sort_last.json"
    args = ["--devices", "cpu,cpu", "--atoms", "3000", "--sizes", "96x64", "--modes", "iso"]
    assert main([*args, "--frames", "2", "--warm", "1", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["devices"] == ["cpu", "cpu"] and doc["graphs"] is True
    (run,) = doc["runs"]
    sl = run["sort_last"]
    assert run["one_device"]["frame_ms"] > 0 and sl["frame_ms"] > 0
    assert run["ratio_to_one_device"] == run["one_device"]["frame_ms"] / sl["frame_ms"]
    assert {"split_ms", "mean_ms", "queue_ms", "combine_ms", "part1_raycast_ms"} <= set(sl)
    # each part holds fewer than all the atoms, together at least all of them
    assert len(sl["atoms_held"]) == 2 and max(sl["atoms_held"]) < 3000 <= sum(sl["atoms_held"])
    assert run["image_vs_one_device"]["max_levels"] <= 1
