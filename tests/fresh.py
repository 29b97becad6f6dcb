"""Python code run in a new interpreter from the checkout: what a user's own process sees on
import (which packages load, which threads race), where the test process has long loaded
them all."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def python_c(
    code: str, *, timeout: float, bare: bool = False, flags: Sequence[str] = ()
) -> subprocess.CompletedProcess[str]:
    """`python [flags] -c code` in the checkout, its output captured. `bare`: an environment
    of the checkout and the system's PATH alone, none of this process's variables; otherwise
    this process's, with the checkout first on its PYTHONPATH (where the GPU machine keeps
    warp)."""
    if bare:
        env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    else:
        path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
        env = {**os.environ, "PYTHONPATH": path}
    return subprocess.run(
        [sys.executable, *flags, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
