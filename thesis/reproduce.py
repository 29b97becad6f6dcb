"""Reproduce the thesis's chapters 3-4: PNG figures and a markdown report (``REPORT.md``).

``python -m thesis.reproduce [--out DIR] [--quick] [--seeds N] [--dpi N]``; the
project CLI calls :func:`main` as ``scalesteer thesis``. ``--quick`` runs the same pipeline with
three noise seeds and coarser quadrature (seconds); the committed report is the full run.
Needs matplotlib and scikit-image besides numpy.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from thesis.experiments import run_all
from thesis.figures import make_figures
from thesis.report import write_report

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Run every experiment, write the figures and the report; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m thesis.reproduce",
        description="Reproduce thesis chapters 3-4 (time-warped signal processing).",
    )
    parser.add_argument(
        "--out", type=Path, default=Path("docs/thesis"), help="output folder (docs/thesis)"
    )
    parser.add_argument("--quick", action="store_true", help="few seeds, coarse quadrature")
    parser.add_argument("--seeds", type=int, default=None, help="noise seeds (100, quick: 3)")
    parser.add_argument("--dpi", type=int, default=None, help="figure resolution")
    args = parser.parse_args(argv)
    seeds = args.seeds if args.seeds is not None else (3 if args.quick else 100)
    if seeds < 1:
        parser.error("--seeds must be positive")
    dpi = args.dpi if args.dpi is not None else (40 if args.quick else 100)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    results = run_all(seeds, args.quick)
    results.figures = make_figures(results, out, dpi)
    results.elapsed = time.perf_counter() - start
    report = write_report(results, out)
    print(f"wrote {report} and {len(results.figures)} figures in {results.elapsed:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
