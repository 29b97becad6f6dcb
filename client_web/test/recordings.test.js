import assert from "node:assert/strict";
import { test } from "node:test";

import { jobResult } from "../src/api.js";
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

test("a finished job's warning reaches the page with its output", async () => {
  const answers = [
    { state: "running", progress: { done: 3, total: 20 } },
    { state: "done", partial: true, warning: "frames.xtc: 20 readable frame(s) of the 40 it should hold" },
  ];
  const fetchImpl = async (url) =>
    url.endsWith("/result")
      ? new Response(new Uint8Array([1, 2, 3]), { status: 200 })
      : new Response(JSON.stringify(answers.shift()), { status: 200 });
  const warnings = [];
  const onWarning = (w) => warnings.push(w);
  const blob = await jobResult({ token: "t", job: "j1", fetchImpl, sleep: async () => {}, onWarning });
  assert.equal(blob.size, 3);
  assert.deepEqual(warnings, ["frames.xtc: 20 readable frame(s) of the 40 it should hold"]);
});

test("a structure alone opens without a trajectory field; the structure goes first", async () => {
  const { formOf, openReplay, replayFiles } = await import("../src/api.js");
  const gro = new File(["x"], "box.gro");
  const xtc = new File(["y"], "run.xtc");
  assert.deepEqual(replayFiles([xtc, gro]), { topology: gro, trajectory: [xtc] });
  assert.deepEqual(replayFiles([gro]), { topology: gro, trajectory: [] });
  assert.throws(() => replayFiles([xtc]), /^Error: run\.xtc: a trajectory holds coordinates only/);
  const alone = formOf({ topology: gro, trajectory: [], fps: 30 });
  assert.deepEqual([...alone.keys()], ["topology", "fps"]); // no trajectory="[]"
  const sent = [];
  const fetchImpl = async (url, init) => {
    sent.push([...init.body.entries()].map(([k, v]) => [k, typeof v === "string" ? v : v.name]));
    return new Response(JSON.stringify({ session: "replay-box" }), { status: 201 });
  };
  assert.equal((await openReplay({ token: "t", files: [xtc, gro], fetchImpl })).session, "replay-box");
  assert.deepEqual(sent[0], [
    ["topology", "box.gro"],
    ["trajectory", "run.xtc"],
    ["fps", "30"],
  ]);
});
