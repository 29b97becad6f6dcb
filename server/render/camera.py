"""Orbit-camera maths in numpy: the device only gets the resulting frame (a few vectors).

Conventions (see docs/rendering.md): `Camera.orientation` is a unit quaternion (w, x, y, z)
rotating camera space into world space; the camera sits at target + R (0, 0, distance) and
looks along camera -z; camera +x is image right, +y image up. Pixel (x, y) counts x from the
left and y from the top; its ray passes through the pixel centre. Perspective rays start at
the eye; orthographic rays start on the plane through the eye, perpendicular to the view.
`fov_deg` is the vertical field of view, `ortho_height` the visible height in angstrom.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from protocol import Camera
from protocol.limits import MAX_CAMERA_A

Projection = Literal["perspective", "orthographic"]
F64 = npt.NDArray[np.float64]


def quat_to_matrix(q: tuple[float, float, float, float] | npt.ArrayLike) -> F64:
    """3x3 rotation of a (w, x, y, z) quaternion; normalised first so drift does no harm."""
    w, x, y, z = np.asarray(q, dtype=np.float64).reshape(4)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0 or not math.isfinite(n):
        raise ValueError("orientation quaternion has zero or non-finite norm")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(m: npt.ArrayLike) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix, with w >= 0 (Shepperd's method, stable everywhere)."""
    r = np.asarray(m, dtype=np.float64).reshape(3, 3)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = ((r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s)
    a = np.asarray(q)
    a = a / np.linalg.norm(a)
    if a[0] < 0:
        a = -a
    return (float(a[0]), float(a[1]), float(a[2]), float(a[3]))


@dataclass(frozen=True)
class CameraFrame:
    """What a ray generator needs: eye and world-space axes, plus the image-plane scale.

    `scale` is tan(fov/2) for perspective and half the visible height (angstrom) for
    orthographic; the horizontal extent is `scale * aspect`.
    """

    eye: F64
    right: F64
    up: F64
    forward: F64
    scale: float
    aspect: float
    ortho: bool
    width: int
    height: int

    def key(self) -> tuple[float | int | bool, ...]:
        """Every value as a hashable tuple: equal keys draw the same rays."""
        vectors = (self.eye, self.right, self.up, self.forward)
        values = tuple(float(v) for vec in vectors for v in vec)
        return (*values, self.scale, self.aspect, self.ortho, self.width, self.height)


def camera_frame(camera: Camera, width: int, height: int) -> CameraFrame:
    r = quat_to_matrix(camera.orientation)
    target = np.asarray(camera.target, dtype=np.float64)
    eye = target + r @ np.array([0.0, 0.0, float(camera.distance)])
    ortho = camera.projection == "orthographic"
    scale = 0.5 * camera.ortho_height if ortho else math.tan(math.radians(camera.fov_deg) / 2)
    return CameraFrame(
        eye=eye,
        right=r[:, 0].copy(),
        up=r[:, 1].copy(),
        forward=-r[:, 2],
        scale=float(scale),
        aspect=width / height,
        ortho=ortho,
        width=int(width),
        height=int(height),
    )


def pixel_rays(frame: CameraFrame, xs: npt.ArrayLike, ys: npt.ArrayLike) -> tuple[F64, F64]:
    """Origins and unit directions (..., 3) of the rays through pixels (xs, ys)."""
    x = np.asarray(xs, dtype=np.float64)
    y = np.asarray(ys, dtype=np.float64)
    u = (2.0 * (x + 0.5) / frame.width - 1.0) * frame.aspect * frame.scale
    v = (1.0 - 2.0 * (y + 0.5) / frame.height) * frame.scale
    plane = u[..., None] * frame.right + v[..., None] * frame.up
    if frame.ortho:
        origins = frame.eye + plane
        dirs = np.broadcast_to(frame.forward, origins.shape).copy()
    else:
        dirs = frame.forward + plane
        dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(frame.eye, dirs.shape).copy()
    return origins, dirs


def image_rays(frame: CameraFrame) -> tuple[F64, F64]:
    """All rays of the image, shaped (height, width, 3), row 0 at the top."""
    ys, xs = np.mgrid[0 : frame.height, 0 : frame.width]
    return pixel_rays(frame, xs, ys)


def project(frame: CameraFrame, points: npt.ArrayLike) -> F64:
    """World points -> (..., 3) of (pixel x, pixel y, depth along the view axis)."""
    p = np.asarray(points, dtype=np.float64) - frame.eye
    cx = p @ frame.right
    cy = p @ frame.up
    cz = p @ frame.forward
    if frame.ortho:
        u, v = cx, cy
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = cx / cz, cy / cz
    px = (u / (frame.aspect * frame.scale) + 1.0) * 0.5 * frame.width - 0.5
    py = (1.0 - v / frame.scale) * 0.5 * frame.height - 0.5
    return np.stack([px, py, cz], axis=-1)


def look_at(
    eye: npt.ArrayLike,
    target: npt.ArrayLike,
    up: npt.ArrayLike = (0.0, 1.0, 0.0),
    **kwargs: object,
) -> Camera:
    """A camera at `eye` looking at `target`, with `up` as close to image-up as possible."""
    e = np.asarray(eye, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    back = e - t
    dist = float(np.linalg.norm(back))
    if not dist > 0:
        raise ValueError("eye and target coincide")
    z = back / dist
    u = np.asarray(up, dtype=np.float64)
    x = np.cross(u, z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    q = matrix_to_quat(np.stack([x, y, z], axis=1))
    return Camera.model_validate(
        {"target": tuple(float(c) for c in t), "distance": dist, "orientation": q, **kwargs}
    )


def orbit(camera: Camera, yaw_deg: float, pitch_deg: float) -> Camera:
    """Turn the camera about its target: yaw around camera up, then pitch around camera right."""
    r = quat_to_matrix(camera.orientation)

    def axis_rot(axis: F64, deg: float) -> F64:
        a = axis / np.linalg.norm(axis)
        th = math.radians(deg)
        k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        rot: F64 = np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * (k @ k)
        return rot

    r = axis_rot(r[:, 1], yaw_deg) @ r
    r = axis_rot(r[:, 0], pitch_deg) @ r
    return camera.model_copy(update={"orientation": matrix_to_quat(r)})


def fit_camera(
    positions: npt.ArrayLike,
    width: int,
    height: int,
    projection: Projection = "perspective",
    *,
    margin: float = 4.0,
    fov_deg: float = 40.0,
    orientation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
) -> Camera:
    """A camera that frames all atoms: the bounding sphere (plus `margin` angstrom for the
    density's extent) fits the narrower of the two fields of view."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) == 0:
        center = np.zeros(3)
        radius = 10.0
    else:
        lo, hi = p.min(axis=0), p.max(axis=0)
        center = 0.5 * (lo + hi)
        radius = float(np.sqrt(((p - center) ** 2).sum(axis=1).max())) + margin
    aspect = width / height
    half_v = math.radians(fov_deg) / 2
    half_h = math.atan(math.tan(half_v) * aspect)
    half = min(half_v, half_h)
    # atoms past MAX_COORDINATE_A draw background anyway: the camera stays within its limit
    distance = min(radius / math.sin(half), MAX_CAMERA_A)
    ortho_height = min(2.0 * radius * max(1.0, 1.0 / aspect), MAX_CAMERA_A)
    return Camera.model_validate(
        {
            "target": tuple(float(c) for c in center),
            "distance": float(distance),
            "orientation": orientation,
            "projection": projection,
            "fov_deg": fov_deg,
            "ortho_height": ortho_height,
        }
    )


def band_planes(frame: CameraFrame, y0: float, y1: float) -> tuple[F64, F64]:
    """The planes (normal, offset) bounding the rays of image rows [y0, y1) (edges in pixels,
    0 at the top): a point p lies between them where dot(normal, p) + offset >= 0 for both,
    with normals of unit length (so a distance from a plane is that expression)."""
    h = float(frame.height)
    v_top = (1.0 - 2.0 * y0 / h) * frame.scale
    v_bottom = (1.0 - 2.0 * y1 / h) * frame.scale
    eye, up, forward = frame.eye, frame.up, frame.forward
    if frame.ortho:
        top_n, bottom_n = -up, up.copy()
        top_d = v_top + float(up @ eye)
        bottom_d = -v_bottom - float(up @ eye)
        return np.append(top_n, top_d), np.append(bottom_n, bottom_d)
    top_n = v_top * forward - up
    bottom_n = up - v_bottom * forward
    top_n = top_n / np.linalg.norm(top_n)
    bottom_n = bottom_n / np.linalg.norm(bottom_n)
    return np.append(top_n, -float(top_n @ eye)), np.append(bottom_n, -float(bottom_n @ eye))
