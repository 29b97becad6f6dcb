// The dashboard's RANGES and ENUMS against the protocol's JSON Schema (docs/protocol.schema.json,
// written by `python -m protocol.schema` and held current by tests/protocol/test_schema.py), both
// ways: every range and choice the dashboard has is the protocol's, and every bounded number or
// choice of the render and simulation parameters is in the dashboard's tables or listed below.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { test } from "node:test";
import { fileURLToPath } from "node:url";

import { ENUMS, RANGES, clampParam } from "../src/params.js";

const here = dirname(fileURLToPath(import.meta.url));
const schema = JSON.parse(readFileSync(join(here, "..", "..", "docs", "protocol.schema.json"), "utf8"));
const defs = schema.$defs;

/** Fields with bounds or choices that the dashboard's tables leave out, and why. */
const NOT_IN_TABLES = {
  transfer_function: "points edited on the transfer-function canvas (transfer.js)",
  uniform_color: "a colour input, channels 0..1",
  background: "a colour input, channels 0..1",
  layers: "each layer's own fields (layers.js)",
  seq: "SimParams' sequence number, not a parameter",
};

function resolve(prop) {
  return prop.$ref ? defs[prop.$ref.split("/").pop()] : prop;
}

/** A field's own schema: `X | None` unwrapped to X. */
function scalar(prop) {
  const p = resolve(prop);
  const values = (p.anyOf ?? []).filter((x) => x.type !== "null");
  return values.length === 1 ? values[0] : p;
}

/** The schema of the field a dashboard key names (`lighting.x`: Lighting's; `projection`: the camera's). */
function field(key) {
  if (key.startsWith("lighting.")) return scalar(defs.Lighting.properties[key.slice("lighting.".length)]);
  if (key === "projection") return scalar(defs.Camera.properties.projection);
  const prop = defs.RenderParams.properties[key] ?? defs.SimParams.properties[key];
  assert.ok(prop, `${key}: no such render or simulation parameter in the schema`);
  return scalar(prop);
}

/** Whether a schema carries a numeric bound or a choice anywhere within it. */
function bounded(prop, seen = new Set()) {
  if (prop === undefined || seen.has(prop)) return false;
  seen.add(prop);
  const p = resolve(prop);
  if (p.enum || ["minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"].some((b) => b in p)) return true;
  const inner = [...(p.anyOf ?? []), ...(p.prefixItems ?? []), p.items, ...Object.values(p.properties ?? {})];
  return inner.some((x) => bounded(x, seen));
}

test("every dashboard range is the protocol's (open ends nudged inside)", () => {
  for (const [key, [lo, hi]] of Object.entries(RANGES)) {
    const s = field(key);
    assert.ok(s.type === "number" || s.type === "integer", `${key}: ${s.type} is not a number`);
    if ("minimum" in s) assert.equal(lo, s.minimum, `${key} minimum`);
    else assert.ok("exclusiveMinimum" in s && lo > s.exclusiveMinimum && lo < hi, `${key}: lower end ${lo}`);
    if ("maximum" in s) assert.equal(hi, s.maximum, `${key} maximum`);
    else assert.ok("exclusiveMaximum" in s && hi < s.exclusiveMaximum && hi > lo, `${key}: upper end ${hi}`);
    const between = clampParam(key, lo + 0.4 * Math.min(1, hi - lo));
    assert.equal(Number.isInteger(between), s.type === "integer", `${key}: rounded as the schema's ${s.type}`);
  }
});

test("every dashboard choice list is the protocol's", () => {
  for (const [key, values] of Object.entries(ENUMS)) {
    const s = field(key);
    assert.ok(s.enum, `${key}: no choices in the schema`);
    assert.deepEqual([...values].sort(), [...s.enum].sort(), key);
  }
});

test("every bounded render and simulation parameter is known to the dashboard", () => {
  const fields = [
    ...Object.entries(defs.RenderParams.properties).filter(([k]) => k !== "lighting"),
    ...Object.entries(defs.Lighting.properties).map(([k, v]) => [`lighting.${k}`, v]),
    ...Object.entries(defs.SimParams.properties),
  ];
  const unknown = fields
    .filter(([key, prop]) => bounded(prop) && !(key in RANGES) && !(key in ENUMS) && !(key in NOT_IN_TABLES))
    .map(([key]) => key);
  assert.deepEqual(unknown, [], `parameters with bounds or choices the dashboard does not know: ${unknown}`);
  for (const key of Object.keys(NOT_IN_TABLES)) {
    assert.ok(key in defs.RenderParams.properties || key in defs.SimParams.properties, `${key} is listed but gone`);
  }
});
