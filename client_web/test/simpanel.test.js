import assert from "node:assert/strict";
import { test } from "node:test";

import { bound } from "../src/simpanel.js";

test("a range's whole-number ends read as numbers, not exponents", () => {
  assert.equal(bound(1_000_000, 4), "1,000,000");
  assert.equal(bound(1, 3), "1");
  assert.equal(bound(0.01, 3), "0.01");
  assert.equal(bound(2.5, 4), "2.5");
  assert.equal(bound(1e-4, 3), "1.00e-4");
});
