"""What the code and docs cite of benchmarks/ is there: a section quoted from the benchmarks'
README or HISTORY.md is in that file."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CITING = ("docs", "server", "protocol", "simulation_adapters", "structures", "benchmarks", "tests")
SUFFIXES = {".py", ".md", ".sh", ".js"}
SECTION = re.compile(r"benchmarks/(README|HISTORY)\.md`?,\s*\"([^\"]+)\"")


def flat(text: str) -> str:
    """Text with its line breaks, comment markers and runs of spaces as one space."""
    return re.sub(r"\s*\n\s*(#\s*)?", " ", text).lower()


def citing_files() -> Iterator[Path]:
    """The project's sources and docs that may cite benchmarks/ (not the results)."""
    yield ROOT / "README.md"
    for top in CITING:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix in SUFFIXES and "results" not in path.parts and path.is_file():
                yield path


def test_every_quoted_section_of_the_benchmarks_docs_exists() -> None:
    docs = {
        name: flat((ROOT / "benchmarks" / f"{name}.md").read_text())
        for name in ("README", "HISTORY")
    }
    cited = 0
    for path in citing_files():
        for m in SECTION.finditer(path.read_text(errors="replace")):
            section = flat(m.group(2))
            assert section in docs[m.group(1)], (
                f'{path.relative_to(ROOT)} cites benchmarks/{m.group(1)}.md, "{m.group(2)}"'
            )
            cited += 1
    assert cited >= 8  # the scan found the citations (heap.py, video.py, docs/...)
