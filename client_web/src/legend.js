// The colour legend drawn over the view: named swatches for element, residue and chain
// colouring, a ramp with its value range for B-factors, charges and motion (sent by the server,
// which computes the colours, in `state.legend`).

import { el } from "./dom.js";
import { sig } from "./format.js";
import { sessionColourApplies } from "./params.js";

const css = (rgb) => `rgb(${rgb.map((c) => Math.round(c * 255)).join(", ")})`;

const TITLES = {
  element: "Element",
  residue: "Residue class",
  chain: "Chain",
  bfactor: "B-factor",
  charge: "Charge",
  motion: "Motion: warp rate γ′",
  uniform: "Colour",
};

/** What a ramp's ends mean, beyond their value, and a line saying what its unit is. */
const RAMPS = {
  motion: {
    low: "at rest",
    high: "fast",
    note:
      "γ′: frames of warped time per frame, the atom's mean over the temporal window; " +
      "a step of d Å counts √(1 + (w·d)²) frames, w the Warp (frames/Å) of Scale and rendering → Temporal scale",
  },
};

/** The legend's words: {title, low, high, note} (the ends of a ramp with their unit). */
export function legendText(legend) {
  const title = TITLES[legend.color_by] ?? legend.color_by;
  if (!legend.ramp?.length) return { title, low: "", high: "", note: "" };
  const unit = legend.unit ? ` ${legend.unit}` : "";
  const words = RAMPS[legend.color_by] ?? { low: "", high: "", note: "" };
  const end = (value, word) => `${sig(value, 3)}${unit}${word ? ` ${word}` : ""}`;
  return { title, low: end(legend.low, words.low), high: end(legend.high, words.high), note: words.note };
}

/**
 * Fill `root` with the legend of `legend` (hidden when there is none); where nothing drawn takes
 * the session's colouring (`render` all volume), it names the transfer function instead.
 */
export function showLegend(root, legend, render = null) {
  if (render && !sessionColourApplies(render)) {
    root.hidden = false;
    root.dataset.colorBy = "transfer_function";
    root.replaceChildren(
      el("div", { className: "legend-title", text: "Transfer function" }),
      el("p", {
        className: "legend-note",
        text: "volume mode: the colours and opacity are the transfer function's (Scale and rendering)",
      }),
    );
    return;
  }
  root.hidden = !legend;
  if (!legend) return;
  root.dataset.colorBy = legend.color_by;
  const text = legendText(legend);
  const title = el("div", { className: "legend-title", text: text.title });
  if (legend.ramp?.length) {
    const gradient = `linear-gradient(to right, ${legend.ramp.map(css).join(", ")})`;
    const bar = el("div", { className: "legend-ramp" });
    bar.style.background = gradient;
    const ends = el("div", { className: "legend-ends" }, [
      el("span", { text: text.low }),
      el("span", { text: text.high }),
    ]);
    const note = text.note ? [el("p", { className: "legend-note", text: text.note })] : [];
    root.replaceChildren(title, bar, ends, ...note);
    return;
  }
  const items = (legend.entries ?? []).map((entry) => {
    const swatch = el("span", { className: "swatch", "aria-hidden": "true" });
    swatch.style.background = css(entry.color);
    return el("li", {}, [swatch, el("span", { text: entry.label })]);
  });
  root.replaceChildren(title, el("ul", { className: "legend-entries" }, items));
}
