// The scale and rendering panel: every control maps to one render parameter; changes go out as
// partial `render_params` updates and the session's state comes back to set the controls.

import { $, isBusy, markEdited } from "./dom.js";
import {
  RENDER_DEFAULTS,
  clampParam,
  sessionColourApplies,
  shownSpace,
  sigmaFromSlider,
  sliderFromSigma,
} from "./params.js";
import { hexToRgb, rgbToHex } from "./transfer.js";
import { sig } from "./format.js";

const SLIDER_STEPS = 1000;

export class RenderPanel {
  /** onChange(patch, final): final is false while a slider is being dragged; onInvalid(text):
   * a typed value was not sent (outside its field's range). */
  constructor({ onChange, onInvalid = () => {} }) {
    this.onChange = onChange;
    this.onInvalid = onInvalid;
    this.render = JSON.parse(JSON.stringify(RENDER_DEFAULTS));
    this.sigmaSlider = $("sigma-slider");
    this.sigmaNumber = $("sigma-number");
    this.isoSlider = $("iso-slider");
    this.isoNumber = $("iso-number");
    this.modeRadios = [...document.querySelectorAll('input[name="mode"]')];
    this.spaceRadios = [...document.querySelectorAll('input[name="scale-space"]')];
    this.warpStrength = $("warp-strength");
    this.smoothing = $("geodesic-smoothing");
    this.densityWeights = $("density-weights");
    this.radiusMode = $("radius-mode");
    this.colorBy = $("color-by");
    this.uniformColor = $("uniform-color");
    this.background = $("background");
    this.lightInputs = [...document.querySelectorAll("[data-light]")];
    this.scalars = [
      ["quality", $("quality"), (v) => `${Math.round(v * 100)}%`],
      ["jpeg_quality", $("jpeg-quality"), (v) => String(Math.round(v))],
      ["step_sigmas", $("step-sigmas"), (v) => sig(v, 2)],
      ["cutoff_sigmas", $("cutoff-sigmas"), (v) => sig(v, 2)],
    ];
    this.bind();
    this.update(this.render);
    // a field left alone by `update` while it had the focus shows the latest values once the
    // focus leaves it (the session's, with this page's own edits)
    $("panel-render").addEventListener("focusout", () => setTimeout(() => this.update(this.render), 0));
  }

  /** The number typed into `input` when it lies within the field's own min and max; otherwise
   * null: the page says it was not sent (a value out of range is not quietly moved to the
   * nearest end) and the field shows `current`, the value in effect, again. */
  typedNumber(input, label, unit, current) {
    const text = input.value.trim();
    const v = text === "" ? NaN : Number(text);
    const lo = Number(input.min);
    const hi = Number(input.max);
    if (Number.isFinite(v) && v >= lo && v <= hi) return v;
    // a number input holds "" for what it cannot read as a finite number (1e400, "abc")
    this.onInvalid(
      Number.isFinite(v)
        ? `${label} ${text} is outside ${lo}–${hi}${unit}; not sent`
        : `${label} must be a number from ${lo} to ${hi}${unit}; not sent`,
    );
    input.value = String(sig(current, 3));
    return null;
  }

  emit(patch, final, source) {
    if (source) markEdited(source);
    Object.assign(this.render, patch);
    this.onChange(patch, final);
  }

  bind() {
    const sigmaFromRange = () => sigmaFromSlider(Number(this.sigmaSlider.value) / SLIDER_STEPS);
    for (const type of ["input", "change"]) {
      this.sigmaSlider.addEventListener(type, () => {
        const sigma = Number(sigmaFromRange().toPrecision(3));
        this.sigmaNumber.value = String(sigma);
        this.sigmaSlider.setAttribute("aria-valuetext", `${sigma} Å`);
        this.emit({ sigma_A: sigma }, type === "change", this.sigmaSlider);
      });
      this.isoSlider.addEventListener(type, () => {
        const iso = Number(this.isoSlider.value);
        this.isoNumber.value = String(iso);
        this.emit({ iso_level: iso }, type === "change", this.isoSlider);
      });
    }
    this.sigmaNumber.addEventListener("change", () => {
      const sigma = this.typedNumber(this.sigmaNumber, "σ", " Å", this.render.sigma_A);
      if (sigma === null) return;
      this.sigmaSlider.value = String(Math.round(sliderFromSigma(sigma) * SLIDER_STEPS));
      this.emit({ sigma_A: sigma }, true, this.sigmaNumber);
    });
    this.isoNumber.addEventListener("change", () => {
      const iso = this.typedNumber(this.isoNumber, "iso level", "", this.render.iso_level);
      if (iso === null) return;
      this.isoSlider.value = String(iso);
      this.emit({ iso_level: iso }, true, this.isoNumber);
    });
    for (const radio of this.modeRadios) {
      radio.addEventListener("change", () => {
        if (radio.checked) this.emit({ mode: radio.value }, true, radio);
      });
    }
    for (const radio of this.spaceRadios) {
      radio.addEventListener("change", () => {
        if (!radio.checked) return;
        this.emit({ scale_space: radio.value }, true, radio);
        this.syncEnabled();
      });
    }
    for (const type of ["input", "change"]) {
      this.warpStrength.addEventListener(type, () => {
        const value = clampParam("warp_strength", this.warpStrength.value);
        if (value === null) return;
        this.showOutput(this.warpStrength);
        this.emit({ warp_strength: value }, type === "change", this.warpStrength);
      });
      this.smoothing.addEventListener(type, () => {
        const value = clampParam("geodesic_smoothing", this.smoothing.value);
        if (value === null) return;
        this.showOutput(this.smoothing);
        this.emit({ geodesic_smoothing: value }, type === "change", this.smoothing);
      });
    }
    this.densityWeights.addEventListener("change", () =>
      this.emit({ density_weights: this.densityWeights.value }, true, this.densityWeights),
    );
    this.radiusMode.addEventListener("change", () =>
      this.emit({ radius_mode: this.radiusMode.value }, true, this.radiusMode),
    );
    this.colorBy.addEventListener("change", () => {
      this.emit({ color_by: this.colorBy.value }, true, this.colorBy);
      this.syncEnabled();
    });
    this.uniformColor.addEventListener("input", () => {
      const rgb = hexToRgb(this.uniformColor.value);
      if (rgb) this.emit({ uniform_color: rgb }, false, this.uniformColor);
    });
    this.uniformColor.addEventListener("change", () => {
      const rgb = hexToRgb(this.uniformColor.value);
      if (rgb) this.emit({ uniform_color: rgb }, true, this.uniformColor);
    });
    const setBackground = (hex, final, source) => {
      const rgb = hexToRgb(hex);
      if (rgb) this.emit({ background: rgb }, final, source);
    };
    this.background.addEventListener("input", () => setBackground(this.background.value, false, this.background));
    this.background.addEventListener("change", () => setBackground(this.background.value, true, this.background));
    for (const swatch of document.querySelectorAll("[data-bg]")) {
      swatch.addEventListener("click", () => {
        this.background.value = swatch.dataset.bg;
        setBackground(swatch.dataset.bg, true, null);
      });
    }
    for (const input of this.lightInputs) {
      const key = input.dataset.light;
      const handler = (final) => {
        const value = input.type === "checkbox" ? input.checked : clampParam(`lighting.${key}`, input.value);
        if (value === null) return;
        this.showOutput(input);
        this.emit({ lighting: { ...this.render.lighting, [key]: value } }, final, input);
      };
      if (input.type === "checkbox") input.addEventListener("change", () => handler(true));
      else {
        input.addEventListener("input", () => handler(false));
        input.addEventListener("change", () => handler(true));
      }
    }
    for (const [key, input] of this.scalars) {
      const handler = (final) => {
        const value = clampParam(key, input.value);
        if (value === null) return;
        this.showOutput(input);
        this.emit({ [key]: value }, final, input);
      };
      input.addEventListener("input", () => handler(false));
      input.addEventListener("change", () => handler(true));
    }
  }

  showOutput(input) {
    const out = document.querySelector(`output[for="${input.id}"]`);
    if (!out) return;
    const scalar = this.scalars.find(([, node]) => node === input);
    out.value = scalar ? scalar[2](Number(input.value)) : sig(Number(input.value), 3);
  }

  syncEnabled() {
    const applies = sessionColourApplies(this.render);
    this.colorBy.disabled = this.disabled || !applies;
    this.colorBy.title = applies
      ? ""
      : "volume mode draws the transfer function's colours: Colour by applies to surfaces, sticks and tubes";
    this.uniformColor.disabled = this.disabled || !applies || this.colorBy.value !== "uniform";
    const space = shownSpace(this.render.scale_space);
    const warped = space !== "classical";
    this.warpStrength.disabled = this.disabled || !warped;
    $("warp-row").classList.toggle("muted", !warped);
    const geodesic = space === "geodesic";
    this.smoothing.disabled = this.disabled || !geodesic;
    $("smoothing-row").classList.toggle("muted", !geodesic);
  }

  setDisabled(disabled) {
    this.disabled = disabled;
    this.syncEnabled();
  }

  /** Set every control from the session's render parameters (skipping one being edited). */
  update(render) {
    this.render = JSON.parse(JSON.stringify(render));
    const set = (node, value) => {
      if (!isBusy(node)) node.value = String(value);
    };
    if (!isBusy(this.sigmaSlider) && !isBusy(this.sigmaNumber)) {
      this.sigmaSlider.value = String(Math.round(sliderFromSigma(render.sigma_A) * SLIDER_STEPS));
      this.sigmaSlider.setAttribute("aria-valuetext", `${sig(render.sigma_A, 3)} Å`);
      this.sigmaNumber.value = String(sig(render.sigma_A, 3));
    }
    if (!isBusy(this.isoSlider) && !isBusy(this.isoNumber)) {
      this.isoSlider.value = String(render.iso_level);
      this.isoNumber.value = String(sig(render.iso_level, 3));
    }
    for (const radio of this.modeRadios) radio.checked = radio.value === render.mode;
    const space = shownSpace(render.scale_space);
    for (const radio of this.spaceRadios) radio.checked = radio.value === space;
    set(this.warpStrength, render.warp_strength);
    this.showOutput(this.warpStrength);
    set(this.smoothing, render.geodesic_smoothing ?? 0.6);
    this.showOutput(this.smoothing);
    set(this.densityWeights, render.density_weights);
    set(this.radiusMode, render.radius_mode);
    set(this.colorBy, render.color_by);
    set(this.uniformColor, rgbToHex(render.uniform_color));
    set(this.background, rgbToHex(render.background));
    for (const input of this.lightInputs) {
      const value = render.lighting[input.dataset.light];
      if (input.type === "checkbox") input.checked = Boolean(value);
      else set(input, value);
      this.showOutput(input);
    }
    for (const [key, input] of this.scalars) {
      set(input, render[key]);
      this.showOutput(input);
    }
    this.syncEnabled();
  }
}
