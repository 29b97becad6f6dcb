"""`scalesteer batch` from the command line (the in-process engine; Ray's path is
tests/server/pipeline/test_ray.py)."""

from __future__ import annotations

import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import protocol as p
from server.commands.batch import main as batch_main


def main(argv: list[str]) -> int:
    """The command as a shell runs it: on a thread of its own, where no event loop runs."""
    with ThreadPoolExecutor(1) as pool:
        return pool.submit(batch_main, argv).result()


pytest.importorskip("MDAnalysisTests")
from MDAnalysisTests.datafiles import DCD, PSF  # noqa: E402


def test_batch_renders_a_trajectory_to_a_zip(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "adk.zip"
    code = main([PSF, DCD, "-o", str(out), "--size", "48x36", "--stop", "6", "--engine", "local",
                 "--device", "cpu"])  # fmt: skip
    assert code == 0
    assert sorted(zipfile.ZipFile(out).namelist()) == [f"frame_{i:06d}.png" for i in range(6)]
    assert "6 frames" in capsys.readouterr().out


def test_batch_names_what_is_wrong(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([PSF, DCD, "-o", str(tmp_path / "x.gif"), "--engine", "local"]) == 2
    assert "must end in .mp4 or .zip" in capsys.readouterr().err
    assert main([PSF, DCD, "-o", str(tmp_path / "x.zip"), "--params", '{"sigma": 2}',
                 "--engine", "local"]) == 2  # fmt: skip
    assert "params.sigma: unknown field" in capsys.readouterr().err
    zipped = str(tmp_path / "x.zip")
    # refused before anything is read (they had failed after the frames, as internal errors)
    for option, says in (
        (["--stride", "0"], "--stride: must be at least 1"),
        (["--fps", "-3"], "--fps: must be between 0.1 and 240"),
    ):
        with pytest.raises(SystemExit) as stopped:
            main([PSF, DCD, "-o", zipped, *option])
        assert stopped.value.code == 2 and says in capsys.readouterr().err
    # and what no frame could be drawn with, all before the input is read
    missing = str(tmp_path / "missing.psf")
    for option, says in (
        (["--start", "50", "--stop", "10"], "--stop 10 must be after --start 50"),
        (["--start", "-5"], "--start -5: frames count from 0"),
        (["--size", "100000x100000"], "--size 100000x100000: at most 16384 px a side"),
        (["--device", "gpu7"], "--device gpu7: unknown device"),
    ):
        assert main([missing, "-o", zipped, *option]) == 2, option
        assert says in capsys.readouterr().err, option
    for camera, says in (
        ("front", "--camera is not valid JSON"),
        ('{"distance": -1}', "--camera: distance:"),
        ('{"zoom": 2}', "--camera: camera.zoom: unknown field"),
    ):
        assert main([PSF, DCD, "-o", zipped, "--camera", camera, "--engine", "local"]) == 2
        assert says in capsys.readouterr().err, camera
    bad = tmp_path / "broken.pdb"
    bad.write_text("ATOM  garbage\n")
    assert main([str(bad), "-o", str(tmp_path / "x.zip"), "--engine", "local", "--device",
                 "cpu"]) == 1  # fmt: skip
    assert "broken.pdb" in capsys.readouterr().err


def test_batch_renders_here_unless_ray_is_asked_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`batch` started Ray by itself on a laptop and printed "0/10 frames" for 30 s while it
    started; without `--engine ray` or a cluster it renders in its own process."""
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.delenv("SCALESTEER_RAY_ADDRESS", raising=False)
    out = tmp_path / "adk.zip"
    code = main([PSF, DCD, "-o", str(out), "--size", "32x24", "--stop", "3", "--device", "cpu"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "rendering on this process (cpu)" in printed and "3 frames" in printed


def test_batch_opens_a_solvated_system_on_its_protein(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`batch` of a GRO/XTC rendered the water box: it follows the rule every entry point
    follows (docs/batch.md), and --select, --layers, --all-atoms and --params say so in --help."""
    import io

    from MDAnalysisTests.datafiles import GRO, XTC
    from PIL import Image

    from server.commands.batch import parser

    helped = parser().format_help()
    for option in ("--select", "--layers", "--all-atoms", "--params"):
        assert option in helped
    assert "solvent and ions hidden" in " ".join(helped.split())

    from tests.server.web.test_solvated import solvated

    camera = solvated()[2].model_dump_json()  # framing the protein

    out = tmp_path / "frames.zip"
    argv = [GRO, XTC, "-o", str(out), "--size", "64x48", "--stop", "1", "--engine", "local",
            "--device", "cpu", "--params", '{"sigma_A": 2}', "--camera", camera]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    rgb = np.asarray(Image.open(io.BytesIO(zipfile.ZipFile(out).read("frame_000000.png"))))
    background = np.asarray(p.RenderParams().background) * 255
    # water and ions hidden: the protein on the background (the water box fills the picture,
    # tests/server/web/test_solvated.py)
    assert (np.abs(rgb[..., :3] - background).max(axis=-1) < 16).mean() > 0.75
    for wrong in (["--select", "protein and ("], ["--layers", '[{"selection": "protein and ("}]']):
        argv = [GRO, XTC, "-o", str(tmp_path / "x.zip"), "--engine", "local", *wrong]
        assert main(argv) == 2
        assert "layers.0.selection" in capsys.readouterr().err
    argv = [GRO, XTC, "-o", str(tmp_path / "x.zip"), "--engine", "local", "--params",
            '{"layers": []}', "--select", "protein"]  # fmt: skip
    assert main(argv) == 2
    assert "--params names layers" in capsys.readouterr().err


def test_a_selection_from_an_option_is_named_by_that_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A --fit that matches nothing was reported as `params.fit_selection`, a name the command
    line never used."""
    from MDAnalysisTests.datafiles import GRO, XTC

    argv = [GRO, XTC, "-o", str(tmp_path / "x.zip"), "--size", "32x24", "--stop", "1",
            "--engine", "local", "--device", "cpu"]  # fmt: skip
    assert main([*argv, "--fit", "resname NOPE"]) == 1
    err = capsys.readouterr().err
    assert "--fit: 'resname NOPE' matches no atom" in err and "params." not in err, err
    assert main([*argv, "--center", "resname NOPE"]) == 1
    assert "--center: 'resname NOPE' matches no atom" in capsys.readouterr().err


def test_a_selection_an_option_gave_is_named_by_that_option_when_it_cannot_be_used(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A --fit or --center that does not parse, or reads coordinates, was refused as
    `fit_selection` or `center_selection`; a --fit on too few atoms for a rotation pointed to
    `fit 'translation'`, a render parameter, instead of --fit-translation."""
    from MDAnalysisTests.datafiles import DCD, PSF

    argv = [PSF, DCD, "-o", str(tmp_path / "x.zip"), "--size", "32x24", "--stop", "1",
            "--engine", "local", "--device", "cpu"]  # fmt: skip
    assert main([*argv, "--fit", "resname ("]) == 2
    err = capsys.readouterr().err
    assert "scalesteer batch: --fit: selection 'resname ('" in err and "_selection" not in err
    assert main([*argv, "--center", "around 3 resid 1"]) == 2
    err = capsys.readouterr().err
    assert "scalesteer batch: --center: 'around 3 resid 1' reads coordinates" in err, err
    # the same selection from --params is named as --params names it
    assert main([*argv, "--params", '{"fit": "rotation", "fit_selection": "resname ("}']) == 2
    assert "scalesteer batch: params.fit_selection: selection" in capsys.readouterr().err
    assert main([*argv, "--fit", "resid 1:2 and name CA"]) == 1
    err = capsys.readouterr().err
    assert "--fit: 'resid 1:2 and name CA' matches 2 atoms" in err, err
    assert "(--fit-translation takes one)" in err and "fit 'translation'" not in err, err
