import assert from "node:assert/strict";
import { test } from "node:test";

import {
  DEFAULT_CAMERA,
  basis,
  eye,
  normalizeCamera,
  orbit,
  pan,
  project,
  quatAxisAngle,
  rayThrough,
  sameCamera,
  setProjection,
  unprojectToPlane,
  viewHeightAtTarget,
  zoom,
} from "../src/camera.js";

const close = (a, b, eps = 1e-6) => assert.ok(Math.abs(a - b) <= eps, `${a} != ${b}`);
const closeVec = (a, b, eps = 1e-6) => a.forEach((v, i) => close(v, b[i], eps));

const cam = { ...DEFAULT_CAMERA, target: [1, 2, 3], distance: 30 };

test("the camera sits on its +z axis and looks along -z", () => {
  closeVec(eye(cam), [1, 2, 33]);
  const turned = { ...cam, orientation: quatAxisAngle([0, 1, 0], Math.PI / 2) };
  closeVec(eye(turned), [31, 2, 3]);
  closeVec(basis(turned).right, [0, 0, -1]);
});

test("the target projects to the centre of the view", () => {
  for (const projection of ["perspective", "orthographic"]) {
    const [px, py, depth] = project({ ...cam, projection }, cam.target, 640, 480);
    close(px, 320);
    close(py, 240);
    close(depth, 30);
  }
});

test("project and unproject are inverse on the plane through a point", () => {
  for (const projection of ["perspective", "orthographic"]) {
    const c = orbit({ ...cam, projection }, 37, -12, 480);
    const p = [4, -1, 6];
    const [px, py] = project(c, p, 640, 480);
    closeVec(unprojectToPlane(c, px, py, 640, 480, p), p, 1e-6);
    // another pixel lands on the same view-parallel plane
    const q = unprojectToPlane(c, px + 50, py - 20, 640, 480, p);
    const { back } = basis(c);
    close(
      back.reduce((s, v, i) => s + v * (q[i] - p[i]), 0),
      0,
      1e-9,
    );
  }
});

test("a ray through a pixel passes through what projects there", () => {
  const c = orbit(cam, 100, 40, 480);
  const p = [2, 5, -1];
  const [px, py] = project(c, p, 800, 600);
  const { origin, dir } = rayThrough(c, px, py, 800, 600);
  const t = dir.reduce((s, v, i) => s + v * (p[i] - origin[i]), 0);
  closeVec(
    origin.map((o, i) => o + t * dir[i]),
    p,
    1e-6,
  );
});

test("dragging right turns the near side of the molecule right", () => {
  const near = [cam.target[0], cam.target[1], cam.target[2] + 5]; // towards the camera
  const before = project(cam, near, 640, 480)[0];
  const after = project(orbit(cam, 50, 0, 480), near, 640, 480)[0];
  assert.ok(after > before, `${after} should be right of ${before}`);
});

test("dragging down tilts the top of the molecule towards the viewer", () => {
  const top = [cam.target[0], cam.target[1] + 5, cam.target[2]];
  const depthBefore = project(cam, top, 640, 480)[2];
  const depthAfter = project(orbit(cam, 0, 40, 480), top, 640, 480)[2];
  assert.ok(depthAfter < depthBefore);
});

test("panning moves the molecule with the pointer", () => {
  for (const projection of ["perspective", "orthographic"]) {
    const c = { ...cam, projection };
    const moved = pan(c, 64, 32, 480);
    const [px, py] = project(moved, c.target, 640, 480);
    close(px, 320 + 64, 1e-6);
    close(py, 240 + 32, 1e-6);
  }
});

test("zoom changes distance and ortho height together; projections keep the size", () => {
  const z = zoom(cam, 2);
  close(z.distance, 15);
  close(z.ortho_height, cam.ortho_height / 2);
  const ortho = setProjection(cam, "orthographic");
  close(viewHeightAtTarget(ortho), viewHeightAtTarget(cam));
  const back = setProjection(ortho, "perspective");
  close(back.distance, cam.distance);
  assert.equal(zoom(cam, Number.NaN).distance, cam.distance);
});

test("normalizeCamera repairs what a hash or a server may hand over", () => {
  const c = normalizeCamera({
    target: [1, "2", Number.NaN],
    orientation: [0, 0, 0, 2],
    distance: -5,
    projection: "fisheye",
  });
  assert.deepEqual(c.target, [1, 2, 0]);
  closeVec(c.orientation, [0, 0, 0, 1]);
  assert.ok(c.distance > 0);
  assert.equal(c.projection, "perspective");
  assert.deepEqual(normalizeCamera(null).orientation, [1, 0, 0, 0]);
});

test("sameCamera ignores rounding and sees any real change", () => {
  const echoed = { ...cam, target: cam.target.map((v) => v * (1 + 1e-9)) };
  assert.ok(sameCamera(cam, echoed));
  assert.ok(!sameCamera(cam, { ...cam, distance: cam.distance + 0.01 }));
  assert.ok(!sameCamera(cam, setProjection(cam, "orthographic")));
  assert.ok(!sameCamera(cam, orbit(cam, 5, 0, 100)));
  assert.ok(sameCamera(null, null));
  assert.ok(!sameCamera(cam, null));
});
