// The colour legend drawn over the view: named swatches for element, residue and chain
// colouring, a ramp with its value range for B-factors and charges (sent by the server, which
// computes the colours, in `state.legend`).

import { el } from "./dom.js";
import { sig } from "./format.js";

const css = (rgb) => `rgb(${rgb.map((c) => Math.round(c * 255)).join(", ")})`;

const TITLES = {
  element: "Element",
  residue: "Residue class",
  chain: "Chain",
  bfactor: "B-factor",
  charge: "Charge",
  uniform: "Colour",
};

/** Fill `root` with the legend of `legend` (hidden when there is none). */
export function showLegend(root, legend) {
  root.hidden = !legend;
  if (!legend) return;
  root.dataset.colorBy = legend.color_by;
  const title = el("div", { className: "legend-title", text: TITLES[legend.color_by] ?? legend.color_by });
  if (legend.ramp?.length) {
    const gradient = `linear-gradient(to right, ${legend.ramp.map(css).join(", ")})`;
    const bar = el("div", { className: "legend-ramp" });
    bar.style.background = gradient;
    const unit = legend.unit ? ` ${legend.unit}` : "";
    const ends = el("div", { className: "legend-ends" }, [
      el("span", { text: `${sig(legend.low, 3)}${unit}` }),
      el("span", { text: `${sig(legend.high, 3)}${unit}` }),
    ]);
    root.replaceChildren(title, bar, ends);
    return;
  }
  const items = (legend.entries ?? []).map((entry) => {
    const swatch = el("span", { className: "swatch", "aria-hidden": "true" });
    swatch.style.background = css(entry.color);
    return el("li", {}, [swatch, el("span", { text: entry.label })]);
  });
  root.replaceChildren(title, el("ul", { className: "legend-entries" }, items));
}
