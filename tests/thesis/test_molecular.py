"""Thesis section 5.3 as printed (eqs. 5.2-5.6) and the figures that compare it with the
warped density: the thesis's distance creases the density and marks the ring's centre."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thesis.molecular import (
    BondGraph,
    classical_density,
    crease_ratio,
    ring,
    thesis_density,
    thesis_distances,
    three_atoms,
)


def test_distances_follow_the_bonds() -> None:
    g = three_atoms()
    # on an atom the distance to itself is 0; to the far atom it runs along both bonds
    d = thesis_distances(g, g.positions)
    length = float(np.linalg.norm(g.positions[0] - g.positions[1]))
    np.testing.assert_allclose(np.diag(d), 0.0, atol=1e-12)
    assert d[0, 2] == pytest.approx(2 * length)
    # the middle of a bond: half a bond to either end (eq. 5.2)
    mid = (g.positions[:1] + g.positions[1:2]) / 2
    assert thesis_distances(g, mid)[0, :2] == pytest.approx([length / 2, length / 2])


def test_the_density_difference_weights_make_dense_atoms_far() -> None:
    g = three_atoms(2.5)
    flat = BondGraph(g.positions, np.ones(3), g.bonds)
    assert g.geodesics()[0, 1] > flat.geodesics()[0, 1]
    # the differences alone (gain -> inf): atoms of equal density are at distance zero
    only = BondGraph(flat.positions, flat.densities, flat.bonds, np.inf)
    assert only.geodesics()[0, 2] == 0.0


def test_eq_5_4_is_creased_where_the_classical_density_is_smooth() -> None:
    g = ring()
    line = ([0.0, 0.05, 0.0], [1.0, 0.1, 0.0])
    assert crease_ratio(lambda p: classical_density(g, p, 1.0), *line, 3.0, 0.01) > 3.9
    assert crease_ratio(lambda p: thesis_density(g, p, 1.0), *line, 3.0, 0.01) < 3.0


def test_the_figures_are_written(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    from thesis.chapter5 import make_figures

    paths = make_figures(tmp_path, dpi=40, renders=False)
    assert [p.name for p in paths] == [
        "fig5_6_three_atoms.png",
        "fig5_7_center_density.png",
        "fig5_8_ring.png",
        "fig5_crease_ratio.png",
    ]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in paths)
