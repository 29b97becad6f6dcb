"""`scalesteer thesis` runs the reproduction from the checkout and names missing extras."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest

from server.commands import cli, thesis


def test_missing_extras_are_named_before_anything_runs(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    real = importlib.util.find_spec

    def without_skimage(name: str, *args: Any) -> Any:
        return None if name == "skimage" else real(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", without_skimage)
    assert cli.main(["thesis", "--quick"]) == 3
    err = capsys.readouterr().err
    assert "missing scikit-image" in err and "scalesteer[thesis]" in err


def test_the_reproduction_runs_from_the_checkout_wherever_the_command_is_given(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PYTHONPATH", raising=False)  # found by `-m` in the checkout, not here
    assert cli.main(["thesis", "--help"]) == 0
    assert "--quick" in capfd.readouterr().out


def test_outside_a_checkout_the_command_says_where_the_reproduction_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(thesis, "CHECKOUT", tmp_path)  # an installed package: no thesis/ beside
    assert cli.main(["thesis", "--help"]) == 3
    err = capfd.readouterr().err
    assert "ships with the source checkout" in err and "python -m thesis.reproduce" in err


def test_a_relative_output_folder_is_read_from_where_the_command_is_given(tmp_path: Path) -> None:
    assert thesis.from_here(["--quick", "--out", "report"], tmp_path) == [
        "--quick",
        "--out",
        str(tmp_path / "report"),
    ]
    assert thesis.from_here(["--out=/abs", "--seeds", "3"], tmp_path) == [
        "--seeds",
        "3",
        "--out",
        "/abs",
    ]
    assert thesis.from_here(["--dpi", "40"], tmp_path) == ["--dpi", "40"]
