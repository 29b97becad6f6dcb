"""Transfer-function tables and per-atom colours (numpy only)."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import TFPoint
from server.render import colors, transfer
from tests.render.conftest import make_topology


def test_table_interpolates_control_points() -> None:
    pts = [
        TFPoint(x=2.0, color=(1.0, 0.0, 0.0), alpha=1.0),
        TFPoint(x=0.0, color=(0.0, 0.0, 1.0), alpha=0.0),
        TFPoint(x=1.0, color=(0.0, 1.0, 0.0), alpha=0.5),
    ]
    t = transfer.build_table(pts)
    assert t.rgba.shape == (transfer.TABLE_SIZE, 4) and t.rgba.dtype == np.float32
    assert t.x_max == 2.0
    np.testing.assert_allclose(t.lookup(1.0), [0, 1, 0, 0.5], atol=1e-2)
    np.testing.assert_allclose(t.lookup(0.5), [0, 0.5, 0.5, 0.25], atol=1e-2)
    np.testing.assert_allclose(t.lookup(9.0), [1, 0, 0, 1], atol=1e-6)  # beyond x_max holds
    x = np.linspace(0, 2, 1000)
    np.testing.assert_allclose(t.lookup(x)[:, 3], np.interp(x, [0, 1, 2], [0, 0.5, 1]), atol=3e-3)
    assert t.clear_below == 0.0


def test_presets_and_clear_level() -> None:
    for name in transfer.PRESETS:
        t = transfer.build_table((), name)
        assert t.rgba.min() >= 0 and t.rgba.max() <= 1
        assert t.clear_below >= 0 and t.rgba[:, 3].max() > 0
    iso_like = transfer.build_table((), "iso-like")
    assert 0.9 < iso_like.clear_below < 1.0
    assert iso_like.lookup(1.5)[3] == pytest.approx(1.0)
    fog = transfer.build_table([TFPoint(x=0.0, alpha=0.1), TFPoint(x=1.0, alpha=0.2)])
    assert fog.clear_below == -1.0
    clear = transfer.build_table([TFPoint(x=0.0), TFPoint(x=1.0)])
    assert clear.clear_below == float("inf")


def test_step_corrected_alpha_composes() -> None:
    a = 0.3
    one = transfer.sample_alpha(a, 1.0)
    halves = 1 - (1 - transfer.sample_alpha(a, 0.5)) ** 2
    assert one == pytest.approx(a) and halves == pytest.approx(a)


def test_invalid_points() -> None:
    with pytest.raises(ValueError):
        transfer.build_table([(0.0, (1.0, 0.0, 0.0), 1.5)])
    with pytest.raises(ValueError):
        transfer.build_table([(-1.0, (1.0, 0.0, 0.0), 0.5)])


def test_element_residue_chain_colors() -> None:
    top = make_topology(
        6,
        elements=["O", "C", "N", "Xx", "FE", "h"],
        chains=["A", "B", "A", "C", "B", "A"],
        residues=["ASP", "LYS", "HOH", "LEU", "DA", "FOO"],
    )
    el = colors.atom_rgb(top, "element")
    np.testing.assert_allclose(el[0], colors.ELEMENT_COLORS["O"])
    np.testing.assert_allclose(el[3], colors.UNKNOWN_ELEMENT)
    np.testing.assert_allclose(el[4], colors.ELEMENT_COLORS["Fe"])
    np.testing.assert_allclose(el[5], colors.ELEMENT_COLORS["H"])
    res = colors.atom_rgb(top, "residue")
    np.testing.assert_allclose(res[0], colors.RESIDUE_CLASS_COLORS["acidic"])
    np.testing.assert_allclose(res[1], colors.RESIDUE_CLASS_COLORS["basic"])
    np.testing.assert_allclose(res[2], colors.RESIDUE_CLASS_COLORS["water"])
    np.testing.assert_allclose(res[4], colors.RESIDUE_CLASS_COLORS["nucleic"])
    np.testing.assert_allclose(res[5], colors.RESIDUE_CLASS_COLORS["other"])
    ch = colors.atom_rgb(top, "chain")
    np.testing.assert_allclose(ch[[0, 2, 5]], np.tile(colors.CHAIN_PALETTE[0], (3, 1)))
    np.testing.assert_allclose(ch[[1, 4]], np.tile(colors.CHAIN_PALETTE[1], (2, 1)))
    np.testing.assert_allclose(ch[3], colors.CHAIN_PALETTE[2])


def test_ramps_and_fallbacks() -> None:
    n = 50
    b = np.linspace(0, 100, n).astype(np.float32)
    q = np.linspace(-2, 2, n).astype(np.float32)
    top = make_topology(n, bfactors=b, charges=q)
    bf = colors.atom_rgb(top, "bfactor")
    assert bf[-1, 0] > bf[0, 0] and bf[0, 2] > bf[-1, 2]  # low blue, high red
    ch = colors.atom_rgb(top, "charge")
    assert ch[0, 0] > ch[0, 2] and ch[-1, 2] > ch[-1, 0]  # negative red, positive blue
    np.testing.assert_allclose(ch[n // 2], [0.95, 0.95, 0.95], atol=0.05)
    bare = make_topology(n)
    for scheme in ("bfactor", "charge", "uniform"):
        np.testing.assert_allclose(
            colors.atom_rgb(bare, scheme, (0.1, 0.2, 0.3)), np.tile([0.1, 0.2, 0.3], (n, 1))
        )  # type: ignore[arg-type]


def test_packing_radii_weights() -> None:
    rgb = np.random.default_rng(0).uniform(size=(100, 3))
    back = colors.unpack_rgba(colors.pack_rgba(rgb))
    assert np.abs(back - rgb).max() <= 0.5 / 255 + 1e-12
    assert np.all(colors.pack_rgba(rgb) >> 24 == 255)
    top = make_topology(3, elements=["H", "C", "Zz"])
    np.testing.assert_allclose(colors.atom_radii(top), [1.1, 1.7, colors.DEFAULT_RADIUS])
    own = make_topology(3, radii=np.array([2.0, 0.0, 1.0], np.float32))
    np.testing.assert_allclose(colors.atom_radii(own), [2.0, colors.DEFAULT_RADIUS, 1.0])
    np.testing.assert_array_equal(colors.atom_weights(top), np.ones(3))
