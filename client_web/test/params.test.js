import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { test } from "node:test";
import { fileURLToPath } from "node:url";

import {
  RENDER_DEFAULTS,
  clampParam,
  diffRender,
  mergeRender,
  shownSpace,
  sigmaFromSlider,
  sliderFromSigma,
} from "../src/params.js";

const here = dirname(fileURLToPath(import.meta.url));

test("the defaults mirror the server's RenderParams (golden state vector)", () => {
  const state = JSON.parse(readFileSync(join(here, "..", "..", "tests", "protocol", "vectors", "state.json"), "utf8"));
  const server = state.message.render_params;
  assert.deepEqual(Object.keys(RENDER_DEFAULTS).sort(), Object.keys(server).sort());
  for (const key of Object.keys(server)) {
    if (key === "sigma_A" || key === "layers") continue; // the vector sets these away from the defaults
    assert.deepEqual(RENDER_DEFAULTS[key], server[key], key);
  }
  assert.deepEqual(RENDER_DEFAULTS.layers, []);
});

test("sigma slider is logarithmic over 0.3-12 A", () => {
  assert.ok(Math.abs(sigmaFromSlider(0) - 0.3) < 1e-12);
  assert.ok(Math.abs(sigmaFromSlider(1) - 12) < 1e-12);
  assert.ok(Math.abs(sigmaFromSlider(0.5) - Math.sqrt(0.3 * 12)) < 1e-12);
  for (const s of [0.3, 1, 1.5, 7.2, 12]) assert.ok(Math.abs(sigmaFromSlider(sliderFromSigma(s)) - s) < 1e-9);
  assert.equal(sliderFromSigma(100), 1);
});

test("merging patches lighting field by field and diff finds changes", () => {
  const a = mergeRender(RENDER_DEFAULTS, { sigma_A: 3, lighting: { ambient: 0.5 } });
  assert.equal(a.lighting.ambient, 0.5);
  assert.equal(a.lighting.diffuse, RENDER_DEFAULTS.lighting.diffuse);
  assert.equal(mergeRender(a, { bogus: 1, mode: null }).mode, "iso");
  assert.deepEqual(Object.keys(diffRender(RENDER_DEFAULTS, a)).sort(), ["lighting", "sigma_A"]);
});

test("values are clamped to the protocol's ranges", () => {
  assert.equal(clampParam("sigma_A", 100), 50);
  assert.equal(clampParam("jpeg_quality", 55.4), 55);
  assert.equal(clampParam("temperature_K", "abc"), null);
  assert.equal(clampParam("frame_interval", 0), 1);
});

test("the carved density's old name shows as Carved", () => {
  assert.equal(shownSpace("warped"), "carved");
  for (const v of ["classical", "geodesic", "carved"]) assert.equal(shownSpace(v), v);
});
