// The golden vectors of tests/protocol/vectors/ decode here exactly as in Python.

import assert from "node:assert/strict";
import { readFileSync, readdirSync } from "node:fs";
import { dirname, join } from "node:path";
import { test } from "node:test";
import { fileURLToPath } from "node:url";

import { encode as pack } from "@msgpack/msgpack";

import { WireArray, WireError, decodeArray, decodeMessage, encodeMessage } from "../src/wire.js";

const here = dirname(fileURLToPath(import.meta.url));
const vectors = join(here, "..", "..", "tests", "protocol", "vectors");
const names = readdirSync(vectors)
  .filter((f) => f.endsWith(".msgpack"))
  .map((f) => f.slice(0, -".msgpack".length))
  .sort();

function load(name) {
  return {
    raw: new Uint8Array(readFileSync(join(vectors, `${name}.msgpack`))),
    sidecar: JSON.parse(readFileSync(join(vectors, `${name}.json`), "utf8")),
  };
}

function hex(bytes) {
  return Buffer.from(bytes).toString("hex");
}

/** Compare a decoded value with the sidecar's JSON form ({"$bytes": hex} for binary). */
function assertMatches(actual, expected, path, arrays) {
  if (actual instanceof WireArray) {
    const field = path.split(".").pop();
    const spec = arrays[field];
    assert.ok(spec, `${path}: decoded as an array but the sidecar lists no array ${field}`);
    assert.equal(actual.dtype, spec.dtype, `${path}.dtype`);
    assert.deepEqual(actual.shape, spec.shape, `${path}.shape`);
    assert.deepEqual(Array.from(actual.values, Number), spec.values, `${path}.values`);
    assert.equal(hex(actual.toWire().data), expected.data.$bytes, `${path}.data`);
    return;
  }
  if (expected && typeof expected === "object" && "$bytes" in expected) {
    assert.ok(actual instanceof Uint8Array, `${path}: expected binary`);
    assert.equal(hex(actual), expected.$bytes, path);
    return;
  }
  if (Array.isArray(expected)) {
    assert.ok(Array.isArray(actual), `${path}: expected a list`);
    assert.equal(actual.length, expected.length, `${path}: length`);
    expected.forEach((e, i) => assertMatches(actual[i], e, `${path}[${i}]`, arrays));
    return;
  }
  if (expected && typeof expected === "object") {
    assert.deepEqual(Object.keys(actual).sort(), Object.keys(expected).sort(), `${path}: keys`);
    for (const key of Object.keys(expected)) assertMatches(actual[key], expected[key], `${path}.${key}`, arrays);
    return;
  }
  assert.equal(actual, expected, path);
}

test("there is a golden vector for every message type", () => {
  for (const type of ["hello", "welcome", "image", "state", "stats", "picked", "params_ack", "error", "pong"]) {
    assert.ok(names.includes(type), `missing vector ${type}`);
  }
});

for (const name of names) {
  test(`golden vector ${name} decodes to its sidecar`, () => {
    const { raw, sidecar } = load(name);
    const message = decodeMessage(raw);
    assert.equal(message.type, sidecar.message.type);
    assertMatches(message, sidecar.message, name, sidecar.arrays);
    for (const field of Object.keys(sidecar.arrays)) {
      assert.ok(message[field] instanceof WireArray, `${name}.${field} is a checked array`);
    }
  });

  test(`golden vector ${name} survives an encode/decode round trip`, () => {
    const { raw } = load(name);
    const once = decodeMessage(raw);
    const twice = decodeMessage(encodeMessage(once));
    assert.deepEqual(twice, once);
  });
}

test("an image's JPEG bytes and histogram come out as typed arrays", () => {
  const histogram = WireArray.from(new Float32Array([0, 5, 2.5]), "<f4");
  const raw = encodeMessage({
    type: "image",
    frame_id: 3,
    format: "jpeg",
    data: new Uint8Array([1, 2]),
    width: 2,
    height: 1,
    histogram,
  });
  const msg = decodeMessage(raw);
  assert.ok(msg.data instanceof Uint8Array);
  assert.ok(msg.histogram.values instanceof Float32Array);
  assert.deepEqual(Array.from(msg.histogram.values), [0, 5, 2.5]);
});

test("inconsistent arrays are refused before allocation", () => {
  const bad = (arr, code = "invalid_message") =>
    assert.throws(
      () => decodeArray(arr, "image.histogram", ["<f4", 1], 1000),
      (e) => e instanceof WireError && e.code === code,
    );
  bad({ dtype: "<f4", shape: [3], data: new Uint8Array(8) }); // byte length
  bad({ dtype: "<f2", shape: [2], data: new Uint8Array(4) }); // dtype not allowed
  bad({ dtype: "<i4", shape: [2], data: new Uint8Array(8) }); // wrong dtype for the field
  bad({ dtype: "<f4", shape: [2, 1], data: new Uint8Array(8) }); // wrong rank
  bad({ dtype: "<f4", shape: [-1], data: new Uint8Array(0) }); // negative
  bad({ dtype: "<f4", shape: [1e12], data: new Uint8Array(4) }, "too_large"); // declared huge
  bad([1, 2, 3]); // a list is not an array
});

test("malformed messages raise coded errors", () => {
  assert.throws(
    () => decodeMessage(new Uint8Array([0xc1])),
    (e) => e.code === "invalid_message",
  );
  assert.throws(() => decodeMessage(pack([1, 2])), /must be a map/);
  assert.throws(
    () => decodeMessage(pack({ seq: 1 })),
    (e) => e.path === "type",
  );
  assert.throws(
    () => decodeMessage(pack({ type: "pong", ref: -1 })),
    (e) => e.path === "pong.ref",
  );
  assert.throws(
    () => decodeMessage(new Uint8Array(10), { maxBytes: 4 }),
    (e) => e.code === "too_large",
  );
});

test("encoding omits null and undefined fields", () => {
  const msg = decodeMessage(encodeMessage({ type: "pick", x: 3, y: 4, seq: null, extra: undefined }));
  assert.deepEqual(msg, { type: "pick", x: 3, y: 4 });
});
