"""benchmarks/README.md's numbers are what the committed results files give: each table is
remade from its files and compared, as a schema check would, and every table names the GPU
each of its files records."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from benchmarks.tables import README, RESULTS, TABLES, Table, TableError, differing, fill, generate
from benchmarks.tables.markdown import NO_GPU, NOT_RECORDED, gpu_of


def copy_results(tmp_path: Path, *names: str) -> Path:
    """The named results files, copied where a test may change them."""
    for name in names:
        shutil.copy(RESULTS / name, tmp_path / name)
    return tmp_path


def test_the_readmes_tables_are_what_the_results_files_give() -> None:
    text = README.read_text()
    made = generate()
    stale = differing(text, made)
    assert not stale, f"benchmarks/README.md differs in {stale}: run make bench-tables"
    assert fill(text, made) == text


def test_a_new_figure_in_a_results_file_is_caught(tmp_path: Path) -> None:
    spec = TABLES["pipeline"]
    (name,) = spec.files
    res = json.loads((RESULTS / name).read_text())
    res["rows"][0]["overlapped"]["fps"] += 10.0
    (tmp_path / name).write_text(json.dumps(res))
    made = generate() | generate(tmp_path, {"pipeline": spec})
    assert differing(README.read_text(), made) == ["pipeline"]


def test_a_figure_typed_into_the_readme_is_caught() -> None:
    text = README.read_text()
    made = generate()
    body = made["multi-session"]
    row = next(line for line in body.splitlines() if line.startswith("| 1M "))
    typed = row.replace("| 1M | 1920x1080 | ", "| 1M | 1920x1080 | 1", 1)
    assert typed != row
    assert differing(text.replace(row, typed), made) == ["multi-session"]


def test_a_results_file_without_a_field_its_table_reads_is_refused_by_name(
    tmp_path: Path,
) -> None:
    (name,) = TABLES["pipeline"].files
    res = json.loads((RESULTS / name).read_text())
    del res["rows"][0]["overlapped_over_serial"]
    (tmp_path / name).write_text(json.dumps(res))
    with pytest.raises(TableError, match=rf"'pipeline' from {name}.*overlapped_over_serial"):
        generate(tmp_path, {"pipeline": TABLES["pipeline"]})


def test_a_missing_results_file_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(TableError, match=r"pipeline_h200\.json: not in"):
        generate(tmp_path, {"pipeline": TABLES["pipeline"]})


def test_markers_and_tables_must_match() -> None:
    made = {"pipeline": "x\n"}
    with pytest.raises(TableError, match="missing: pipeline"):
        fill("no markers\n", made)
    with pytest.raises(TableError, match="unknown: nope"):
        fill(
            "<!-- bench-tables: pipeline -->\n<!-- /bench-tables -->\n"
            "<!-- bench-tables: nope -->\n<!-- /bench-tables -->\n",
            made,
        )


def test_every_table_names_each_file_it_read_and_its_gpu() -> None:
    made = generate()
    for table, spec in TABLES.items():
        first = made[table].splitlines()[0]
        for name in spec.files:
            gpu = gpu_of(json.loads((RESULTS / name).read_text()))
            assert f"`{name}` ({gpu}" in first, (table, name, first)


def test_the_gpu_is_what_the_file_records_or_said_to_be_unrecorded(tmp_path: Path) -> None:
    read = {n: json.loads((RESULTS / n).read_text()) for s in TABLES.values() for n in s.files}
    assert gpu_of(read["video_h200_round4.json"]) == "NVIDIA H200"  # as "device"
    assert gpu_of(read["multi_session_h200x2.json"]) == "2x NVIDIA H200"  # as "gpus"
    assert gpu_of(read["batch_cpu_2core.json"]) == NO_GPU  # warp's CPU device
    assert gpu_of(read["cpu_interactive_2core.json"]) == NO_GPU  # "no GPU" in "machine"
    assert gpu_of(read["ws_parse_h200_host.json"]) == NOT_RECORDED
    copy_results(tmp_path, "pipeline_h200.json")
    res = json.loads((tmp_path / "pipeline_h200.json").read_text())
    del res["gpu"]
    assert gpu_of(res) == NOT_RECORDED  # "device": "cuda:0" names no model
    (tmp_path / "pipeline_h200.json").write_text(json.dumps(res))
    made = generate(tmp_path, {"pipeline": Table(("pipeline_h200.json",), TABLES["pipeline"].make)})
    assert made["pipeline"].startswith(f"From `pipeline_h200.json` ({NOT_RECORDED}")


def test_each_table_reads_a_file_kept_in_results_not_the_archive() -> None:
    for spec in TABLES.values():
        for name in spec.files:
            assert (RESULTS / name).is_file(), name
