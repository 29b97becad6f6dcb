import assert from "node:assert/strict";
import { test } from "node:test";

import { formatBytes, formatElapsed } from "../src/recordings.js";
import { crossedRenderMarks } from "../src/timeline.js";

test("sizes and durations read as people write them", () => {
  assert.equal(formatBytes(512), "512 B");
  assert.equal(formatBytes(1536), "1.5 kB");
  assert.equal(formatBytes(300 * 1024 * 1024), "300 MB");
  assert.equal(formatElapsed(0), "0:00");
  assert.equal(formatElapsed(75.4), "1:15");
});

test("render marks are re-applied when playback passes them, not when seeking", () => {
  const marks = [
    { kind: "render", frame: 5, changes: { sigma_A: 3 } },
    { kind: "sim_params", frame: 6, text: "temperature_K 400" },
    { kind: "render", frame: 9, changes: { mode: "volume" } },
  ];
  assert.deepEqual(crossedRenderMarks(marks, 4, 5), [marks[0]]);
  assert.deepEqual(crossedRenderMarks(marks, 5, 9), [marks[2]]); // frame 5 was already passed
  assert.deepEqual(crossedRenderMarks(marks, 0, 10), [marks[0], marks[2]]);
  assert.deepEqual(crossedRenderMarks(marks, 9, 3), []); // backwards: a seek
  assert.deepEqual(crossedRenderMarks(marks, null, 5), []); // the first frame seen
  assert.deepEqual(crossedRenderMarks(marks, 0, 500), []); // a jump forward: a seek
});
