import assert from "node:assert/strict";
import { test } from "node:test";

import { LatencyTracker, RateMeter, clockSample } from "../src/latency.js";

test("latency is measured once, from the message an image reflects", () => {
  const lat = new LatencyTracker();
  lat.sent(1, "view", 1000);
  lat.sent(2, "view", 1010);
  lat.sent(3, "render_params", 1020);
  assert.equal(lat.shown(null, 1030), null);
  assert.deepEqual(lat.shown(2, 1060), { latency: 50, kind: "view" });
  assert.equal(lat.shown(2, 1070), null, "a second image for the same ref is not a sample");
  assert.equal(lat.shown(1, 1080), null, "older refs were settled by the newer image");
  assert.deepEqual(lat.shown(3, 1100), { latency: 80, kind: "render_params" });
  assert.deepEqual(lat.summary(), { count: 2, last: 80, mean: 65, p95: 80 });
});

test("pending entries are bounded and reset on reconnect", () => {
  const lat = new LatencyTracker({ maxPending: 3, window: 2 });
  for (let s = 1; s <= 5; s++) lat.sent(s, "view", s);
  assert.deepEqual([...lat.pending.keys()], [3, 4, 5]);
  lat.shown(3, 10);
  lat.shown(4, 10);
  lat.shown(5, 10);
  assert.equal(lat.summary().count, 2, "the sample window is bounded");
  lat.sent(6, "view", 0);
  lat.reset();
  assert.equal(lat.shown(6, 1), null);
});

test("rate meter counts events per second over its window", () => {
  const m = new RateMeter(1000);
  for (let t = 0; t <= 1000; t += 100) m.tick(t);
  assert.ok(Math.abs(m.rate(1000) - 11) < 1e-9);
  assert.equal(m.rate(5000), 0);
});

test("ping/pong gives round trip and clock offset", () => {
  const s = clockSample(100.0, 160.5, 101.0);
  assert.equal(s.rtt, 1);
  assert.equal(s.offset, 60);
});
