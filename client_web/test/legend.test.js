import assert from "node:assert/strict";
import { test } from "node:test";

import { legendText } from "../src/legend.js";

test("the motion legend says what its unit is and what its ends mean", () => {
  const motion = {
    color_by: "motion",
    ramp: [
      [0, 0, 1],
      [1, 0, 0],
    ],
    low: 1,
    high: 3,
    unit: "γ′",
  };
  const text = legendText(motion);
  assert.equal(text.title, "Motion: warp rate γ′");
  assert.equal(text.low, "1 γ′ at rest");
  assert.equal(text.high, "3 γ′ fast");
  assert.match(text.note, /^γ′: frames of warped time per frame/);
  assert.match(text.note, /Warp \(frames\/Å\)/); // the control that sets it, by its name
});

test("other ramps and swatches keep their plain words", () => {
  const charge = {
    color_by: "charge",
    ramp: [
      [1, 0, 0],
      [0, 0, 1],
    ],
    low: -0.5,
    high: 0.5,
    unit: "e",
  };
  assert.deepEqual(legendText(charge), { title: "Charge", low: "-0.5 e", high: "0.5 e", note: "" });
  assert.equal(legendText({ color_by: "element", entries: [] }).title, "Element");
});
