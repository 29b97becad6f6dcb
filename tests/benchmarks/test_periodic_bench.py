"""The periodic benchmark's smoke test: a quick run on the CPU device writes its figures."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.periodic_bench import MODES, main


def test_quick_run_writes_every_mode_beside_its_upload(tmp_path: Path) -> None:
    out = tmp_path / "periodic.json"
    assert main(["--quick", "--device", "cpu", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    (size,) = result["sizes"]
    assert size["upload_ms"] > 0 and size["molecules"] > 1 and size["pointer_rounds"] >= 1
    assert [m["mode"] for m in size["modes"]] == list(MODES)
    for mode in size["modes"]:
        assert mode["device_ms"] > 0 and mode["round_trip_ms"] > 0
        assert mode["device_per_upload"] == mode["device_ms"] / size["upload_ms"]
