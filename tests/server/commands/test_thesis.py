"""`scalesteer thesis` finds the reproduction in the checkout and names missing extras."""

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


def test_the_reproduction_is_found_in_the_checkout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (thesis.CHECKOUT / "thesis" / "reproduce.py").is_file()
    with pytest.raises(SystemExit) as done:
        cli.main(["thesis", "--help"])
    assert done.value.code == 0
    assert "--quick" in capsys.readouterr().out
