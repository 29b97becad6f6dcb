// The trajectory timeline of a replay session: frame counter, scrub bar, play/pause, speed and
// loop. It shows only when the session's engine is a replay (`engine.kind`), and sends the
// replay controls the protocol has (seek, speed, loop, pause, resume).

import { $, setText, throttle } from "./dom.js";

const SEEK_MS = 120;

/** Render-change marks passed when the replay moved from frame `from` to `to` (playing forward). */
export function crossedRenderMarks(marks, from, to) {
  if (from === null || to <= from || to - from > 50) return []; // a seek, not playback
  return marks.filter((m) => m.kind === "render" && m.changes && m.frame > from && m.frame <= to);
}

/** A replay apart from how it plays: its speed and loop change as it is steered, the rest
 * (and its steering marks) only with the replay itself. */
export function replayIdentity(engine) {
  const { playback, seq, ...replay } = engine ?? {};
  return JSON.stringify(replay);
}

export class Timeline {
  constructor({ onControl, onApplyRender = () => {} }) {
    this.onControl = onControl;
    this.onApplyRender = onApplyRender;
    this.marks = [];
    this.lastFrame = null;
    this.markBox = $("tl-marks");
    this.apply = $("tl-apply");
    this.root = $("timeline");
    this.scrub = $("tl-scrub");
    this.play = $("tl-play");
    this.frame = $("tl-frame");
    this.speed = $("tl-speed");
    this.loop = $("tl-loop");
    this.nFrames = 0;
    this.playback = null;
    this.paused = false;
    this.steering = true;
    this.ended = false;
    this.scrubbing = false;
    this.seekSoon = throttle(() => this.seek(), SEEK_MS);
    this.scrub.addEventListener("input", () => {
      this.scrubbing = true;
      this.showFrame(Number(this.scrub.value));
      this.seekSoon();
    });
    this.scrub.addEventListener("change", () => {
      this.seekSoon.cancel();
      this.seek();
      this.scrubbing = false;
    });
    this.play.addEventListener("click", () => this.onControl(this.paused ? "resume" : "pause", {}, "play"));
    this.speed.addEventListener("change", () => this.onControl("speed", { speed: Number(this.speed.value) }, "speed"));
    this.loop.addEventListener("change", () => this.onControl("loop", { loop: this.loop.checked }, "loop"));
    // the view's status line (the HUD) sits above the bar, however tall it wraps
    new ResizeObserver(() => this.makeRoom()).observe(this.root);
  }

  makeRoom() {
    const space = this.root.hidden ? 0 : this.root.offsetHeight + 10;
    this.root.parentElement.style.setProperty("--timeline-space", `${space}px`);
  }

  seek() {
    this.onControl("seek", { frame: Number(this.scrub.value) }, `seek ${this.scrub.value}`);
  }

  /** Show the timeline for a replay engine, hide it for anything else. */
  setEngine(engine) {
    const replay = engine?.kind === "replay" && engine.n_frames > 0;
    this.root.hidden = !replay;
    document.body.classList.toggle("has-timeline", replay);
    this.makeRoom();
    this.playback = (replay && engine.playback) || null;
    if (!replay) return;
    this.nFrames = engine.n_frames;
    this.scrub.max = String(Math.max(0, this.nFrames - 1));
    if (this.playback) this.showPlayback(this.playback); // its speed and loop as they are
    // the status may have come first (joining a paused or finished replay): draw it again
    // now that the range is known
    const frame = this.lastFrame ?? 0;
    if (!this.scrubbing) this.scrub.value = String(frame);
    this.showFrame(frame);
  }

  /** Steering marks of a recorded run: one button per action at its frame; a click seeks there. */
  setMarks(marks) {
    this.marks = marks ?? [];
    const last = Math.max(1, this.nFrames - 1);
    this.markBox.replaceChildren(
      ...this.marks.map((m) => {
        const b = document.createElement("button");
        b.type = "button";
        b.className = `tl-mark tl-mark-${m.kind}`;
        b.style.left = `${(100 * Math.min(m.frame, last)) / last}%`;
        b.dataset.frame = String(m.frame);
        b.title = `step ${m.step}: ${m.text}`;
        b.setAttribute("aria-label", `frame ${m.frame + 1}, step ${m.step}: ${m.text}`);
        b.addEventListener("click", () => this.onControl("seek", { frame: m.frame }, `seek to ${m.text}`));
        return b;
      }),
    );
    this.apply.parentElement.hidden = !this.marks.some((m) => m.kind === "render");
  }

  /** The session's simulation status: a replay's step is its frame index. */
  update(sim) {
    const frame = sim.step ?? 0;
    if (this.apply.checked && sim.state !== "paused") {
      for (const m of crossedRenderMarks(this.marks, this.lastFrame, frame)) this.onApplyRender(m.changes);
    }
    this.lastFrame = frame;
    this.paused = sim.state === "paused";
    // a replay that has gone (it ended, failed or was stopped) plays nothing: its controls
    // rest until a simulation runs in the session again
    const ended = sim.state === "disconnected" || sim.state === "waiting";
    setText(this.play, this.paused || ended ? "Play" : "Pause");
    this.play.setAttribute("aria-pressed", String(!this.paused && !ended));
    if (ended !== this.ended) {
      this.ended = ended;
      this.applyDisabled();
    }
    if (!this.scrubbing) {
      this.scrub.value = String(sim.step ?? 0);
      this.showFrame(sim.step ?? 0);
    }
  }

  /** An acknowledged replay control: keep speed and loop as the replay has them. The engine's
   * playback, which the session keeps from the acknowledgements it can take, says so where
   * there is one (a choice the replay refused goes back too); the acknowledgement itself only
   * for an engine without one. */
  acknowledged(applied) {
    this.showPlayback(this.playback ?? applied ?? {});
  }

  showPlayback({ speed, loop }) {
    if (typeof speed === "number" && speed > 0) this.showSpeed(speed);
    if (typeof loop === "boolean") this.loop.checked = loop;
  }

  /** Select `speed`, adding it to the list where the list lacks it (a script's 3x). */
  showSpeed(speed) {
    const value = String(speed);
    const options = [...this.speed.options];
    if (!options.some((o) => o.value === value)) {
      const option = document.createElement("option");
      option.value = value;
      option.textContent = `${value}×`;
      this.speed.add(option, options.find((o) => Number(o.value) > speed) ?? null);
    }
    this.speed.value = value;
  }

  showFrame(index) {
    setText(this.frame, `frame ${index + 1} / ${this.nFrames}${this.ended ? " · ended" : ""}`);
  }

  /** Whether this page may steer (a read-only viewer's timeline only shows). */
  setDisabled(disabled) {
    this.steering = !disabled;
    this.applyDisabled();
  }

  applyDisabled() {
    const off = !this.steering || this.ended;
    for (const node of [this.scrub, this.play, this.speed, this.loop, this.apply]) node.disabled = off;
    for (const node of this.markBox.children) node.disabled = off;
    this.play.title = this.ended ? "the replay has ended: open it again to play it" : "";
  }
}
