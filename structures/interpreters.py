"""Child interpreters that import this checkout's packages (the readers' and the selections'
worker processes): fresh interpreters, never forks of the server, whose GPU context and threads
must not be copied."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = str(Path(__file__).resolve().parents[1])
"""The folder that holds the packages."""


def child_environment(**extra: str) -> dict[str, str]:
    """This process's environment for a child interpreter, with this checkout first on
    PYTHONPATH (whatever the server's working directory) and `extra` set."""
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": ROOT + (os.pathsep + path if path else ""), **extra}
