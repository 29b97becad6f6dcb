// The orbit camera of the protocol and the maths the dashboard does with it.
//
// Camera: {target [x,y,z] angstrom, distance, orientation [w,x,y,z] (rotates camera space into
// world space), projection "perspective" | "orthographic", fov_deg (vertical), ortho_height}.
// The camera looks along its own -z: eye = target + R * (0, 0, distance).
// Pixel coordinates: (0, 0) is the top-left corner of the image, pixel centres at +0.5.

export const DEFAULT_CAMERA = Object.freeze({
  target: [0, 0, 0],
  distance: 50,
  orientation: [1, 0, 0, 0],
  projection: "perspective",
  fov_deg: 40,
  ortho_height: 40,
});

const MIN_DISTANCE = 0.5;
const MAX_DISTANCE = 1e5;

export function add(a, b) {
  return [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
}
export function sub(a, b) {
  return [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
}
export function scale(a, s) {
  return [a[0] * s, a[1] * s, a[2] * s];
}
export function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

export function quatMul(a, b) {
  const [aw, ax, ay, az] = a;
  const [bw, bx, by, bz] = b;
  return [
    aw * bw - ax * bx - ay * by - az * bz,
    aw * bx + ax * bw + ay * bz - az * by,
    aw * by - ax * bz + ay * bw + az * bx,
    aw * bz + ax * by - ay * bx + az * bw,
  ];
}

export function quatNormalize(q) {
  const n = Math.hypot(q[0], q[1], q[2], q[3]);
  if (!(n > 1e-12) || !Number.isFinite(n)) return [1, 0, 0, 0];
  const s = q[0] < 0 ? -1 / n : 1 / n; // keep w >= 0: one representative per rotation
  return [q[0] * s, q[1] * s, q[2] * s, q[3] * s];
}

export function quatAxisAngle(axis, angle) {
  const n = Math.hypot(axis[0], axis[1], axis[2]) || 1;
  const s = Math.sin(angle / 2) / n;
  return [Math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s];
}

/** Rotate vector v by unit quaternion q (R v). */
export function rotate(q, v) {
  const [w, x, y, z] = q;
  // t = 2 * cross(q.xyz, v); v' = v + w t + cross(q.xyz, t)
  const tx = 2 * (y * v[2] - z * v[1]);
  const ty = 2 * (z * v[0] - x * v[2]);
  const tz = 2 * (x * v[1] - y * v[0]);
  return [v[0] + w * tx + (y * tz - z * ty), v[1] + w * ty + (z * tx - x * tz), v[2] + w * tz + (x * ty - y * tx)];
}

/** Rotate by the inverse (R^T v). */
export function rotateInverse(q, v) {
  return rotate([q[0], -q[1], -q[2], -q[3]], v);
}

/** World-space camera axes: right (+x), up (+y), back (+z, from the target towards the eye). */
export function basis(cam) {
  const q = cam.orientation;
  return { right: rotate(q, [1, 0, 0]), up: rotate(q, [0, 1, 0]), back: rotate(q, [0, 0, 1]) };
}

export function eye(cam) {
  return add(cam.target, scale(rotate(cam.orientation, [0, 0, 1]), cam.distance));
}

/** Height of the view (angstrom) in the plane through the target. */
export function viewHeightAtTarget(cam) {
  if (cam.projection === "orthographic") return cam.ortho_height;
  return 2 * cam.distance * Math.tan((cam.fov_deg * Math.PI) / 360);
}

function finite(x, fallback) {
  return Number.isFinite(x) ? x : fallback;
}

/**
 * Everything wrong with a camera a file or a link gives (each naming its field), where
 * `normalizeCamera` would quietly put a default or a clamped value in its place; empty when none.
 */
export function cameraProblems(cam) {
  if (!cam || typeof cam !== "object" || Array.isArray(cam)) return ["camera is not an object"];
  const problems = [];
  const numbers = (key, n) => {
    const v = cam[key];
    if (v === undefined) return;
    if (!Array.isArray(v) || v.length !== n || !v.every((x) => typeof x === "number" && Number.isFinite(x))) {
      problems.push(`camera.${key} must be ${n} numbers`);
    }
  };
  numbers("target", 3);
  numbers("orientation", 4);
  if (Array.isArray(cam.orientation) && cam.orientation.every((x) => x === 0))
    problems.push("camera.orientation is zero");
  const bounded = (key, lo, hi) => {
    const v = cam[key];
    if (v === undefined) return;
    if (typeof v !== "number" || !Number.isFinite(v))
      problems.push(`camera.${key} ${JSON.stringify(v)} is not a number`);
    else if (v < lo || v > hi) problems.push(`camera.${key} ${v} is outside [${lo}, ${hi}]`);
  };
  bounded("distance", MIN_DISTANCE, MAX_DISTANCE);
  bounded("fov_deg", 5, 120);
  bounded("ortho_height", 0.1, Infinity);
  if (cam.projection !== undefined && !["perspective", "orthographic"].includes(cam.projection)) {
    problems.push(`camera.projection ${JSON.stringify(cam.projection)} is not perspective or orthographic`);
  }
  return problems;
}

/** A valid camera from anything camera-like (missing or non-finite fields take defaults). */
export function normalizeCamera(cam) {
  const c = cam && typeof cam === "object" ? cam : {};
  const t = Array.isArray(c.target) && c.target.length === 3 ? c.target : DEFAULT_CAMERA.target;
  const q = Array.isArray(c.orientation) && c.orientation.length === 4 ? c.orientation : DEFAULT_CAMERA.orientation;
  return {
    target: t.map((v) => finite(Number(v), 0)),
    distance: Math.min(MAX_DISTANCE, Math.max(MIN_DISTANCE, finite(Number(c.distance), DEFAULT_CAMERA.distance))),
    orientation: quatNormalize(q.map((v) => finite(Number(v), 0))),
    projection: c.projection === "orthographic" ? "orthographic" : "perspective",
    fov_deg: Math.min(120, Math.max(5, finite(Number(c.fov_deg), DEFAULT_CAMERA.fov_deg))),
    ortho_height: Math.max(0.1, finite(Number(c.ortho_height), DEFAULT_CAMERA.ortho_height)),
  };
}

/**
 * Orbit around the target: dragging right turns the molecule right, dragging down tilts its
 * top towards the viewer. `dx`, `dy` in pixels of a view `height` pixels tall; a drag over the
 * full height turns by `turn` radians.
 */
export function orbit(cam, dx, dy, height, turn = Math.PI) {
  const k = turn / Math.max(1, height);
  const yaw = quatAxisAngle([0, 1, 0], -dx * k);
  const pitch = quatAxisAngle([1, 0, 0], -dy * k);
  return { ...cam, orientation: quatNormalize(quatMul(quatMul(cam.orientation, yaw), pitch)) };
}

/** Pan: the molecule follows the pointer (dx, dy pixels of a view `height` pixels tall). */
export function pan(cam, dx, dy, height) {
  const s = viewHeightAtTarget(cam) / Math.max(1, height);
  const { right, up } = basis(cam);
  const move = add(scale(right, -dx * s), scale(up, dy * s));
  return { ...cam, target: add(cam.target, move) };
}

/** Zoom by `factor` > 1 (closer) or < 1 (farther); both projections stay in step. */
export function zoom(cam, factor) {
  const f = Number.isFinite(factor) && factor > 0 ? factor : 1;
  const distance = Math.min(MAX_DISTANCE, Math.max(MIN_DISTANCE, cam.distance / f));
  const applied = cam.distance / distance;
  return { ...cam, distance, ortho_height: Math.max(0.1, cam.ortho_height / applied) };
}

/** Switch projection keeping the apparent size of the molecule at the target. */
export function setProjection(cam, projection) {
  if (projection === cam.projection) return { ...cam };
  if (projection === "orthographic") {
    return { ...cam, projection, ortho_height: viewHeightAtTarget(cam) };
  }
  const tan = Math.tan((cam.fov_deg * Math.PI) / 360);
  const distance = Math.min(MAX_DISTANCE, Math.max(MIN_DISTANCE, cam.ortho_height / (2 * tan)));
  return { ...cam, projection, distance };
}

/** The ray through pixel (px, py) of a width x height view: {origin, dir} in world space. */
export function rayThrough(cam, px, py, width, height) {
  const aspect = width / height;
  const nx = (2 * px) / width - 1;
  const ny = 1 - (2 * py) / height;
  const q = cam.orientation;
  if (cam.projection === "orthographic") {
    const h = cam.ortho_height / 2;
    const offset = rotate(q, [nx * h * aspect, ny * h, 0]);
    return { origin: add(eye(cam), offset), dir: rotate(q, [0, 0, -1]) };
  }
  const t = Math.tan((cam.fov_deg * Math.PI) / 360);
  const d = rotate(q, [nx * t * aspect, ny * t, -1]);
  const n = Math.hypot(d[0], d[1], d[2]);
  return { origin: eye(cam), dir: scale(d, 1 / n) };
}

/**
 * Project a world point into pixel coordinates of a width x height view. Returns
 * [px, py, depth] with depth the distance in front of the camera along its viewing axis
 * (negative behind the camera).
 */
export function project(cam, point, width, height) {
  const local = rotateInverse(cam.orientation, sub(point, eye(cam)));
  const depth = -local[2];
  const aspect = width / height;
  let nx;
  let ny;
  if (cam.projection === "orthographic") {
    const h = cam.ortho_height / 2;
    nx = local[0] / (h * aspect);
    ny = local[1] / h;
  } else {
    const t = Math.tan((cam.fov_deg * Math.PI) / 360);
    const z = depth > 1e-9 ? depth : 1e-9;
    nx = local[0] / (z * t * aspect);
    ny = local[1] / (z * t);
  }
  return [((nx + 1) * width) / 2, ((1 - ny) * height) / 2, depth];
}

/**
 * The point under pixel (px, py) on the plane through `planePoint` parallel to the view plane:
 * where a pulled atom's spring should pull to. Null if the plane is behind the camera.
 */
export function unprojectToPlane(cam, px, py, width, height, planePoint) {
  const { origin, dir } = rayThrough(cam, px, py, width, height);
  const normal = rotate(cam.orientation, [0, 0, 1]);
  const denom = dot(dir, normal);
  if (Math.abs(denom) < 1e-12) return null;
  const t = dot(sub(planePoint, origin), normal) / denom;
  if (!(t > 0)) return null;
  return add(origin, scale(dir, t));
}

/** Camera with view presets: look along +-x, +-y, +-z of the world (axis name "x", "-y", ...). */
export function lookAlong(cam, axis) {
  const presets = {
    z: [1, 0, 0, 0],
    "-z": [0, 0, 1, 0],
    x: quatAxisAngle([0, 1, 0], Math.PI / 2),
    "-x": quatAxisAngle([0, 1, 0], -Math.PI / 2),
    y: quatAxisAngle([1, 0, 0], -Math.PI / 2),
    "-y": quatAxisAngle([1, 0, 0], Math.PI / 2),
  };
  const q = presets[axis];
  return q ? { ...cam, orientation: quatNormalize(q) } : { ...cam };
}

/** Whether two cameras are the same up to rounding (relative `eps`). */
export function sameCamera(a, b, eps = 1e-6) {
  if (!a || !b) return a === b;
  const close = (x, y) => Math.abs(x - y) <= eps * Math.max(1, Math.abs(x), Math.abs(y));
  return (
    a.projection === b.projection &&
    close(a.distance, b.distance) &&
    close(a.fov_deg, b.fov_deg) &&
    close(a.ortho_height, b.ortho_height) &&
    a.target.every((v, i) => close(v, b.target[i])) &&
    a.orientation.every((v, i) => close(v, b.orientation[i]))
  );
}
