"""The render benchmark's command line works as documented (a smoke run on the CPU device)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
QUICK = ["--quick", "--device", "cpu"]
# a section skips what its budget leaves no time for
VARIANTS = [*QUICK, "--sections", "variants", "--variant-cases", "2000@48x32", "--budget-s", "3600"]


def bench(*args: str) -> subprocess.CompletedProcess[str]:
    """The benchmark run with `args` from the project root."""
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "render_bench.py"), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )


def results(out: Path, *args: str) -> dict[str, Any]:
    """The results a successful run with `args` writes to `out`."""
    run = bench(*args, "--out", str(out))
    assert run.returncode == 0, run.stderr[-2000:]
    loaded: dict[str, Any] = json.loads(out.read_text())
    return loaded


def test_quick_run_writes_results_and_sample_images_into_a_new_folder(tmp_path: Path) -> None:
    images = tmp_path / "not" / "yet" / "there"
    args = [*QUICK, "--sections", "main", "--sizes", "496", "--image-n", "496"]
    frames = results(tmp_path / "quick.json", *args, "--images", str(images))["frames"]
    assert sorted(f.name for f in images.iterdir()) == [
        "render_iso_496.jpg",
        "render_volume_496.jpg",
    ]
    assert {(f["n_atoms"], f["mode"]) for f in frames} == {(496, "iso"), (496, "volume")}


def test_variants_of_a_turning_camera_record_their_options(tmp_path: Path) -> None:
    """`--variant-turn` times still positions under a turning camera, `--visible-rays` sets
    the marking rays of view-following part bounds; both are recorded with the results."""
    variants = (
        '[{"label": "whole", "part_bounds": "none"}, {"label": "view", "part_bounds": "visible"}]'
    )
    args = [*VARIANTS, "--variants", variants, "--variant-turn", "5", "--visible-rays", "3:2"]
    got = results(tmp_path / "turn.json", *args)
    assert got["visible_rays"] == {"stride": 3, "depth": 2}
    rows = got["variants"]
    assert [(v["label"], v["turn_deg"]) for v in rows] == [("whole", 5.0), ("view", 5.0)]
    # still positions: nothing is uploaded after the first (warm-up) frame
    assert all(v["stages_ms"]["upload"] == 0.0 for v in rows)


def test_variants_seen_by_several_cameras_record_their_count(tmp_path: Path) -> None:
    """`--variant-views` has every frame of new positions seen by that many cameras."""
    args = [*VARIANTS, "--variants", '[{"label": "three"}]', "--variant-views", "3"]
    rows = results(tmp_path / "views.json", *args)["variants"]
    assert [(v["label"], v["views"], v["turn_deg"]) for v in rows] == [("three", 3, 0.0)]
    assert rows[0]["stages_ms"]["upload"] > 0.0


def test_the_scale_section_renders_with_the_given_parameters(tmp_path: Path) -> None:
    """`--variant-params` sets the render parameters of the scale section too (volume
    frames of large systems), recorded with each row."""
    args = [*QUICK, "--sections", "scale", "--scale-sizes", "2000", "--scale-cells", "2"]
    args += ["--variant-params", '{"mode": "volume"}', "--budget-s", "3600"]
    rows = results(tmp_path / "scale.json", *args)["scale"]
    assert [(e["params"], e["pipelined"]) for e in rows] == [
        ({"mode": "volume"}, False),
        ({"mode": "volume"}, True),
    ]


def test_camera_counts_below_one_are_refused() -> None:
    run = bench("--variant-views", "0")
    assert run.returncode == 2
    assert "--variant-views must be >= 1, got 0" in run.stderr


def test_marking_rays_that_are_not_two_positive_integers_are_refused() -> None:
    for bad in ("2", "2:0", "two:4"):
        run = bench("--visible-rays", bad)
        assert run.returncode == 2, bad
        assert f"--visible-rays takes STRIDE:DEPTH, two integers >= 1, got '{bad}'" in run.stderr


def test_the_passes_section_counts_the_work_of_iso_and_volume_frames(tmp_path: Path) -> None:
    """`--sections passes` records the density passes per ray of an iso and a volume frame
    of each case, and their ratio."""
    args = [*QUICK, "--sections", "passes", "--variant-cases", "2000@48x32,3000@40x30"]
    rows = results(tmp_path / "passes.json", *args)["passes"]
    assert [(e["n_atoms"], e["width"], e["height"]) for e in rows] == [
        (2000, 48, 32),
        (3000, 40, 30),
    ]
    for e in rows:
        assert 0 < e["iso"]["per_ray"] <= e["iso"]["per_ray_reaching"] <= e["iso"]["max"]
        assert 0 < e["volume"]["rays_reaching"] <= 1
        assert e["volume_over_iso"] == e["volume"]["per_ray"] / e["iso"]["per_ray"]
        assert 0 < e["iso"]["tile_use"] <= 1 and 0 < e["volume"]["tile_use"] <= 1


def test_tile_use_is_the_share_of_a_warps_pass_slots_that_work(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Passes taken over the tile's most times its rays, over tiles with work; tiles that
    the image cuts at its edges and tiles without passes are left out."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from render_bench import tile_use

    counts = np.zeros((9, 17), dtype=np.int32)  # two full 8x4 tiles a row, two rows
    counts[0, 0] = 4  # tile one: one ray of 32 takes 4 passes, the rest none
    counts[4:8, 8:16] = 2  # tile four: every ray takes 2
    counts[8, :] = 9  # the cut row and column are left out
    counts[:, 16] = 9
    assert tile_use(counts) == (4 + 64) / ((4 + 2) * 32)
    assert tile_use(np.zeros((4, 8), dtype=np.int32)) == 1.0


def test_cases_that_are_not_atoms_at_a_size_are_refused() -> None:
    for bad in ("1000", "1000@64", "1000@64x", "x@64x48", "0@64x48"):
        run = bench("--variant-cases", bad)
        assert run.returncode == 2, bad
        assert (
            f"--variant-cases takes N@WxH,... (atoms @ width x height, each >= 1), got '{bad}'"
            in run.stderr
        )


def test_the_densities_section_times_each_density_and_counts_its_bytes(tmp_path: Path) -> None:
    args = [*QUICK, "--sections", "densities", "--density-cases", "496@32x24"]
    (row,) = results(tmp_path / "densities.json", *args)["densities"]
    assert row["n_atoms"] == 496 and (row["width"], row["height"]) == (32, 24)
    for space in ("classical", "geodesic", "carved"):
        assert row[space]["median_ms"] > 0
    # the geodesic density's route tables come on top of the classical density's buffers
    assert row["geodesic_bytes_per_atom"] > row["classical_bytes_per_atom"]


def test_the_multi_session_benchmark_compares_sessions_with_one(tmp_path: Path) -> None:
    out = tmp_path / "sessions.json"
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "multi_session_bench.py"),
            *("--devices", "cpu,cpu", "--atoms", "300", "--size", "32x24", "--seconds", "0.3"),
            *("--out", str(out)),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(out.read_text())
    assert got["one_session_one_device"]["frames"] > 0
    assert len(got["sessions_one_device_each"]) == 2 and len(got["each_over_one"]) == 2
    assert got["spread_over_one"] > 0


def test_the_farfield_section_sets_a_far_grids_build_against_what_it_could_save(
    tmp_path: Path,
) -> None:
    """`--sections farfield` times today's frame and the frame at a 2.5-sigma cutoff (the most
    a far-field split could save) and a far grid's build at each spacing, over the frame's
    box widened by the reach."""
    args = [*QUICK, "--sections", "farfield", "--variant-cases", "496@48x32"]
    (e,) = results(tmp_path / "farfield.json", *args)["farfield"]
    near = e["near part only (cutoff 2.5 sigma)"]["median_ms"]
    assert e["saving_at_most_ms"] == e["today"]["median_ms"] - near
    builds = e["far_grid_builds"]
    assert [b["spacing_sigmas"] for b in builds] == [0.5, 0.75]
    assert builds[0]["nodes"] > 3 * builds[1]["nodes"]  # (1.5)^3 as many, less the rounding
    for b in builds:
        assert b["median_ms"] > 0 and b["spacing_A"] == b["spacing_sigmas"] * 1.5
