"""`scalesteer batch` from the command line (the in-process engine; Ray's path is
tests/server/pipeline/test_ray.py)."""

from __future__ import annotations

import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

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
