// The layers panel: parts of the system (MDAnalysis selections) each drawn at its own scale.
// The session's `render_params.layers` is the truth (with this page's edits on their way over
// it: unconfirmed.js); edits go out as a whole new list, and a selection is checked on the
// server (`select` -> `selected`: its atom count, or where it is wrong) as it is typed, before
// it is applied.

import { $, el } from "./dom.js";
import { RANGES, clamp } from "./params.js";
import { normalizePoints } from "./transfer.js";

export const MAX_LAYERS = 8;
const MODES = ["iso", "volume", "licorice", "tube"];
const CHECK_MS = 250;

/** A protocol Layer with only the fields it sets (defaults dropped), or null if invalid. */
export function normalizeLayer(raw) {
  if (!raw || typeof raw !== "object") return null;
  const selection = typeof raw.selection === "string" ? raw.selection.trim() : "all";
  if (!selection || selection.length > 2048) return null;
  const out = { name: String(raw.name ?? "").slice(0, 64), selection };
  if (raw.visible === false) out.visible = false;
  if (MODES.includes(raw.mode)) out.mode = raw.mode;
  if (raw.sigma_A !== undefined && raw.sigma_A !== null) {
    const s = Number(raw.sigma_A);
    if (!Number.isFinite(s)) return null;
    out.sigma_A = clamp(s, RANGES.sigma_A[0], RANGES.sigma_A[1]);
  }
  if (raw.radius_A !== undefined && raw.radius_A !== null) {
    const r = Number(raw.radius_A);
    if (!Number.isFinite(r) || r <= 0) return null;
    out.radius_A = Math.min(r, 10);
  }
  if (raw.iso_level !== undefined && raw.iso_level !== null) {
    const v = Number(raw.iso_level);
    if (!Number.isFinite(v)) return null;
    out.iso_level = clamp(v, RANGES.iso_level[0], RANGES.iso_level[1]);
  }
  for (const key of ["scale_space", "color_by", "tf_preset"]) {
    if (typeof raw[key] === "string") out[key] = raw[key];
  }
  if (Array.isArray(raw.uniform_color) && raw.uniform_color.length === 3) out.uniform_color = raw.uniform_color.map(Number);
  if (Array.isArray(raw.transfer_function)) out.transfer_function = normalizePoints(raw.transfer_function).slice(0, 64);
  if (raw.opacity !== undefined && raw.opacity !== null) {
    const a = Number(raw.opacity);
    if (!Number.isFinite(a)) return null;
    if (a !== 1) out.opacity = clamp(a, 0, 1);
  }
  return out;
}

/** A whole layer list, normalized; null when any layer is invalid or there are too many. */
export function normalizeLayers(raw) {
  if (!Array.isArray(raw) || raw.length > MAX_LAYERS) return null;
  const out = raw.map(normalizeLayer);
  return out.includes(null) ? null : out;
}

/** `list` with the item at `from` moved to `to` (a new array). */
export function moveItem(list, from, to) {
  const out = list.slice();
  if (from < 0 || from >= out.length || to < 0 || to >= out.length) return out;
  const [item] = out.splice(from, 1);
  out.splice(to, 0, item);
  return out;
}

/** The text of a `selected` reply for the status line under a selection. */
export function describeSelected(reply) {
  if (reply.error) {
    const at = reply.position ?? 0;
    return { ok: false, text: `character ${at + 1}: ${reply.error}`, position: at };
  }
  const n = reply.count ?? 0;
  const atoms = `${n.toLocaleString("en-US")} atom${n === 1 ? "" : "s"}`;
  return { ok: true, text: reply.dynamic ? `${atoms} now (follows the frames)` : atoms, position: null };
}

/** A new layer's fields, named so it is told apart from the others. */
export function newLayer(existing) {
  const names = new Set(existing.map((l) => l.name));
  let i = existing.length + 1;
  while (names.has(`layer ${i}`)) i += 1;
  return { name: `layer ${i}`, selection: "protein" };
}

export class LayersPanel {
  /** onChange(layers): a whole new list to send; select(text) -> Promise<selected reply>. */
  constructor({ onChange, select }) {
    this.onChange = onChange;
    this.select = select;
    this.layers = [];
    this.list = $("layer-list");
    this.empty = $("layers-empty");
    this.addButton = $("layer-add");
    this.disabled = false;
    this.stale = false; // rows older than `layers`: a change came while the list had focus
    this.list.addEventListener("focusout", (e) => {
      // leaving the list: show what changed meanwhile (after the field's own change applies)
      if (this.stale && !this.list.contains(e.relatedTarget)) setTimeout(() => this.update(this.layers), 0);
    });
    this.addButton.addEventListener("click", () => {
      if (this.layers.length >= MAX_LAYERS) return;
      this.emit([...this.layers, newLayer(this.layers)]);
    });
  }

  emit(layers) {
    const clean = normalizeLayers(layers);
    if (!clean) return;
    this.layers = clean;
    this.draw();
    this.onChange(clean);
  }

  setDisabled(disabled) {
    this.disabled = disabled;
    this.addButton.disabled = disabled || this.layers.length >= MAX_LAYERS;
  }

  /** The layers the page shows (the session's, with this page's edits on their way); while
   * a field of the list has the focus the rows are left alone, and redrawn when it leaves. */
  update(layers) {
    const clean = normalizeLayers(layers ?? []) ?? [];
    const same = JSON.stringify(clean) === JSON.stringify(this.layers) && this.list.children.length === clean.length;
    if (same && !this.stale) return;
    this.layers = clean;
    if (this.list.contains(document.activeElement)) {
      this.stale = true; // redrawn when the focus leaves the list
      return;
    }
    this.draw();
  }

  draw() {
    this.stale = false;
    this.list.replaceChildren(...this.layers.map((layer, i) => this.row(layer, i)));
    this.empty.hidden = this.layers.length > 0;
    this.setDisabled(this.disabled);
  }

  change(i, fields) {
    const next = this.layers.map((l, k) => (k === i ? { ...l, ...fields } : l));
    for (const [key, value] of Object.entries(fields)) if (value === undefined) delete next[i][key];
    this.emit(next);
  }

  row(layer, i) {
    const id = `layer-${i}`;
    const visible = el("input", { type: "checkbox", id: `${id}-visible`, "aria-label": `Show ${layer.name || `layer ${i + 1}`}` });
    visible.checked = layer.visible !== false;
    visible.addEventListener("change", () => this.change(i, { visible: visible.checked ? undefined : false }));
    const name = el("input", { type: "text", id: `${id}-name`, value: layer.name, maxlength: 64, "aria-label": "Layer name", className: "layer-name" });
    name.addEventListener("change", () => this.change(i, { name: name.value }));
    const selection = el("input", {
      type: "text",
      id: `${id}-selection`,
      value: layer.selection,
      maxlength: 2048,
      spellcheck: "false",
      autocomplete: "off",
      "aria-label": "Selection (MDAnalysis syntax)",
      "aria-describedby": `${id}-status`,
      className: "layer-selection",
    });
    const status = el("p", { id: `${id}-status`, className: "layer-status", "aria-live": "polite" });
    let timer = null;
    let checked = { text: layer.selection, ok: true };
    const check = async () => {
      const text = selection.value.trim();
      if (!text) {
        checked = { text, ok: false };
        this.showStatus(status, selection, { ok: false, text: "empty: use “all” for every atom", position: 0 });
        return checked;
      }
      try {
        const { reply } = await this.select(text);
        const shown = describeSelected(reply);
        checked = { text, ok: shown.ok };
        if (selection.value.trim() === text) this.showStatus(status, selection, shown);
      } catch (err) {
        checked = { text, ok: false };
        this.showStatus(status, selection, { ok: false, text: String(err.message ?? err), position: null });
      }
      return checked;
    };
    selection.addEventListener("input", () => {
      clearTimeout(timer);
      timer = setTimeout(check, CHECK_MS);
    });
    const apply = async () => {
      clearTimeout(timer);
      const text = selection.value.trim();
      const result = checked.text === text ? checked : await check();
      if (result.ok && text !== layer.selection) this.change(i, { selection: text });
    };
    selection.addEventListener("change", apply);
    selection.addEventListener("keydown", (e) => {
      if (e.key === "Enter") apply();
    });
    const sigma = this.lengthField(i, layer, "sigma_A", {
      id: `${id}-sigma`,
      max: 50,
      placeholder: "as above",
      label: "Layer scale σ in ångström (empty: the session's)",
    });
    const mode = el("select", { id: `${id}-mode`, "aria-label": "Layer mode" }, [
      el("option", { value: "", text: "session mode" }),
      el("option", { value: "iso", text: "surface" }),
      el("option", { value: "volume", text: "cloud" }),
      el("option", { value: "licorice", text: "sticks" }),
      el("option", { value: "tube", text: "backbone tube" }),
    ]);
    mode.value = layer.mode ?? "";
    mode.addEventListener("change", () => this.change(i, { mode: mode.value || undefined }));
    const shape = layer.mode === "licorice" || layer.mode === "tube";
    const radius = this.lengthField(i, layer, "radius_A", {
      id: `${id}-radius`,
      max: 10,
      placeholder: layer.mode === "tube" ? "0.6" : "0.25",
      label: "Stick or tube radius in ångström",
    });
    const opacity = el("input", {
      type: "range",
      id: `${id}-opacity`,
      min: 0,
      max: 1,
      step: 0.05,
      value: layer.opacity ?? 1,
      "aria-label": "Layer opacity",
    });
    opacity.addEventListener("change", () => this.change(i, { opacity: Number(opacity.value) }));
    const button = (label, text, fn, disabled) => {
      const b = el("button", { type: "button", "aria-label": label, title: label, text, className: "icon" });
      b.disabled = disabled;
      b.addEventListener("click", fn);
      return b;
    };
    const n = this.layers.length;
    const tools = el("span", { className: "layer-tools" }, [
      button("Move up", "↑", () => this.emit(moveItem(this.layers, i, i - 1)), i === 0),
      button("Move down", "↓", () => this.emit(moveItem(this.layers, i, i + 1)), i === n - 1),
      button("Remove layer", "✕", () => this.emit(this.layers.filter((_, k) => k !== i)), false),
    ]);
    const item = el("li", { className: "layer", "data-layer": i }, [
      el("div", { className: "row layer-head" }, [visible, name, tools]),
      selection,
      status,
      el("div", { className: "row layer-opts" }, [
        el("label", { for: shape ? `${id}-radius` : `${id}-sigma`, text: shape ? "r" : "σ" }),
        shape ? radius : sigma,
        mode,
        el("label", { for: `${id}-opacity`, text: "opacity" }),
        opacity,
      ]),
    ]);
    check();
    return item;
  }

  /** A length in ångström that the layer may leave empty (then the default applies). */
  lengthField(i, layer, key, { id, max, placeholder, label }) {
    const input = el("input", {
      type: "number",
      id,
      min: 0.05,
      max,
      step: 0.05,
      placeholder,
      value: layer[key] ?? "",
      "aria-label": label,
      className: "num",
    });
    input.addEventListener("change", () => {
      const v = input.value.trim() === "" ? undefined : Number(input.value);
      if (v !== undefined && !(Number.isFinite(v) && v > 0)) return;
      this.change(i, { [key]: v });
    });
    return input;
  }

  /** The count, or the error with the text marked where it goes wrong. */
  showStatus(status, input, shown) {
    status.classList.toggle("error", !shown.ok);
    input.setAttribute("aria-invalid", shown.ok ? "false" : "true");
    if (shown.ok || shown.position === null) {
      status.replaceChildren(shown.text);
      return;
    }
    const text = input.value.trim();
    const at = Math.min(shown.position, text.length);
    const rest = text.slice(at) || " ";
    status.replaceChildren(
      el("span", { text: shown.text }),
      el("code", { className: "layer-where" }, [text.slice(0, at), el("mark", { text: rest })]),
    );
  }
}
