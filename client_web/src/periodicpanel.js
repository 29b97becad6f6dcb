// The periodic box controls (inside "Scale and rendering"): how a frame with a box is shown
// (molecules whole, wrapped, followed), whose centre sits at the box's centre, the fit onto a
// reference frame, and the box's outline. Each maps to one render parameter.

import { $, isBusy, markEdited } from "./dom.js";

export class PeriodicPanel {
  /** onChange(patch, final) */
  constructor({ onChange }) {
    this.onChange = onChange;
    this.mode = $("periodic-mode");
    this.center = $("periodic-center");
    this.centerText = $("periodic-center-selection");
    this.fit = $("periodic-fit");
    this.fitText = $("periodic-fit-selection");
    this.cell = $("periodic-cell");
    this.render = null;
    this.bind();
  }

  bind() {
    this.mode.addEventListener("change", () => this.emit({ periodic: this.mode.value }, this.mode));
    this.center.addEventListener("change", () => this.emit({ center: this.center.value }, this.center));
    this.fit.addEventListener("change", () => this.emit({ fit: this.fit.value }, this.fit));
    this.cell.addEventListener("change", () => this.emit({ show_cell: this.cell.checked }, this.cell));
    this.centerText.addEventListener("change", () => {
      const text = this.centerText.value.trim();
      if (text) this.emit({ center: "selection", center_selection: text }, this.centerText);
    });
    this.fitText.addEventListener("change", () => {
      const text = this.fitText.value.trim();
      if (text) this.emit({ fit_selection: text }, this.fitText);
    });
  }

  emit(patch, source) {
    markEdited(source);
    if (this.render) Object.assign(this.render, patch);
    this.onChange(patch, true);
    this.sync();
  }

  update(render) {
    this.render = { ...render };
    this.mode.value = render.periodic;
    this.center.value = render.center;
    this.fit.value = render.fit;
    this.cell.checked = Boolean(render.show_cell);
    if (!isBusy(this.centerText)) this.centerText.value = render.center_selection;
    if (!isBusy(this.fitText)) this.fitText.value = render.fit_selection;
    this.sync();
  }

  /** The selection fields matter only when their choice uses them. */
  sync() {
    const r = this.render;
    if (!r || this.disabled) return;
    this.fitText.disabled = r.fit === "off";
  }

  setDisabled(disabled) {
    this.disabled = disabled;
    for (const node of [this.mode, this.center, this.centerText, this.fit, this.fitText, this.cell]) {
      node.disabled = disabled;
    }
    if (!disabled) this.sync();
  }
}
