import assert from "node:assert/strict";
import { test } from "node:test";

import { MOVIE_MAX_S, movieLabel } from "../src/movies.js";
import { pageInstance, runningWork } from "../src/work.js";

class Storage {
  constructor() {
    this.items = new Map();
  }
  getItem(k) {
    return this.items.get(k) ?? null;
  }
  setItem(k, v) {
    this.items.set(k, String(v));
  }
}

test("a tab keeps its instance across reloads; another tab gets its own", () => {
  const tab = new Storage();
  let n = 0;
  const random = () => `0000000${++n}-aaaa`;
  const first = pageInstance(tab, random);
  assert.equal(pageInstance(tab, random), first); // a reload: the same page
  assert.notEqual(pageInstance(new Storage(), random), first); // another tab
  tab.setItem("scalesteer.instance", "x y"); // not one of ours
  assert.match(pageInstance(tab, random), /^page-/);
  assert.match(pageInstance(null, random), /^page-/); // no storage at all
});

const recording = { id: "r1", session: "default", state: "recording", frames: 12, bytes: 2048, owner: "page-a" };
const movie = (m, extra = {}) => ({
  id: "j1",
  kind: "live",
  session: "default",
  state: "running",
  owner: "page-b",
  progress: { done: 3, total: 9 },
  movie: { taken: 9, max_s: 600, recording: true, ...m },
  ...extra,
});

test("running work is listed with who owns it and what ends it", () => {
  const job = {
    id: "j2",
    kind: "trajectory",
    state: "queued",
    owner: null,
    progress: { done: 0, total: 0 },
    stage: null,
  };
  const finished = { ...recording, id: "r0", state: "finished" };
  const rows = runningWork([movie({}), job], [recording, finished], "page-a");
  assert.deepEqual(
    rows.map((r) => [r.id, r.kind, r.mine, r.actions.map((a) => `${a.text} ${a.method} ${a.path}`)]),
    [
      ["r1", "recording", true, ["Stop POST /api/recordings/r1/stop"]],
      // stopping never DELETEs: a movie or job that ended meanwhile keeps its output
      ["j1", "movie", false, ["Stop POST /api/jobs/j1/cancel", "Cancel DELETE /api/jobs/j1"]],
      ["j2", "job", false, ["Cancel POST /api/jobs/j2/cancel"]],
    ],
  );
  assert.equal(rows[0].label, "recording default · 12 frames · 2.0 kB · this page");
  assert.equal(rows[1].label, "movie of default · 9 frames taken, 3 rendered · another page");
  assert.equal(rows[2].label, "trajectory job · queued");
  const stopped = runningWork([movie({ recording: false }, { owner: null })], [], "page-a")[0];
  assert.equal(stopped.label, "movie of default · rendering 3 / 9 · kept running");
  assert.deepEqual(
    stopped.actions.map((a) => a.text),
    ["Cancel"],
  ); // a stopped movie is finishing: only cancelling is left
});

test("the movie button says how long it records and, after the stop, how far it saves", () => {
  assert.equal(movieLabel(movie({}), 75), "Stop recording 1:15 / 10:00");
  assert.equal(movieLabel(null, 2), `Stop recording 0:02 / ${Math.floor(MOVIE_MAX_S / 60)}:00`);
  assert.equal(movieLabel(movie({ recording: false }), 0), "Saving… 3 / 9 frames");
  assert.equal(movieLabel(movie({ recording: false, eta_s: 75 }), 0), "Saving… 3 / 9 frames, about 1:15 left");
});
