import assert from "node:assert/strict";
import { test } from "node:test";

import { overlaps, placeLabels } from "../src/labels.js";

const pairs = (rects) => rects.flatMap((a, i) => rects.slice(i + 1).map((b) => [a, b]));

test("labels of atoms close together and their measurement do not cover each other", () => {
  // three picked atoms a few pixels apart (side chains seen end on) and the angle's label
  const items = [
    { anchor: [200, 150], w: 70, h: 16 },
    { anchor: [206, 153], w: 70, h: 16 },
    { anchor: [203, 158], w: 70, h: 16 },
    { anchor: [206, 153], w: 90, h: 16 },
  ];
  const markers = items.slice(0, 3).map(({ anchor: [x, y] }) => ({ x: x - 8, y: y - 8, w: 16, h: 16 }));
  const rects = placeLabels(items, { w: 640, h: 480 }, { obstacles: markers });
  for (const [a, b] of pairs(rects)) assert.ok(!overlaps(a, b), `${JSON.stringify(a)} covers ${JSON.stringify(b)}`);
  for (const r of rects) for (const m of markers) assert.ok(!overlaps(r, m), "a label covers an atom's marker");
  assert.equal(rects[0].moved, false); // the first keeps its place beside its atom
  assert.ok(rects.slice(1).some((r) => r.moved));
});

test("a label stays in the view at its edge", () => {
  const [r] = placeLabels([{ anchor: [630, 5], w: 80, h: 16 }], { w: 640, h: 480 });
  assert.ok(r.x >= 0 && r.x + r.w <= 640 && r.y >= 0 && r.y + r.h <= 480, JSON.stringify(r));
});
