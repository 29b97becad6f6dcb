"""The reach the renderer takes (server/render/reach.py): the least cutoff that keeps the
surface within max(0.05 A, 1 % of sigma) of the untruncated density's, never more than the
render parameters' cutoff_sigmas; held on adenylate kinase here (villin's whole sigma range is
held in test_carved.py's `test_the_default_cutoff_keeps_the_surface_in_place`)."""

from __future__ import annotations

import math
import warnings

import pytest

from protocol import RenderParams
from server.render.reach import REACH, reach_sigmas, surface_shift
from server.render.renderer import Renderer
from server.render.tuning import Tuning

pytest.importorskip("MDAnalysisTests")


def test_the_reach_follows_the_table_and_never_exceeds_the_cutoff() -> None:
    for sigma, k in REACH:
        assert reach_sigmas(sigma, 6.0) == pytest.approx(k)
        assert reach_sigmas(sigma, 3.0) == min(k, 3.0)
    # between the table's sigmas it is interpolated in log sigma; beyond, held flat
    a, b = REACH[3], REACH[4]
    mid = math.sqrt(a[0] * b[0])
    assert reach_sigmas(mid, 6.0) == pytest.approx(0.5 * (a[1] + b[1]))
    assert reach_sigmas(100.0, 6.0) == REACH[-1][1]
    assert reach_sigmas(0.01, 6.0) == REACH[0][1]


def test_the_renderer_reaches_what_the_surface_needs() -> None:
    r = Renderer("cpu")
    classical = r._derive(RenderParams(sigma_A=1.5))
    assert classical.reach == pytest.approx(1.5 * reach_sigmas(1.5, 4.0))
    assert classical.reach < 1.5 * 4.0  # the default sigma needs less than cutoff_sigmas
    fixed = Renderer("cpu", tuning=Tuning(fixed_cutoff=True))._derive(RenderParams(sigma_A=1.5))
    assert fixed.reach == pytest.approx(1.5 * 4.0)
    assert r._derive(RenderParams(sigma_A=1.5, cutoff_sigmas=2.0)).reach == pytest.approx(3.0)
    carved = r._derive(RenderParams(sigma_A=1.5, scale_space="carved"))
    assert carved.reach == pytest.approx(4.0 * carved.sigma)  # measured for the Gaussian only


@pytest.mark.parametrize("sigma", [0.5, 1.5])
def test_adenylate_kinases_surface_stays_in_place(sigma: float) -> None:
    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import DCD, PSF

    with warnings.catch_warnings():  # the DCD reader's notice of a coming change
        warnings.simplefilter("ignore", DeprecationWarning)
        positions = mda.Universe(PSF, DCD).atoms.positions
    k = reach_sigmas(sigma, 4.0)
    assert surface_shift(positions, sigma, k) <= max(0.05, 0.01 * sigma)
