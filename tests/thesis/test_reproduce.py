"""The reproduction runs end to end (quick mode) and its report carries the computed numbers."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")
pytest.importorskip("skimage")

from thesis.experiments import (
    SIGMAS,
    THESIS_4_1,
    crossover,
    ml_data,
    run_reconstruction,
)
from thesis.reproduce import main

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("thesis")
    assert main(["--quick", "--out", str(out)]) == 0
    return out


def test_quick_run_writes_every_figure_and_the_report(quick_run: Path) -> None:
    report = (quick_run / "REPORT.md").read_text(encoding="utf-8")
    figures = re.findall(r"\]\(([\w.]+\.png)\)", report)
    assert len(figures) >= 12
    for name in figures:
        assert (quick_run / name).read_bytes()[:8] == PNG, name
    for heading in ("table 4.1", "table 4.2", "Table 4.3", "Table 4.4", "Table 4.5", "figs. 3.3"):
        assert heading in report
    assert "holds here" in report


def test_report_quotes_the_thesis_and_our_numbers(quick_run: Path) -> None:
    report = (quick_run / "REPORT.md").read_text(encoding="utf-8")
    ts, fs, tl, truth = ml_data("samples")
    rec = run_reconstruction(ts, fs, tl, truth, SIGMAS)
    row = next(line for line in report.splitlines() if line.startswith("| 0.200000 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert float(cells[1]) == THESIS_4_1["classical"][2]
    assert float(cells[3]) == pytest.approx(rec.classical[2], abs=5e-4)
    assert float(cells[4]) == pytest.approx(rec.warped[2], abs=5e-4)


def test_crossover_of_the_thesis_table() -> None:
    grid, interp = crossover(
        SIGMAS, np.asarray(THESIS_4_1["classical"]), np.asarray(THESIS_4_1["warped"])
    )
    assert grid == pytest.approx(4 / 15)
    assert interp is not None and 0.2 < interp < 4 / 15
    c = np.array([1.0, 2.0, 3.0])
    assert crossover(np.arange(3.0), c, c + 1) == (None, None)
