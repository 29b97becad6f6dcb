import assert from "node:assert/strict";
import { test } from "node:test";

import {
  MIN_GAP,
  TF_DOMAIN,
  curvePath,
  domainFor,
  evaluate,
  fromScreen,
  hexToRgb,
  histogramBars,
  histogramRange,
  insertPoint,
  movePoint,
  nearestPoint,
  normalizePoints,
  presetPoints,
  recolorPoint,
  removePoint,
  rgbToHex,
  toScreen,
} from "../src/transfer.js";

const pts = [
  { x: 0, color: [0, 0, 0], alpha: 0 },
  { x: 1, color: [1, 0, 0], alpha: 0.5 },
  { x: 2, color: [1, 1, 1], alpha: 1 },
];
const box = { left: 10, top: 5, width: 300, height: 100 };
const close = (a, b, eps = 1e-9) => assert.ok(Math.abs(a - b) <= eps, `${a} != ${b}`);

test("evaluate interpolates opacity and colour and holds the ends", () => {
  close(evaluate(pts, 0.5).alpha, 0.25);
  assert.deepEqual(evaluate(pts, 1.5).color, [1, 0.5, 0.5]);
  close(evaluate(pts, -1).alpha, 0);
  close(evaluate(pts, 9).alpha, 1);
});

test("a dragged point stays between its neighbours and inside the unit opacity range", () => {
  const moved = movePoint(pts, 1, 5, 1.7);
  close(moved[1].x, 2 - MIN_GAP);
  close(moved[1].alpha, 1);
  const left = movePoint(pts, 1, -3, -0.2);
  close(left[1].x, MIN_GAP);
  close(left[1].alpha, 0);
  close(movePoint(pts, 2, 99, 0.3)[2].x, TF_DOMAIN[1]);
  assert.equal(pts[1].x, 1, "the input is not modified");
});

test("inserting interpolates, keeps order, refuses duplicates", () => {
  const { points, index } = insertPoint(pts, 1.5);
  assert.equal(index, 2);
  assert.deepEqual(
    points.map((p) => p.x),
    [0, 1, 1.5, 2],
  );
  close(points[2].alpha, 0.75);
  assert.equal(insertPoint(pts, 1).index, -1);
  assert.equal(insertPoint(pts, 0.5, 0.9).points[1].alpha, 0.9);
});

test("removing keeps at least two points", () => {
  assert.equal(removePoint(pts, 1).length, 2);
  const two = removePoint(pts, 1);
  assert.equal(removePoint(two, 0).length, 2);
});

test("screen mapping is invertible and hit-testing finds the nearest point", () => {
  const p = { x: 1.2, alpha: 0.3 };
  const [sx, sy] = toScreen(p, box);
  const back = fromScreen(sx, sy, box);
  close(back.x, 1.2);
  close(back.alpha, 0.3);
  const [hx, hy] = toScreen(pts[1], box);
  assert.equal(nearestPoint(pts, hx + 3, hy - 2, box), 1);
  assert.equal(nearestPoint(pts, hx + 40, hy, box), -1);
  const clamped = fromScreen(-100, 1000, box);
  assert.deepEqual([clamped.x, clamped.alpha], [TF_DOMAIN[0], 0]);
});

test("recolouring and normalising clamp and sort", () => {
  assert.deepEqual(recolorPoint(pts, 0, [2, -1, 0.5])[0].color, [1, 0, 0.5]);
  const n = normalizePoints([{ x: 2, alpha: 3 }, { x: Number.NaN }, { x: -1, color: [0.1, 0.2, 0.3], alpha: 0.5 }]);
  assert.deepEqual(
    n.map((p) => p.x),
    [0, 2],
  );
  assert.equal(n[1].alpha, 1);
  assert.deepEqual(n[1].color, [1, 1, 1]);
});

test("presets are sorted, inside the domain, and copies", () => {
  for (const name of ["cloud", "shells", "iso-like"]) {
    const p = presetPoints(name);
    assert.deepEqual(normalizePoints(p), p);
    assert.ok(p.every((q) => q.x >= TF_DOMAIN[0] && q.x <= TF_DOMAIN[1]));
    p[0].alpha = 0.9;
    assert.notEqual(presetPoints(name)[0].alpha, 0.9);
  }
});

test("histogram bars are log-scaled to the box and the curve spans the domain", () => {
  const bars = histogramBars(new Float32Array([0, 9, 99, 999]), box, [0, 4], [0, 4]);
  assert.equal(bars.length, 4);
  assert.equal(bars[0].height, 0);
  close(bars[3].height, box.height);
  close(bars[3].y, box.top);
  assert.ok(bars[1].height < bars[2].height);
  assert.deepEqual(histogramBars([0, 0], box), []);
  const path = curvePath(pts, box);
  assert.ok(path.startsWith("M10.0,105.0"));
  assert.ok(path.endsWith("L310.0,5.0"));
});

test("colours convert between rgb and hex", () => {
  assert.equal(rgbToHex([1, 0.5, 0]), "#ff8000");
  assert.deepEqual(hexToRgb("#ff8000"), [1, 0.502, 0]);
  assert.equal(hexToRgb("red"), null);
});

test("histogram bins land on their density within the editor's range", () => {
  const bars = histogramBars([1, 1, 1], box, [0, 3], [0, 4]);
  close(bars[0].x, box.left);
  close(bars[2].x + bars[2].width, box.left + 0.75 * box.width);
  const clipped = histogramBars([1, 1], box, [0, 8], [0, 4]);
  assert.equal(clipped.length, 1, "bins beyond the editor's range are not drawn");
  close(clipped[0].width, box.width);
});

test("the editor widens for far points; the histogram range follows the server", () => {
  assert.deepEqual(domainFor(pts), TF_DOMAIN);
  assert.deepEqual(
    domainFor([
      { x: 0, alpha: 0 },
      { x: 5.5, alpha: 1 },
    ]),
    [0, 6],
  );
  assert.deepEqual(histogramRange("iso", presetPoints("cloud")), [0, 3]);
  assert.deepEqual(histogramRange("volume", presetPoints("cloud")), [0, 4]);
  assert.deepEqual(histogramRange("volume", presetPoints("iso-like")), [0, 3]);
});
