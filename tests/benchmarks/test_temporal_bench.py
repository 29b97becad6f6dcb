"""The temporal benchmark's smoke test: a quick run on the CPU device writes its figures."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.temporal_bench import main


def test_quick_run_writes_every_window_with_its_baseline(tmp_path: Path) -> None:
    out = tmp_path / "temporal.json"
    assert main(["--quick", "--device", "cpu", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    (size,) = result["sizes"]
    assert size["baseline_frame_ms"] > 0
    assert [w["window"] for w in size["windows"]] == [4, 16]
    for w in size["windows"]:
        assert w["smooth_ms_warped"] > 0 and w["frame_ms"] > 0
        assert w["ring_bytes_per_atom"] == w["window"] * 12 + 4
