"""`scalesteer thesis`: regenerate the reproduction of the thesis's chapters 3-4.

The reproduction is not part of the installed package: it lives in the source checkout's
`thesis/` folder beside `benchmarks/`. This command checks the extras it needs (matplotlib,
scikit-image, scipy) and says which are missing before anything runs, then runs it as
`python -m thesis.reproduce` from the checkout, where `thesis` is importable without touching
this process's import path. Its report goes to the checkout's `docs/thesis/` unless `--out`
says otherwise (a relative `--out` is taken from where the command was given).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
from pathlib import Path

EXTRAS = {"matplotlib": "matplotlib", "skimage": "scikit-image", "scipy": "scipy"}
CHECKOUT = Path(__file__).resolve().parents[2]


def missing_extras() -> list[str]:
    """Distribution names of the reproduction's dependencies that are not installed."""
    return [dist for module, dist in EXTRAS.items() if importlib.util.find_spec(module) is None]


def from_here(args: list[str], here: Path) -> list[str]:
    """`args` with a relative `--out` made absolute from `here` (the reproduction runs in the
    checkout, so it would read a relative folder from there)."""
    parser = argparse.ArgumentParser(prog="scalesteer thesis", add_help=False)
    parser.add_argument("--out", type=Path)
    known, rest = parser.parse_known_args(args)
    if known.out is None:
        return args
    return [*rest, "--out", str(here / known.out)]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not (CHECKOUT / "thesis" / "reproduce.py").is_file():
        print(
            "scalesteer thesis: the thesis reproduction ships with the source checkout, not the "
            "installed package; run it from a clone: python -m thesis.reproduce",
            file=sys.stderr,
        )
        return 3
    if "-h" not in args and "--help" not in args and (missing := missing_extras()):
        print(
            f"scalesteer thesis: missing {', '.join(missing)}; "
            "install them with: pip install 'scalesteer[thesis]'",
            file=sys.stderr,
        )
        return 3
    command = [sys.executable, "-m", "thesis.reproduce", *from_here(args, Path.cwd())]
    return subprocess.run(command, cwd=CHECKOUT, check=False).returncode
