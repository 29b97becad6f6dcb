import assert from "node:assert/strict";
import { test } from "node:test";

// The few DOM parts the timeline touches, enough to drive it without a browser.
class FakeNode {
  constructor() {
    this.textContent = "";
    this.value = "";
    this.max = "";
    this.hidden = false;
    this.checked = false;
    this.children = [];
    this.style = { setProperty() {} };
    this.parentElement = this;
    this.offsetHeight = 40;
    this.dataset = {};
    this.options = [];
  }
  add(option, before) {
    const at = this.options.indexOf(before);
    this.options.splice(at < 0 ? this.options.length : at, 0, option);
  }
  addEventListener() {}
  setAttribute() {}
  replaceChildren(...nodes) {
    this.children = nodes;
  }
}

const nodes = new Map();
globalThis.document = {
  getElementById: (id) => nodes.get(id) ?? nodes.set(id, new FakeNode()).get(id),
  createElement: () => new FakeNode(),
  body: { classList: { toggle() {} } },
};
globalThis.ResizeObserver = class {
  observe() {}
};

const { Timeline } = await import("../src/timeline.js");

test("joining a paused replay shows its frame once the engine's length is known", () => {
  const timeline = new Timeline({ onControl: () => {} });
  // the status comes first: frame 5 of a replay whose length is not known yet
  timeline.update({ step: 4, state: "paused" });
  timeline.setEngine({ kind: "replay", n_frames: 12 });
  assert.equal(nodes.get("tl-frame").textContent, "frame 5 / 12");
  assert.equal(nodes.get("tl-scrub").value, "4");
  assert.equal(nodes.get("tl-play").textContent, "Play");
});

test("a replay's speed and loop show as its engine says, also for a viewer who joins later", () => {
  const timeline = new Timeline({ onControl: () => {} });
  timeline.setEngine({ kind: "replay", n_frames: 12, playback: { speed: 2, loop: true } });
  assert.equal(nodes.get("tl-speed").value, "2");
  assert.equal(nodes.get("tl-loop").checked, true);
  timeline.setEngine({ kind: "replay", n_frames: 12, playback: { speed: 0.5, loop: false } });
  assert.equal(nodes.get("tl-speed").value, "0.5");
  assert.equal(nodes.get("tl-loop").checked, false);
});

test("a replay that has gone rests its controls and says so, until a simulation runs again", () => {
  const timeline = new Timeline({ onControl: () => {} });
  timeline.setDisabled(false); // a steerer's page
  timeline.setEngine({ kind: "replay", n_frames: 12 });
  timeline.update({ step: 6, state: "running" });
  assert.equal(nodes.get("tl-play").textContent, "Pause");
  assert.equal(nodes.get("tl-play").disabled, false);
  timeline.update({ step: 6, state: "disconnected" });
  assert.equal(nodes.get("tl-play").textContent, "Play");
  for (const id of ["tl-play", "tl-scrub", "tl-speed", "tl-loop"]) assert.equal(nodes.get(id).disabled, true, id);
  assert.equal(nodes.get("tl-frame").textContent, "frame 7 / 12 · ended");
  timeline.update({ step: 0, state: "running" });
  assert.equal(nodes.get("tl-play").disabled, false);
  assert.equal(nodes.get("tl-frame").textContent, "frame 1 / 12");
});

test("a read-only viewer's timeline stays at rest when its replay runs again", () => {
  const timeline = new Timeline({ onControl: () => {} });
  timeline.setEngine({ kind: "replay", n_frames: 12 });
  timeline.setDisabled(true);
  timeline.update({ step: 2, state: "disconnected" });
  timeline.update({ step: 3, state: "running" });
  assert.equal(nodes.get("tl-play").disabled, true);
  timeline.setDisabled(false);
  assert.equal(nodes.get("tl-play").disabled, false);
});
