"""What the code and docs cite of benchmarks/ is there: a section quoted from the benchmarks'
README or HISTORY.md is in that file, and a results file they name is where they say: in
`results/` (code, docs and tests cite only those), or for HISTORY.md in `results/` or
`results/archive/`."""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CITING = ("docs", "server", "protocol", "simulation_adapters", "structures", "benchmarks", "tests")
SUFFIXES = {".py", ".md", ".sh", ".js"}
RESULTS = ROOT / "benchmarks" / "results"
BENCHMARKS = (
    "render|latency|layers|multi_device|multi_session|pipeline|video|temporal|batch"
    "|cpu_interactive|ws_parse|ncu|reach_accuracy|periodic"
)
CITED = re.compile(
    r"(--out\s+)?(?<![\w/.])((?:benchmarks/)?results/(?:archive/)?)?"
    rf"((?:{BENCHMARKS})[\w{{}},*-]*(?:\.(?:json|csv|txt)|_\*))"
)
"""A results file's name or pattern ({a,b} and * as the docs write them), with the folder it is
said to be in; a name after --out is where a command writes, not a citation."""
MACHINE = re.compile(r"_(h100|h200|cpu)")
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


def expand(pattern: str) -> list[str]:
    """A cited pattern's {a,b} alternatives, each a glob."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern.removesuffix("_*") + "_*" if pattern.endswith("_*") else pattern]
    return [
        name
        for alt in m.group(1).split(",")
        for name in expand(pattern[: m.start()] + alt + pattern[m.end() :])
    ]


def test_every_results_file_named_is_where_the_citation_says() -> None:
    kept = sorted(p.name for p in RESULTS.iterdir() if p.is_file())
    archived = sorted(p.name for p in (RESULTS / "archive").iterdir())
    history = ROOT / "benchmarks" / "HISTORY.md"
    cited = 0
    for path in citing_files():
        for m in CITED.finditer(path.read_text(errors="replace")):
            folder, pattern = m.group(2) or "", m.group(3)
            if m.group(1) or not (folder or MACHINE.search(pattern)):
                continue  # an output path, or a scratch name such as render_quick.json
            if "archive/" in folder:
                where = archived
            elif path == history and not folder:
                where = kept + archived
            else:
                where = kept
            for name in expand(pattern):
                assert fnmatch.filter(where, name), (
                    f"{path.relative_to(ROOT)} names {folder}{pattern}: no {name} there"
                )
                cited += 1
    assert cited >= 200  # HISTORY.md alone names most of the results
