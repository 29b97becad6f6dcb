import assert from "node:assert/strict";
import { test } from "node:test";
import { applyRoster } from "../src/roster.js";

const a = { client_id: "c1", role: "steerer" };
const b = { client_id: "c2", role: "viewer" };
const sim = { client_id: "c3", role: "simulation" };

test("the whole list replaces, deltas add and remove", () => {
  let r = applyRoster([], { clients: [a] });
  assert.deepEqual(r, [a]);
  r = applyRoster(r, { joined: [b, sim] });
  assert.deepEqual(r.map((c) => c.client_id), ["c3", "c1", "c2"]);
  r = applyRoster(r, { left: ["c1"] });
  assert.deepEqual(r.map((c) => c.client_id), ["c3", "c2"]);
  r = applyRoster(r, { joined: [b] });
  assert.equal(r.length, 2, "a client id is never listed twice");
  r = applyRoster(r, { left: ["c2"], joined: [{ client_id: "c4", role: "viewer" }] });
  assert.deepEqual(r.map((c) => c.client_id), ["c3", "c4"]);
});
