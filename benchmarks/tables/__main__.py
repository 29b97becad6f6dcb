"""`python -m benchmarks.tables [--check]`: rewrite (or check) the README's tables."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import README, RESULTS, TableError, differing, fill, generate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--check", action="store_true", help="only say whether the README differs")
    ap.add_argument("--readme", type=Path, default=README)
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    try:
        made = generate(args.results)
        text = args.readme.read_text()
        filled = fill(text, made)
    except TableError as e:
        print(f"bench-tables: {e}", file=sys.stderr)
        return 2
    if args.check:
        stale = differing(text, made)
        if stale:
            print(
                f"bench-tables: {args.readme} differs from its results in: {', '.join(stale)} "
                "(run make bench-tables)",
                file=sys.stderr,
            )
            return 1
        return 0
    if filled != text:
        args.readme.write_text(filled)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
