"""Volume mode's pre-integrated segments: the table against the float64 integral, and the image
against a converged one, with the sample sum at the same step as the control."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from protocol import Camera, Lighting, RenderParams
from server.render import segments, transfer
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
