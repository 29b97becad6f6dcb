"""`scalesteer render` end to end on real structure files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("MDAnalysis")
datafiles = pytest.importorskip("MDAnalysisTests.datafiles")
GRO, PDB_HOLE, XYZ = datafiles.GRO, datafiles.PDB_HOLE, datafiles.XYZ

from server.commands.render import main  # noqa: E402
from server.render.device import cuda_count  # noqa: E402

ABSENT_GPU = f"cuda:{cuda_count()}"
"""One past the last CUDA device of this machine: absent wherever the test runs."""


@pytest.mark.parametrize(("src", "mode"), [(PDB_HOLE, "iso"), (GRO, "volume"), (XYZ, "iso")])
def test_renders_structure_files(
    tmp_path: Path, src: str, mode: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "sub" / "still.png"
    rc = main([src, "-o", str(out), "--size", "40x30", "--mode", mode, "--device", "cpu"])
    assert rc == 0, capsys.readouterr().err
    img = np.asarray(Image.open(out))
    assert img.shape == (30, 40, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # a molecule, not a flat image
    assert "40x30" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["missing.pdb", "-o", "x.png"], "no such file"),
        ([PDB_HOLE, "-o", "x.png", "--frame", "3"], "frame 3 out of range"),
        ([PDB_HOLE, "-o", "x.gif"], ".png or .jpg"),
        ([PDB_HOLE, "-o", "x.png", "--sigma", "0"], "sigma_A"),
        ([PDB_HOLE, "-o", "x.png", "--warp-strength", "2"], "warp_strength"),
        ([PDB_HOLE, "-o", "x.png", "--device", ABSENT_GPU], "device"),
        ([PDB_HOLE, "-o", "x.png", "--fit-translation"], "--fit-translation needs --fit"),
        ([PDB_HOLE, "-o", "x.png", "--fit", "resname ("], "--fit: selection 'resname ('"),
        (
            [PDB_HOLE, "-o", "x.png", "--fit", "resid 1 and name CA"],
            "--fit: 'resid 1 and name CA' matches 2 atoms; a rotation fit needs at least 3 "
            "(--fit-translation takes one)",
        ),
    ],
)
def test_clear_errors(
    tmp_path: Path,
    argv: list[str],
    match: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "scalesteer render: error:" in err and match in err


def test_unreadable_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "broken.pdb"
    bad.write_bytes(b"\x00\x01 not a pdb \xff" * 10)
    assert main([str(bad), "-o", str(tmp_path / "o.png")]) == 2
    assert "broken.pdb" in capsys.readouterr().err


def test_bad_size_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([PDB_HOLE, "-o", "x.png", "--size", "800by600"])
    assert exc.value.code == 2
    assert "800x600" in capsys.readouterr().err
    # past the renderer's limits: named before the file is read (it had been a traceback)
    for size in ("100000x100000", "20000x10", "5000x4000"):
        assert main(["no-such-file.pdb", "-o", "x.png", "--size", size]) == 2
        assert f"--size {size}: at most 16384 px a side" in capsys.readouterr().err
    assert main(["no-such-file.pdb", "-o", "x.png", "--device", "gpu7"]) == 2
    assert "--device gpu7: unknown device" in capsys.readouterr().err


def test_the_geodesic_and_carved_densities_render_and_differ(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = {}
    for space in ("classical", "geodesic", "carved"):
        out = tmp_path / f"{space}.png"
        argv = [PDB_HOLE, "-o", str(out), "--size", "48x36", "--device", "cpu"]
        assert main([*argv, "--scale-space", space, "--weights", "electrons"]) == 0
        images[space] = np.asarray(Image.open(out), dtype=np.float64)
    for space in ("geodesic", "carved"):
        assert np.abs(images["classical"] - images[space]).mean() > 2.0
        assert len(np.unique(images[space].reshape(-1, 3), axis=0)) > 10
    assert np.abs(images["geodesic"] - images["carved"]).mean() > 2.0


def test_a_solvated_file_opens_on_its_protein_and_layers_steer_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = [GRO, "--size", "64x48", "--device", "cpu"]
    assert main([*base, "-o", str(tmp_path / "default.png")]) == 0
    assert "3341 of 47681 atoms" in capsys.readouterr().out  # water and ions hidden
    assert main([*base, "-o", str(tmp_path / "all.png"), "--all-atoms"]) == 0
    assert "47681 atoms" in capsys.readouterr().out
    layers = json.dumps(
        [{"selection": "protein", "opacity": 0.4}, {"selection": "resname ARG", "mode": "licorice"}]
    )
    assert main([*base, "-o", str(tmp_path / "layers.png"), "--layers", layers]) == 0
    capsys.readouterr()
    images = [np.asarray(Image.open(tmp_path / f"{n}.png")) for n in ("default", "all", "layers")]
    assert not np.array_equal(images[0], images[1]) and not np.array_equal(images[0], images[2])
    assert main([*base, "-o", str(tmp_path / "x.png"), "--select", "name CA and ("]) == 2
    err = capsys.readouterr().err
    assert "layers.0.selection" in err and "character 14" in err
    assert err.split("error: ", 1)[1].startswith("--select: ")
    assert main([*base, "-o", str(tmp_path / "x.png"), "--select", "resname NONE"]) == 2
    assert "takes no atoms" in capsys.readouterr().err
    assert main([*base, "-o", str(tmp_path / "x.png"), "--select", "all", "--all-atoms"]) == 2
    capsys.readouterr()
    typo = json.dumps([{"selection": "all", "sigma": 2}])
    assert main([*base, "-o", str(tmp_path / "x.png"), "--layers", typo]) == 2
    assert "layers.0.sigma: unknown field" in capsys.readouterr().err
