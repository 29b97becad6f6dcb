"""Golden images of a real small molecule (gramicidin A, PDB 1GRM, 272 atoms), compared with
tolerance. The coordinates travel with the tests (data/gramicidin_1grm.npz, read from
MDAnalysisTests' 1grm_single.pdb) so this runs without MDAnalysis.

Regenerate deliberately with `pytest tests/render --regen-golden` (then look at the PNGs)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from protocol import Lighting, RenderParams
from server.render.camera import fit_camera, orbit
from tests.render.conftest import GOLDEN_DIR
from tests.render.golden_images import H, W, assert_image_approx_equal, check_golden, gramicidin
from tests.render.helpers import render

CASES = {
    "iso_element": RenderParams(sigma_A=1.2, color_by="element"),
    "iso_chain_ao": RenderParams(
        sigma_A=2.0,
        iso_level=0.4,
        color_by="chain",
        lighting=Lighting(ambient_occlusion=True, depth_cue=0.5),
    ),
    "volume_cloud": RenderParams(mode="volume", sigma_A=1.5, tf_preset="cloud"),
    "volume_shells": RenderParams(mode="volume", sigma_A=1.8, tf_preset="shells"),
    "iso_warped": RenderParams(sigma_A=2.0, scale_space="warped", color_by="residue"),
    "volume_warped": RenderParams(
        mode="volume", sigma_A=2.0, scale_space="warped", tf_preset="cloud"
    ),
}


@pytest.fixture(scope="module", name="gramicidin")
def gramicidin_fixture() -> tuple[object, np.ndarray]:
    return gramicidin()


@pytest.mark.parametrize("name", sorted(CASES))
def test_golden(
    device: str, name: str, gramicidin: tuple[object, np.ndarray], regen_golden: bool
) -> None:
    top, pos = gramicidin
    cam = orbit(fit_camera(pos, W, H, margin=2.0), 35.0, 20.0)
    r = render(device, top, pos, CASES[name], cam, W, H)  # type: ignore[arg-type]
    check_golden(r.read_rgba()[..., :3], name, device, regen_golden)
    # guard against a blank reference: the molecule fills a good part of the frame
    assert np.isfinite(r.read_depth()).mean() > 0.1


def test_comparison_catches_a_different_picture() -> None:
    want = np.asarray(Image.open(GOLDEN_DIR / "iso_element.png").convert("RGB"))
    shifted = np.roll(want, 6, axis=1)
    with pytest.raises(AssertionError):
        assert_image_approx_equal(shifted, want, "shifted")
