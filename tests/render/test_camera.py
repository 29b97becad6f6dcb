"""Camera maths (numpy): quaternions, rays, projection, framing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import Camera
from server.render.camera import (
    camera_frame,
    fit_camera,
    image_rays,
    look_at,
    matrix_to_quat,
    orbit,
    pixel_rays,
    project,
    quat_to_matrix,
)

unit = st.floats(-1, 1, allow_nan=False)


@given(st.tuples(unit, unit, unit, unit).filter(lambda q: sum(c * c for c in q) > 1e-3))
@settings(max_examples=60, deadline=None)
def test_quaternion_roundtrip(q: tuple[float, float, float, float]) -> None:
    m = quat_to_matrix(q)
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m) == pytest.approx(1.0)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(m)), m, atol=1e-9)


def test_quaternion_convention_rotates_camera_to_world() -> None:
    # 90 degrees about +y: camera +z (towards the viewer) becomes world +x
    q = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
    np.testing.assert_allclose(quat_to_matrix(q) @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    cam = Camera(target=(1.0, 2.0, 3.0), distance=10.0, orientation=q)
    f = camera_frame(cam, 10, 10)
    np.testing.assert_allclose(f.eye, [11.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(f.forward, [-1.0, 0.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError):
        quat_to_matrix((0.0, 0.0, 0.0, 0.0))


def test_identity_camera_frame_and_fov() -> None:
    cam = Camera(target=(0.0, 0.0, 0.0), distance=50.0, fov_deg=60.0)
    f = camera_frame(cam, 200, 100)
    np.testing.assert_allclose(f.eye, [0, 0, 50])
    np.testing.assert_allclose(f.forward, [0, 0, -1])
    assert f.aspect == 2.0 and f.scale == pytest.approx(math.tan(math.radians(30)))
    # the top edge of the image (y = -0.5) is fov/2 above the axis
    _, d = pixel_rays(f, np.array([99.5]), np.array([-0.5]))
    assert math.degrees(math.acos(-d[0, 2])) == pytest.approx(30.0)
    o, d = image_rays(f)
    assert o.shape == (100, 200, 3) and d.shape == (100, 200, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    assert d[0, 100, 1] > 0 > d[99, 100, 1]  # row 0 is the top
    assert d[50, 0, 0] < 0 < d[50, 199, 0]  # column 0 is the left


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_project_inverts_rays(projection: str) -> None:
    cam = orbit(Camera(target=(3.0, -1.0, 7.0), distance=40.0, projection=projection), 30, 20)  # type: ignore[arg-type]
    f = camera_frame(cam, 64, 48)
    xs, ys = np.meshgrid(np.arange(64), np.arange(48))
    o, d = pixel_rays(f, xs, ys)
    p = project(f, o + 25.0 * d)
    np.testing.assert_allclose(p[..., 0], xs, atol=1e-9)
    np.testing.assert_allclose(p[..., 1], ys, atol=1e-9)
    if projection == "orthographic":
        np.testing.assert_allclose(d, np.broadcast_to(f.forward, d.shape))
        assert np.ptp(o @ f.up) == pytest.approx(cam.ortho_height * 47 / 48)


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
@pytest.mark.parametrize(("w", "h"), [(100, 100), (300, 100), (100, 300)])
def test_fit_camera_frames_every_atom(projection: str, w: int, h: int) -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(500, 3)) * [20, 5, 9] + [100, -40, 7]
    cam = fit_camera(pts, w, h, projection, margin=0.0)  # type: ignore[arg-type]
    pix = project(camera_frame(cam, w, h), pts)
    assert pix[:, 0].min() >= -0.5 and pix[:, 0].max() <= w - 0.5
    assert pix[:, 1].min() >= -0.5 and pix[:, 1].max() <= h - 0.5
    assert pix[:, 2].min() > 0  # everything in front of the camera
    # and not absurdly small: the cloud spans a good part of the narrower side
    span = max(np.ptp(pix[:, 0]), np.ptp(pix[:, 1])) / min(w, h)
    assert span > 0.5


def test_fit_camera_empty_and_look_at() -> None:
    assert fit_camera(np.zeros((0, 3)), 10, 10).distance > 0
    cam = look_at((10.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    f = camera_frame(cam, 8, 8)
    np.testing.assert_allclose(f.eye, [10, 0, 0], atol=1e-9)
    np.testing.assert_allclose(f.forward, [-1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(f.up, [0, 1, 0], atol=1e-9)
    straight_down = look_at((0.0, 5.0, 0.0), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(camera_frame(straight_down, 4, 4).forward, [0, -1, 0], atol=1e-9)


def test_orbit_keeps_target_and_distance() -> None:
    cam = Camera(target=(1.0, 2.0, 3.0), distance=12.0)
    turned = cam
    for _ in range(4):
        turned = orbit(turned, 90.0, 0.0)
    np.testing.assert_allclose(quat_to_matrix(turned.orientation), np.eye(3), atol=1e-9)
    tilted = orbit(cam, 10.0, 35.0)
    f = camera_frame(tilted, 4, 4)
    assert np.linalg.norm(f.eye - np.array(cam.target)) == pytest.approx(12.0)
    assert tilted.target == cam.target


def test_a_camera_fitted_to_atoms_past_any_coordinate_stays_within_the_cameras_limit() -> None:
    """A damaged file with an atom at 1e30 A (its frame draws background): the fitted camera
    is a valid one, at the farthest distance a camera may have."""
    from protocol.limits import MAX_CAMERA_A

    far = np.array([[0.0, 0.0, 0.0], [1.0e30, 0.0, 0.0]], dtype=np.float32)
    for projection in ("perspective", "orthographic"):
        cam = fit_camera(far, 32, 24, projection)  # type: ignore[arg-type]
        assert cam.distance == MAX_CAMERA_A and cam.ortho_height == MAX_CAMERA_A
