// The temporal scale controls (inside "Scale and rendering"): smoothing off / classical /
// arclength-warped, its width tau and window in frames, the warp strength in frames per
// angstrom, the kernel (with the display lag it costs) and rigid-body removal.

import { $, markEdited } from "./dom.js";
import { clampParam } from "./params.js";

/** The frames a centred kernel shows late; 0 for a causal one. */
export function displayLag(render, replay) {
  const kernel = render.time_kernel === "auto" ? (replay ? "centred" : "causal") : render.time_kernel;
  return kernel === "centred" ? Math.floor((render.time_window - 1) / 2) : 0;
}

export class TimePanel {
  /** onChange(patch, final); `replay()` says whether the session replays a trajectory. */
  constructor({ onChange, replay }) {
    this.onChange = onChange;
    this.replay = replay;
    this.mode = $("time-smoothing");
    this.kernel = $("time-kernel");
    this.rigid = $("rigid-fit");
    this.sliders = [
      ["tau_frames", $("tau-frames")],
      ["time_window", $("time-window")],
      ["time_warp_per_A", $("time-warp")],
    ];
    this.render = null;
    this.bind();
  }

  bind() {
    this.mode.addEventListener("change", () => this.emit({ time_smoothing: this.mode.value }, true, this.mode));
    this.kernel.addEventListener("change", () => this.emit({ time_kernel: this.kernel.value }, true, this.kernel));
    this.rigid.addEventListener("change", () => this.emit({ rigid_fit: this.rigid.checked }, true, this.rigid));
    for (const [key, input] of this.sliders) {
      for (const type of ["input", "change"]) {
        input.addEventListener(type, () => {
          const value = clampParam(key, input.value);
          if (value === null) return;
          input.nextElementSibling.value = String(value);
          this.emit({ [key]: value }, type === "change", input);
        });
      }
    }
  }

  emit(patch, final, source) {
    markEdited(source);
    if (this.render) Object.assign(this.render, patch);
    this.onChange(patch, final);
    this.sync();
  }

  update(render) {
    this.render = { ...render };
    this.mode.value = render.time_smoothing;
    this.kernel.value = render.time_kernel;
    this.rigid.checked = Boolean(render.rigid_fit);
    for (const [key, input] of this.sliders) {
      input.value = String(render[key]);
      input.nextElementSibling.value = String(render[key]);
    }
    this.sync();
  }

  /** Controls that do nothing with smoothing off are disabled; the lag is stated. */
  sync() {
    const r = this.render;
    if (!r) return;
    const off = r.time_smoothing === "off";
    for (const [key, input] of this.sliders) input.disabled = off && !(key === "time_warp_per_A" && r.color_by === "motion");
    this.kernel.disabled = off;
    this.rigid.disabled = off;
    const lag = displayLag(r, this.replay());
    $("time-lag").textContent = off ? "" : lag ? `Display lag: ${lag} frames.` : "No display lag (causal).";
  }

  setDisabled(disabled) {
    for (const node of [this.mode, this.kernel, this.rigid, ...this.sliders.map(([, i]) => i)]) node.disabled = disabled;
    if (!disabled) this.sync();
  }
}
