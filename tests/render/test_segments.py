"""Volume mode's pre-integrated segments: the table against the float64 integral, and the image
against a converged one, with the sample sum at the same step as the control."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from protocol import Camera, Lighting, RenderParams, TFPoint
from server.render import segments, transfer
from server.render.camera import camera_frame, fit_camera, image_rays, look_at
from server.render.renderer import Renderer
from server.render.tuning import VOLUME_STEPS, Tuning
from tests.render.conftest import blob, make_topology
from tests.render.helpers import render
from tests.render.molecules import villin

LENGTH_A = 0.75


@pytest.fixture(scope="module")
def shells() -> tuple[transfer.TransferTable, np.ndarray]:
    tf = transfer.build_table((), "shells")
    size = tf.rgba.shape[0]
    out = wp.empty((size, size), dtype=wp.vec4, device="cpu")
    segments.build(wp.array(tf.rgba, dtype=wp.vec4, device="cpu"), LENGTH_A, out)
    return tf, out.numpy()


def test_each_entry_is_the_integral_along_its_ramp(
    shells: tuple[transfer.TransferTable, np.ndarray],
) -> None:
    tf, table = shells
    step = tf.x_max / (tf.rgba.shape[0] - 1)
    rng = np.random.default_rng(3)
    for i, j in [(0, 255), (255, 0), (40, 41), *rng.integers(0, 256, size=(12, 2))]:
        want = segments.ramp_integral(tf, i * step, j * step, LENGTH_A, substeps=2048)
        np.testing.assert_allclose(table[i, j], want, atol=2e-3)


def test_a_constant_density_is_one_sample_of_the_sum(
    shells: tuple[transfer.TransferTable, np.ndarray],
) -> None:
    tf, table = shells
    diag = table[np.arange(256), np.arange(256)]
    a = transfer.sample_alpha(tf.rgba[:, 3], LENGTH_A)
    np.testing.assert_allclose(diag[:, 3], a, atol=1e-6)
    np.testing.assert_allclose(diag[:, :3], tf.rgba[:, :3] * a[:, None], atol=1e-6)


def test_a_ramp_past_the_table_holds_its_last_value_beyond_it() -> None:
    """x runs to three times the table's end: the part past it is the last entry's medium."""
    tf = transfer.build_table((), "shells")
    size = tf.rgba.shape[0]
    out = wp.empty((size, size), dtype=wp.vec4, device="cpu")
    segments.build(wp.array(tf.rgba, dtype=wp.vec4, device="cpu"), LENGTH_A, out)
    got = wp.zeros(4, dtype=wp.vec4, device="cpu")
    last = size - 1
    u = wp.array(
        np.array([[200, 3 * last], [3 * last, 200], [2 * last, 3 * last], [10, 20]]),
        dtype=wp.vec2,
        device="cpu",
    )

    wp.launch(_read_ramps, 4, (out, last, u, got), device="cpu")
    x = u.numpy() * tf.x_max / last
    for k in range(4):
        want = segments.ramp_integral(tf, x[k, 0], x[k, 1], LENGTH_A, substeps=4096)
        np.testing.assert_allclose(got.numpy()[k], want, atol=1e-2)


@wp.kernel
def _read_ramps(
    seg: wp.array2d[wp.vec4], last: int, u: wp.array[wp.vec2], out: wp.array[wp.vec4]
) -> None:
    i = wp.tid()
    out[i] = segments.ramp(seg, last, u[i][0], u[i][1])


def _image(preset: str, step: float, ramps: bool) -> np.ndarray:
    m = villin()
    c = m.positions.mean(0)
    cam = Camera(position=tuple(c + np.array([0.0, 0.0, 60.0])), target=tuple(c), fov_deg=40)
    p = RenderParams(
        mode="volume",
        tf_preset=preset,  # type: ignore[arg-type]
        step_sigmas=step,
        lighting=Lighting(diffuse=0.0, specular=0.0, ambient=1.0),
    )
    r = render("cpu", m.topology, m.positions, p, cam, 48, 48, volume_steps=1, volume_ramps=ramps)
    return r.read_rgba()[..., :3].astype(np.float64)


def test_ramps_at_twice_the_step_beat_the_sum_at_one() -> None:
    """Villin through the sharp "shells" transfer function, against a converged image (step
    1/32 sigma): segments at 0.5 sigma err less than the sample sum did at 0.25 sigma, and at
    the same step less than the sum at that step."""
    ref = _image("shells", 1 / 32, True)
    err = {
        (step, ramps): np.abs(_image("shells", step, ramps) - ref).mean()
        for step in (0.25, 0.5)
        for ramps in (False, True)
    }
    assert err[(0.5, True)] < err[(0.25, False)], err
    assert err[(0.5, True)] < 0.5 * err[(0.5, False)], err
    assert err[(0.25, True)] < 0.5 * err[(0.25, False)], err


def _villin_image(
    camera: Camera, preset: str, step: float, limit: np.ndarray | None = None, **tuning: object
) -> np.ndarray:
    """Villin unshaded at 48x48, each ray stopped at `limit` when one is given."""
    m = villin()
    r = Renderer("cpu", tuning=Tuning.of(tuning) if tuning else None)
    r.set_topology(m.topology)
    r.set_positions(m.positions)
    if limit is not None:
        r.depth_limit = wp.array(limit.astype(np.float32).ravel(), dtype=float, device="cpu")
    p = RenderParams(
        mode="volume",
        tf_preset=preset,  # type: ignore[arg-type]
        step_sigmas=step,
        lighting=Lighting(diffuse=0.0, specular=0.0, ambient=1.0),
    )
    r.render(p, camera, 48, 48)
    return r.read_rgba()[..., :3].astype(np.float64)


def _errors(
    camera: Camera, preset: str, limit: np.ndarray | None = None
) -> dict[str, tuple[float, float]]:
    """(mean |error|, mean error) in 8-bit levels against the converged image (1/32 sigma) of
    the default volume step and of the sample sum at one step (the control)."""
    ref = _villin_image(camera, preset, 1 / 32, limit, volume_steps=1)
    out = {}
    for name, tuning in (("default", {}), ("sum", {"volume_steps": 1, "volume_ramps": False})):
        err = _villin_image(camera, preset, 0.25, limit, **tuning) - ref
        out[name] = (float(np.abs(err).mean()), float(err.mean()))
    return out


def test_a_camera_inside_the_molecule_sees_no_shell_that_is_not_there() -> None:
    """A ray that starts inside the molecule begins with the density at its origin: its
    first segment does not ramp up from the clear level through every shell of the transfer
    function below the density at the camera, which drew those shells over the whole image
    (mean error 7.3 levels against the sum's 2.7)."""
    c = villin().positions.mean(0)
    inside = look_at(tuple(c), tuple(c + np.array([0.0, 0.0, -5.0])), fov_deg=70.0)
    err = _errors(inside, "shells")
    assert err["default"][0] < err["sum"][0], err
    assert abs(err["default"][1]) < 1.5, err


def test_a_cloud_cut_at_a_surface_keeps_its_segment_up_to_it() -> None:
    """A cloud whose rays stop at a depth limit (the opaque layers in front of its far side)
    composites the segment from its last sample to the limit: without it the cloud lost up
    to a step of material in front of every surface (mean error 1.4 levels, a bias of -1.2,
    largest 51)."""
    c = villin().positions.mean(0)
    cam = Camera(position=tuple(c + np.array([0.0, 0.0, 60.0])), target=tuple(c), fov_deg=40)
    origins, dirs = image_rays(camera_frame(cam, 48, 48))
    plane = (c[2] - origins[..., 2]) / dirs[..., 2]  # a wall through the molecule's centre
    err = _errors(cam, "cloud", plane)
    assert err["default"][0] < err["sum"][0], err
    assert abs(err["default"][1]) < 0.3, err


def test_the_segments_are_made_again_when_their_table_or_step_changes_and_only_then(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One renderer through changes of parameters: the segment table is rebuilt when the
    transfer table or the volume step (sigma, step_sigmas) changes, and each image equals a
    fresh renderer's; a preset named beside control points (which replace it) or an iso frame
    in between rebuilds nothing."""
    built: list[float] = []
    real = segments.build

    def build(table: object, length_A: float, out: object) -> None:
        built.append(length_A)
        real(table, length_A, out)

    monkeypatch.setattr(segments, "build", build)
    n = 40
    top = make_topology(n)
    pos = blob(n, seed=3)
    cam = fit_camera(pos, 24, 18)
    tf = [TFPoint(x=0.0), TFPoint(x=0.5), TFPoint(x=1.0, color=(1.0, 0.0, 0.0), alpha=0.6)]
    steps: list[tuple[RenderParams, bool]] = [
        (RenderParams(mode="volume", sigma_A=1.5), True),
        (RenderParams(mode="volume", sigma_A=1.5, iso_level=0.4), False),
        (RenderParams(mode="iso", sigma_A=1.2), False),
        (RenderParams(mode="volume", sigma_A=1.5, iso_level=0.4), False),
        (RenderParams(mode="volume", sigma_A=2.0), True),
        (RenderParams(mode="volume", sigma_A=2.0, transfer_function=tf), True),
        (RenderParams(mode="volume", sigma_A=2.0, transfer_function=tf, tf_preset="shells"), False),
        (RenderParams(mode="volume", sigma_A=2.0, step_sigmas=0.4, transfer_function=tf), True),
    ]
    r = Renderer("cpu")
    r.set_topology(top)
    r.set_positions(pos)
    for params, rebuilt in steps:
        before = len(built)
        r.render(params, cam, 24, 18)
        assert len(built) - before == int(rebuilt), params
        if rebuilt:
            assert built[-1] == pytest.approx(params.step_sigmas * params.sigma_A * VOLUME_STEPS)
        fresh = render("cpu", top, pos, params, cam, 24, 18)
        np.testing.assert_array_equal(r.read_rgba(), fresh.read_rgba())
