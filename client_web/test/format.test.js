import assert from "node:assert/strict";
import { test } from "node:test";

import { integer, milliseconds, nanoseconds, observableLabel, position, sig } from "../src/format.js";

test("simulation time shows in ns, numbers stay readable", () => {
  assert.equal(nanoseconds(2468.5), "2.4685 ns");
  assert.equal(nanoseconds(Number.NaN), "–");
  assert.equal(integer(1234567.4), "1,234,567");
  assert.equal(milliseconds(12.34), "12.3 ms");
  assert.equal(milliseconds(1234.5), "1235 ms");
  assert.equal(sig(0.000012345, 3), "1.23e-5");
  assert.equal(sig(-850.0123, 4), "-850");
  assert.equal(position([1, -2.5, 3.14159]), "(1.00, -2.50, 3.14) Å");
});

test("observable keys read as names with units", () => {
  assert.equal(observableLabel("temperature_K"), "temperature (K)");
  assert.equal(observableLabel("potential_kJmol"), "potential (kJ/mol)");
  assert.equal(observableLabel("box_volume_nm3"), "box volume (nm³)");
  assert.equal(observableLabel("rmsd"), "rmsd");
});
