import assert from "node:assert/strict";
import { test } from "node:test";

import { legendText } from "../src/legend.js";
import { sessionColourApplies } from "../src/params.js";

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

test("the session's colouring applies unless everything drawn is volume", () => {
  assert.equal(sessionColourApplies({ mode: "iso", layers: [] }), true);
  assert.equal(sessionColourApplies({ mode: "volume", layers: [] }), false);
  const protein = { name: "protein", selection: "protein", visible: true, mode: null };
  const ligand = { name: "ligand", selection: "resname LIG", visible: true, mode: "licorice" };
  assert.equal(sessionColourApplies({ mode: "volume", layers: [protein] }), false);
  assert.equal(sessionColourApplies({ mode: "volume", layers: [protein, ligand] }), true);
  // a layer with its own colouring does not take the session's; a hidden one draws nothing
  assert.equal(sessionColourApplies({ mode: "volume", layers: [protein, { ...ligand, color_by: "chain" }] }), false);
  assert.equal(sessionColourApplies({ mode: "volume", layers: [protein, { ...ligand, visible: false }] }), false);
  assert.equal(sessionColourApplies({ mode: "iso", layers: [{ ...protein, mode: "volume" }] }), false);
});
