import assert from "node:assert/strict";
import { test } from "node:test";

import { SeriesTable, toCSV } from "../src/timeseries.js";

test("rows outside the window are dropped and data is laid out for uPlot", () => {
  const t = new SeriesTable(["temperature_K", "target_K"], { windowS: 10 });
  for (let s = 0; s <= 20; s += 2) t.push(1000 + s, { temperature_K: 300 + s, target_K: 300 });
  assert.deepEqual(t.t, [1010, 1012, 1014, 1016, 1018, 1020]);
  const [x, temp, target] = t.data();
  assert.equal(x.length, temp.length);
  assert.equal(temp.at(-1), 320);
  assert.equal(target[0], 300);
  assert.equal(t.last("temperature_K"), 320);
  t.push(1005, { temperature_K: 1 });
  assert.equal(t.length, 6, "rows going back in time are ignored");
  t.setWindow(4, 1020);
  assert.deepEqual(t.t, [1016, 1018, 1020]);
});

test("missing and non-finite values stay empty", () => {
  const t = new SeriesTable(["a", "b"]);
  t.push(1, { a: 1 });
  t.push(2, { a: Number.NaN, b: 2 });
  assert.deepEqual(t.data(), [
    [1, 2],
    [1, null],
    [null, 2],
  ]);
  assert.equal(t.last("a"), 1);
});

test("several tables export as one CSV merged on time", () => {
  const a = new SeriesTable(["temperature_K"]);
  const b = new SeriesTable(["latency_ms"]);
  a.push(10, { temperature_K: 300 });
  a.push(11, { temperature_K: 301.5 });
  b.push(10.5, { latency_ms: 42 });
  b.push(11, { latency_ms: 40 });
  assert.equal(toCSV([a, b]), "time_unix_s,temperature_K,latency_ms\n10.000,300,\n10.500,,42\n11.000,301.5,40\n");
  assert.equal(toCSV([new SeriesTable(["x"])]), "time_unix_s,x\n");
});
