// The simulation panel: status, run control and parameters. Each change shows "pending" until
// the server acknowledges the step at which the simulation applied it.

import { $, el, isBusy, setText } from "./dom.js";
import { integer, nanoseconds, observableLabel, sig } from "./format.js";
import { clampParam } from "./params.js";
import { FAILED, PENDING } from "./steering.js";

export const SIM_FIELDS = ["temperature_K", "timestep_fs", "friction_per_ps", "frame_interval"];

export class SimPanel {
  constructor({ onControl, onParam, onInvalid }) {
    Object.assign(this, { onControl, onParam, onInvalid });
    this.sim = { state: "waiting", step: 0, time_ps: 0, steps_per_s: 0, n_atoms: 0, engine: "", observables: {} };
    this.play = $("sim-play");
    this.stepBtn = $("sim-step-btn");
    this.nSteps = $("sim-nsteps");
    this.reset = $("sim-reset");
    this.inputs = new Map(SIM_FIELDS.map((key) => [key, document.querySelector(`[data-param="${key}"]`)]));
    this.disabled = false;
    this.engine = null;
    this.params = {}; // the session's simulation parameters (updateParams)
    // key -> {value, seq} of the value sent last and not yet answered: a field restored while
    // it is in flight shows it, not the session's older value
    this.inFlight = new Map();
    this.bind();
    this.updateStatus(this.sim);
  }

  bind() {
    this.play.addEventListener("click", () => this.togglePlay());
    this.stepBtn.addEventListener("click", () => this.step());
    this.reset.addEventListener("click", () => {
      if (window.confirm("Reset the simulation to its initial state?")) this.onControl("reset", {}, "reset");
    });
    for (const [key, input] of this.inputs) {
      input.addEventListener("change", () => {
        if (input.value.trim() === "") return;
        const range = this.engine?.params?.[key];
        const raw = Number(input.value);
        if (range && Number.isFinite(raw) && (raw < range.min || raw > range.max)) {
          this.onInvalid(`${key} ${input.value} is outside ${rangeText(this.engine, range)}; not sent`);
          // the field shows the value in effect again, and its line says this one was not sent
          this.showAck(key, { state: "failed", text: `${input.value} not sent: outside the range` });
          this.restoreParam(key);
          return;
        }
        const value = clampParam(key, input.value);
        if (value === null || Number(input.value) !== value) {
          this.onInvalid(`${key}: ${input.value} is outside the allowed range; sent ${value}`);
          if (value === null) return;
          input.value = String(value);
        }
        this.inFlight.set(key, { value, seq: undefined });
        this.onParam(key, value);
      });
    }
  }

  togglePlay() {
    if (this.sim.state === "paused") this.onControl("resume", {}, "resume");
    else this.onControl("pause", {}, "pause");
  }

  step() {
    const raw = Math.round(Number(this.nSteps.value));
    const n = Number.isFinite(raw) ? Math.min(1_000_000, Math.max(1, raw)) : 1;
    this.nSteps.value = String(n);
    this.onControl("step", { n_steps: n }, `step ${n}`);
  }

  setDisabled(disabled) {
    this.disabled = disabled;
    this.syncButtons();
  }

  /** What the simulation declared it can be steered with: ranges beside the fields, and
   * what it cannot change disabled with the reason. */
  setEngine(engine) {
    this.engine = engine;
    for (const [key, input] of this.inputs) {
      const why = engine?.unavailable?.[key];
      const range = engine?.params?.[key];
      input.dataset.unavailable = why ? "true" : "";
      input.title = why ? `${engine.name} cannot change this: ${why}` : range ? rangeText(engine, range) : "";
      if (range) {
        input.min = String(range.min);
        input.max = String(range.max);
      }
      // the value the engine runs at, where it says, until a steerer sets one
      const running = range && Number.isFinite(range.recommended) ? bound(range.recommended, 4) : "";
      input.placeholder = running || "default";
      const hint = document.getElementById(`range-${key}`);
      if (hint) setText(hint, why ? "not available" : range ? `${bound(range.min, 3)}–${bound(range.max, 4)}` : "");
    }
    this.syncButtons();
  }

  /** Why the engine cannot do `action`, or "" when it can (or nothing was declared). */
  unavailable(action) {
    const e = this.engine;
    if (!e || !e.controls?.length || e.controls.includes(action)) return "";
    return e.unavailable?.[action] || "not offered by this engine";
  }

  syncButtons() {
    const connected = this.sim.state === "running" || this.sim.state === "paused";
    this.play.disabled = this.disabled || !connected;
    for (const [button, action] of [
      [this.stepBtn, "step"],
      [this.reset, "reset"],
    ]) {
      const why = this.unavailable(action);
      button.disabled = this.disabled || !connected || Boolean(why);
      if (why) button.title = `${this.engine.name} cannot ${action}: ${why}`;
    }
    for (const [, input] of this.inputs) input.disabled = this.disabled || input.dataset.unavailable === "true";
    setText(this.play, this.sim.state === "paused" ? "Resume" : "Pause");
    this.play.setAttribute("aria-pressed", String(this.sim.state === "paused"));
  }

  updateStatus(sim) {
    this.sim = { ...this.sim, ...sim };
    const s = this.sim;
    const pill = $("sim-state");
    pill.dataset.state = s.state;
    setText(pill, s.state);
    setText($("sim-step"), integer(s.step));
    setText($("sim-time"), nanoseconds(s.time_ps));
    setText($("sim-rate"), s.state === "running" ? `${integer(s.steps_per_s)} steps/s` : "–");
    setText($("sim-engine"), s.engine || "–");
    setText($("sim-atoms"), s.n_atoms ? integer(s.n_atoms) : "–");
    this.renderObservables(s.observables ?? {});
    this.syncButtons();
  }

  renderObservables(observables) {
    const dl = $("sim-observables");
    const keys = Object.keys(observables).sort();
    if (dl.dataset.keys !== keys.join(",")) {
      dl.dataset.keys = keys.join(",");
      dl.replaceChildren(
        ...keys.flatMap((k) => [el("dt", { text: observableLabel(k) }), el("dd", { "data-observable": k })]),
      );
    }
    for (const k of keys) setText(dl.querySelector(`[data-observable="${k}"]`), sig(observables[k], 6));
  }

  /** The session's current simulation parameters (unset ones show the engine default). */
  updateParams(params) {
    this.params = params;
    for (const [key, input] of this.inputs) if (!isBusy(input)) this.restoreParam(key);
  }

  /** The field of `key` shows the value in effect (unset: empty, the engine's value as its
   * placeholder), even while it has the focus: a refused value leaves it this way. */
  restoreParam(key) {
    const input = this.inputs.get(key);
    if (!input) return;
    const sent = this.inFlight.get(key);
    const v = sent ? sent.value : this.params?.[key];
    input.value = v === undefined || v === null ? "" : String(v);
  }

  /** The value just given for `key` could not be sent (`why`): nothing is in flight for it. */
  notSent(key, why) {
    this.inFlight.delete(key);
    this.showAck(key, { state: FAILED, text: why });
  }

  /** Show a status {state, text} for a parameter key or "control". */
  showAck(key, status, label = "") {
    const sent = this.inFlight.get(key);
    if (sent && status.seq !== undefined) {
      if (status.state === PENDING && sent.seq === undefined) sent.seq = status.seq;
      else if (status.state !== PENDING && status.seq === sent.seq) this.inFlight.delete(key);
    }
    const node = document.getElementById(`ack-${key}`);
    if (!node) return;
    node.dataset.state = status.state;
    setText(node, label ? `${label}: ${status.text}` : status.text);
  }
}

/** A range's end: whole numbers with thousands separators (1,000,000, not 1.000e+6). */
export function bound(v, digits) {
  return Number.isInteger(v) && Math.abs(v) < 1e12 ? integer(v) : sig(v, digits);
}

function rangeText(engine, range) {
  const unit = range.unit ? ` ${range.unit}` : "";
  return `${engine.name}'s range ${bound(range.min, 3)}–${bound(range.max, 4)}${unit}`;
}
