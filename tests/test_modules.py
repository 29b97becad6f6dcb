"""Module size: a module past `MAX_LINES` says at its top why it stays whole.

A long module is split where a split is natural; where it is not, its docstring (a Python
module) or its opening comment (a dashboard module) carries a paragraph starting with `MARKER`
that says why. `server/render/` is left out: its kernels share code generated per family.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 450
MARKER = "Kept whole:"
PYTHON = ("server", "simulation_adapters", "structures", "protocol", "scalesteer", "benchmarks")
EXEMPT = ("server/render/",)
JAVASCRIPT = ("client_web/src",)


def python_reason(source: str) -> bool:
    doc = ast.get_docstring(ast.parse(source), clean=True) or ""
    return any(para.startswith(MARKER) for para in doc.split("\n\n"))


def javascript_reason(source: str) -> bool:
    """The comment lines before the first line of code."""
    head: list[str] = []
    for line in source.splitlines():
        if not line.startswith("//"):
            break
        head.append(line.removeprefix("//").strip())
    return any(line.startswith(MARKER) for line in head)


def long_modules() -> list[tuple[str, int, bool]]:
    """(path, lines, states a reason) of every module past the limit."""
    found = []
    for top in PYTHON:
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel.startswith(EXEMPT):
                continue
            source = path.read_text()
            n = source.count("\n")
            if n > MAX_LINES:
                found.append((rel, n, python_reason(source)))
    for top in JAVASCRIPT:
        for path in sorted((ROOT / top).glob("*.js")):
            source = path.read_text()
            n = source.count("\n")
            if n > MAX_LINES:
                found.append((path.relative_to(ROOT).as_posix(), n, javascript_reason(source)))
    return found


def test_every_long_module_states_why_it_stays_whole() -> None:
    found = long_modules()
    assert found, "no module past the limit: the check reads nothing (paths moved?)"
    offenders = [f"{path} ({n} lines)" for path, n, reason in found if not reason]
    assert not offenders, (
        f"modules over {MAX_LINES} lines without a '{MARKER}' paragraph at their top "
        f"(split them, or say why not): {', '.join(offenders)}"
    )


def test_the_marker_is_read_only_as_a_paragraph_of_its_own() -> None:
    assert python_reason('"""Title.\n\nKept whole: one schema."""\n')
    assert not python_reason('"""Title. Kept whole: mid-sentence."""\n')
    assert not python_reason('x = 1\n"""Kept whole: not the docstring."""\n')
    assert javascript_reason("// Title.\n//\n// Kept whole: one canvas.\n\nimport x;\n")
    assert not javascript_reason("import x;\n// Kept whole: below the code.\n")
