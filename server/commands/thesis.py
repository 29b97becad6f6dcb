"""`scalesteer thesis`: regenerate the reproduction of the thesis's chapters 3-4.

The reproduction is not part of the installed package: it lives in the source checkout's
`thesis/` folder beside `benchmarks/`. This command finds it there, checks the extras it needs
(matplotlib, scikit-image, scipy) and says which are missing before anything runs.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

EXTRAS = {"matplotlib": "matplotlib", "skimage": "scikit-image", "scipy": "scipy"}
CHECKOUT = Path(__file__).resolve().parents[2]


def missing_extras() -> list[str]:
    """Distribution names of the reproduction's dependencies that are not installed."""
    return [dist for module, dist in EXTRAS.items() if importlib.util.find_spec(module) is None]


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if (CHECKOUT / "thesis" / "reproduce.py").is_file() and str(CHECKOUT) not in sys.path:
        sys.path.insert(0, str(CHECKOUT))
    if importlib.util.find_spec("thesis") is None:
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
    reproduce = importlib.import_module("thesis.reproduce")
    result: int = reproduce.main(args)
    return result
