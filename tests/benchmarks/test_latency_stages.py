"""The latency benchmark's stage marks: changes paired from the marks in order, the server's
classes restored afterwards, and a quick run on the CPU device reporting every stage."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.latency_bench import main
from benchmarks.latency_stages import MARKS, STAGES, Marks, traced
from server.session.session import Session


def _feed(marks: Marks, events: list[tuple[str, float]]) -> None:
    marks.events.extend(events)


def test_a_change_is_paired_from_its_marks_in_order() -> None:
    marks = Marks()
    t = 0.0
    one = [(label, t + i * 0.001) for i, label in enumerate(MARKS)]
    # a rest render between two changes: its marks start without a steer and are ignored;
    # a change whose render never came is dropped when the next change starts
    rest = [("loop", 1.0), ("render", 1.001), ("thread_in", 1.002)]
    lost = [("steer_in", 2.0), ("steer_out", 2.001)]
    two = [(label, 3.0 + i * 0.002) for i, label in enumerate(MARKS)]
    _feed(marks, one + rest + lost + two)
    rows = marks.changes()
    assert len(rows) == 2
    assert set(rows[0]) == set(STAGES)
    assert rows[0]["steer"] == pytest.approx(1.0)
    assert rows[1]["deliver"] == pytest.approx(2.0)


def test_the_marks_leave_the_server_as_it_was() -> None:
    original = Session._set_render_params
    with traced():
        assert Session._set_render_params is not original
    assert Session._set_render_params is original


def test_a_quick_run_reports_each_stage_and_each_run(tmp_path: Path) -> None:
    out = tmp_path / "latency.json"
    args = ["--quick", "--device", "cpu", "--no-throughput", "--stages", "--repeats", "2"]
    assert main([*args, "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert len(doc["latency_runs"]) == 2
    assert doc["latency"]["changes"] == sum(r["changes"] for r in doc["latency_runs"])
    stages = doc["latency_stages"]
    assert stages["changes"] >= doc["latency"]["changes"]
    assert all(stages[s]["p50"] > 0 for s in STAGES)
    # the device thread's time holds the render the image reports
    assert stages["thread"]["p50"] >= 0.9 * doc["latency"]["render"]["p50"]
