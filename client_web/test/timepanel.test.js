import assert from "node:assert/strict";
import { test } from "node:test";

import { RENDER_DEFAULTS } from "../src/params.js";
import { displayLag } from "../src/timepanel.js";

test("the display lag is half the window for a centred kernel, none for a causal one", () => {
  const r = { ...RENDER_DEFAULTS, time_window: 16 };
  assert.equal(displayLag(r, false), 0); // auto on a live run: causal
  assert.equal(displayLag(r, true), 7); // auto on a replay: centred
  assert.equal(displayLag({ ...r, time_kernel: "centred" }, false), 7);
  assert.equal(displayLag({ ...r, time_kernel: "causal" }, true), 0);
});
