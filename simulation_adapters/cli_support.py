"""What the adapters' command lines share: argument parsing that returns an exit code instead
of exiting, and quiet-by-default logging."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence


def parse(ap: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace | int:
    """Parsed arguments, or the exit code argparse chose (--help: 0, bad usage: 2)."""
    try:
        return ap.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def configure_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")
    if not verbose:  # MDAnalysis notes optional packages it lacks at import
        logging.getLogger("MDAnalysis").setLevel(logging.ERROR)


def retry_seconds(text: str) -> float | None:
    """`--retry` values: seconds of failed reconnection before giving up, or `forever`."""
    if text.strip().lower() == "forever":
        return None
    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or 'forever', got {text!r}") from None
    if not seconds > 0:
        raise argparse.ArgumentTypeError("--retry must be positive seconds or 'forever'")
    return seconds


def add_retry(ap: argparse.ArgumentParser) -> None:
    ap.add_argument(
        "--retry",
        type=retry_seconds,
        default=60.0,
        metavar="SECONDS|forever",
        help="keep reconnecting to the server this long before giving up (default 60; each "
        "retry is logged)",
    )
