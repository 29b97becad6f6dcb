import { test } from "node:test";
import assert from "node:assert/strict";
import { MAX_LAYERS, describeSelected, moveItem, newLayer, normalizeLayer, normalizeLayers } from "../src/layers.js";
import { decodeHash, encodeHash } from "../src/urlstate.js";
import { RENDER_DEFAULTS, mergeRender } from "../src/params.js";

test("a layer keeps only the fields it sets, clamped to the protocol's ranges", () => {
  assert.deepEqual(normalizeLayer({ name: "lig", selection: " resname LIG ", sigma_A: 100, opacity: 1 }), {
    name: "lig",
    selection: "resname LIG",
    sigma_A: 50,
  });
  assert.deepEqual(normalizeLayer({ selection: "all", visible: false, mode: "volume", opacity: 0.4 }), {
    name: "",
    selection: "all",
    visible: false,
    mode: "volume",
    opacity: 0.4,
  });
  assert.deepEqual(normalizeLayer({ selection: "name CA", mode: "tube", radius_A: 0.8 }), {
    name: "",
    selection: "name CA",
    mode: "tube",
    radius_A: 0.8,
  });
  assert.equal(normalizeLayer({ selection: "all", radius_A: -1 }), null);
  const cloud = normalizeLayer({ selection: "all", transfer_function: [{ x: 2, color: [1, 0, 0], alpha: 0.5 }] });
  assert.deepEqual(cloud.transfer_function, [{ x: 2, color: [1, 0, 0], alpha: 0.5 }]); // kept through edits
  assert.equal(normalizeLayer({ selection: "" }), null);
  assert.equal(normalizeLayer({ selection: "all", sigma_A: "wide" }), null);
  assert.equal(normalizeLayers(Array.from({ length: MAX_LAYERS + 1 }, () => ({ selection: "all" }))), null);
  assert.equal(normalizeLayers([{ selection: "all" }, null]), null);
});

test("reordering, naming and the selection status line", () => {
  assert.deepEqual(moveItem(["a", "b", "c"], 2, 0), ["c", "a", "b"]);
  assert.deepEqual(moveItem(["a", "b"], 0, 5), ["a", "b"]);
  assert.equal(newLayer([{ name: "layer 2" }]).name, "layer 3");
  assert.deepEqual(describeSelected({ count: 1 }), { ok: true, text: "1 atom", position: null });
  assert.equal(describeSelected({ count: 12345, dynamic: true }).text, "12,345 atoms now (follows the frames)");
  const bad = describeSelected({ error: "Unknown selection token: 'protien'", position: 0 });
  assert.equal(bad.ok, false);
  assert.equal(bad.position, 0);
  assert.match(bad.text, /^character 1: Unknown/);
});

test("layers travel in the link", () => {
  const layers = [
    { name: "protein", selection: "protein" },
    { name: "ligand", selection: "resname LIG & co", sigma_A: 0.7, opacity: 0.5 },
  ];
  const render = mergeRender(RENDER_DEFAULTS, { layers });
  const back = decodeHash(encodeHash({ render }));
  assert.deepEqual(back.render.layers, layers);
  assert.deepEqual(decodeHash(encodeHash({ render: mergeRender(RENDER_DEFAULTS, {}) })).render.layers, []);
  const broken = decodeHash("v=1&layers=%5B%7B%22selection%22%3A1%7D");
  assert.deepEqual(broken.render.layers, []);
  assert.ok(broken.invalid.length > 0);
  // whether the link names layers at all: one that does not keeps the session's
  assert.equal(broken.hasLayers, true);
  assert.equal(decodeHash("v=1&iso=0.3").hasLayers, false);
});
