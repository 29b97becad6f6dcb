"""CI runs the README's test command, and that command includes lint and type checks."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ci_runs_make_test() -> None:
    script = (ROOT / ".ci" / "run").read_text()
    commands = [line.strip() for line in script.splitlines() if line.strip()]
    assert "make test" in commands
    assert "make test" in (ROOT / "README.md").read_text()


def test_make_test_lints_and_type_checks_before_the_tests() -> None:
    dry = subprocess.run(
        ["make", "-n", "-W", "pyproject.toml", "test"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    lines = dry.splitlines()

    def first(needle: str) -> int:
        return next(i for i, line in enumerate(lines) if needle in line)

    assert first("ruff check") < first("-m pytest")
    assert first("ruff format --check") < first("-m pytest")
    assert first("mypy") < first("-m pytest")


def test_make_demo_takes_a_port_and_options() -> None:
    """`make demo` could not take a port, nor said how."""

    def dry(*variables: str) -> str:
        out = subprocess.run(
            ["make", "-n", "-W", "pyproject.toml", "demo", *variables],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        return next(line for line in out.splitlines() if "scalesteer demo" in line).split()[1:]

    assert dry() == ["demo"]
    assert dry("PORT=8001") == ["demo", "--port", "8001"]
    assert dry("ARGS=--port 0 --no-browser") == ["demo", "--port", "0", "--no-browser"]
    assert "make demo PORT=8001" in (ROOT / "Makefile").read_text()
