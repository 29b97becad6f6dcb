"""Shared fixtures: devices ("cpu" always, "cuda:0" when present), small molecules, and the
`--regen-golden` flag that rewrites tests/render/golden/*.png instead of comparing."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from protocol import Topology, WireArray
from server.render import device as render_device

GOLDEN_DIR = Path(__file__).parent / "golden"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--regen-golden",
        action="store_true",
        default=False,
        help="rewrite the render golden images instead of comparing with them",
    )


DEVICES = [pytest.param("cpu", id="cpu")]
if render_device.cuda_count() > 0:
    DEVICES.append(pytest.param("cuda:0", id="cuda", marks=pytest.mark.gpu))


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@pytest.fixture
def regen_golden(request: pytest.FixtureRequest) -> bool:
    return bool(request.config.getoption("--regen-golden", default=False))


def make_topology(
    n: int,
    elements: list[str] | None = None,
    chains: list[str] | None = None,
    residues: list[str] | None = None,
    bfactors: np.ndarray | None = None,
    charges: np.ndarray | None = None,
    radii: np.ndarray | None = None,
    bonds: np.ndarray | None = None,
) -> Topology:
    els = elements if elements is not None else ["CNOSH"[i % 5] for i in range(n)]
    return Topology(
        n_atoms=n,
        elements=els,
        names=[e + "X" for e in els],
        residue_ids=WireArray.from_numpy(np.arange(n) // 4, "<i4"),
        residue_names=residues
        if residues is not None
        else ["ALA", "GLU", "LYS", "SER"] * (n // 4) + ["GLY"] * (n % 4),
        chain_ids=chains if chains is not None else ["A" if i < n // 2 else "B" for i in range(n)],
        bonds=WireArray.from_numpy(np.zeros((0, 2)) if bonds is None else bonds, "<i4"),
        bfactors=None if bfactors is None else WireArray.from_numpy(bfactors, "<f4"),
        charges=None if charges is None else WireArray.from_numpy(charges, "<f4"),
        radii=None if radii is None else WireArray.from_numpy(radii, "<f4"),
    )


def blob(
    n: int, seed: int, spread: float = 4.0, offset: tuple[float, float, float] = (0, 0, 0)
) -> np.ndarray:
    """A protein-like cluster: a few lumps of atoms about 1.5 A apart."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(size=(max(n // 8, 1), 3)) * spread
    pts = centers[rng.integers(0, len(centers), n)] + rng.normal(size=(n, 3)) * 1.6
    return (pts + np.asarray(offset)).astype(np.float32)


@pytest.fixture
def molecule() -> Callable[..., tuple[Topology, np.ndarray]]:
    def make(n: int = 40, seed: int = 1, **kw: object) -> tuple[Topology, np.ndarray]:
        return make_topology(n), blob(n, seed, **kw)  # type: ignore[arg-type]

    return make


def bonds_by_distance(positions: np.ndarray, elements: list[str]) -> np.ndarray:
    """Bonds between atoms closer than 1.9 A (1.3 A when either is a hydrogen)."""
    pos = np.asarray(positions, dtype=np.float64)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    light = np.array([e.upper().startswith("H") for e in elements])
    limit = np.where(light[:, None] | light[None, :], 1.3, 1.9)
    i, j = np.nonzero(np.triu(d < limit, k=1))
    return np.stack([i, j], axis=1).astype(np.int32)
