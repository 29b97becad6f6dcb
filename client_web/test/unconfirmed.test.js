import { test } from "node:test";
import assert from "node:assert/strict";

import { RENDER_DEFAULTS, mergeRender } from "../src/params.js";
import { Unconfirmed } from "../src/unconfirmed.js";

const session = (patch) => mergeRender(RENDER_DEFAULTS, patch);
const A = { name: "layer 1", selection: "protein" };
const A6 = { ...A, sigma_A: 0.6 };
const B = { name: "ligand", selection: "resname LIG" };

test("a state from before an edit on its way does not take the edit back", () => {
  const edits = new Unconfirmed();
  assert.deepEqual(edits.over(session({ layers: [B] })).layers, [B]); // nothing sent: the session's
  edits.sent(7, { layers: [A] }); // a layer added
  edits.sent(8, { layers: [A6] }); // its scale typed before the first answer came back
  // a state from before both (another steerer's, say): the page keeps its edits
  assert.deepEqual(edits.over(session({ layers: [B] })).layers, [A6]);
  edits.answered(7); // the layer's own echo: the scale is still on its way
  assert.equal(edits.size, 1);
  assert.deepEqual(edits.over(session({ layers: [A] })).layers, [A6]);
  edits.answered(8);
  assert.equal(edits.size, 0);
  assert.deepEqual(edits.over(session({ layers: [A6] })).layers, [A6]);
  // once answered, another steerer's change shows as it comes
  assert.deepEqual(edits.over(session({ layers: [B] })).layers, [B]);
});

test("edits apply over the session in the order they were sent, nested fields merged", () => {
  const edits = new Unconfirmed();
  edits.sent(1, { lighting: { specular: 0.9 } });
  edits.sent(2, { lighting: { ambient: 0.5 }, sigma_A: 2.0 });
  edits.sent(3, { sigma_A: 3.0 });
  const shown = edits.over(session({ iso_level: 0.4 }));
  assert.equal(shown.lighting.specular, 0.9);
  assert.equal(shown.lighting.ambient, 0.5);
  assert.equal(shown.lighting.diffuse, RENDER_DEFAULTS.lighting.diffuse);
  assert.equal(shown.sigma_A, 3.0);
  assert.equal(shown.iso_level, 0.4); // the session's, which no edit names
  edits.answered(2); // one answer covers every edit sent before it
  assert.deepEqual(edits.items.map((item) => item.seq), [3]);
});

test("a refused edit stops counting, an unsent one never counts, a new connection forgets all", () => {
  const edits = new Unconfirmed();
  edits.sent(null, { sigma_A: 9.0 }); // not connected: nothing will answer it
  assert.equal(edits.size, 0);
  edits.sent(9, { layers: [A] });
  edits.sent(10, { sigma_A: 2.0 });
  assert.equal(edits.refused(4), false); // another message's error
  assert.equal(edits.refused(9), true); // the layer's: the session's list shows again
  assert.deepEqual(edits.over(session({ layers: [B] })).layers, [B]);
  assert.equal(edits.over(session({})).sigma_A, 2.0);
  edits.clear();
  assert.equal(edits.size, 0);
  assert.equal(edits.over(session({ sigma_A: 1.0 })).sigma_A, 1.0);
});
