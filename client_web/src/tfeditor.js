// The transfer-function editor: an SVG opacity curve over the density histogram, control points
// dragged with the pointer or moved with the keyboard, a colour per point.

import { setText, svg } from "./dom.js";
import {
  HISTOGRAM_X_MAX,
  TF_DOMAIN,
  curvePath,
  domainFor,
  evaluate,
  fromScreen,
  hexToRgb,
  histogramBars,
  insertPoint,
  movePoint,
  nearestPoint,
  recolorPoint,
  removePoint,
  rgbToHex,
  toScreen,
} from "./transfer.js";

const PAD = { left: 8, right: 8, top: 8, bottom: 16 };
const HIT_RADIUS = 12;
const KEY_STEP_X = 0.02;
const KEY_STEP_ALPHA = 0.02;

export class TransferEditor {
  constructor({ svgRoot, colorInput, selectedLabel, addButton, removeButton, onChange }) {
    Object.assign(this, { root: svgRoot, colorInput, selectedLabel, addButton, removeButton, onChange });
    this.points = [];
    this.histogram = null;
    this.histRange = [0, HISTOGRAM_X_MAX];
    this.domain = [...TF_DOMAIN];
    this.selected = -1;
    this.drag = null;
    this.enabled = true;
    this.build();
    this.bind();
    new ResizeObserver(() => this.render()).observe(this.root);
  }

  build() {
    const r = this.root;
    const defs = svg("defs");
    this.gradient = svg("linearGradient", { id: "tf-gradient", x1: "0", x2: "1", y1: "0", y2: "0" });
    defs.append(this.gradient);
    this.gridLayer = svg("g");
    this.histLayer = svg("g");
    this.area = svg("path", { class: "area", fill: "url(#tf-gradient)" });
    this.curve = svg("path", { class: "curve" });
    this.pointLayer = svg("g");
    this.axisLayer = svg("g");
    r.append(defs, this.gridLayer, this.histLayer, this.area, this.curve, this.pointLayer, this.axisLayer);
  }

  box() {
    const w = this.root.clientWidth || 300;
    const h = this.root.clientHeight || 140;
    return {
      left: PAD.left,
      top: PAD.top,
      width: Math.max(10, w - PAD.left - PAD.right),
      height: Math.max(10, h - PAD.top - PAD.bottom),
    };
  }

  // ------------------------------------------------------------------ state in

  /** Points from the session (ignored while the user drags one). */
  setPoints(points) {
    if (this.drag) return;
    this.points = points.map((p) => ({ x: p.x, color: [...p.color], alpha: p.alpha }));
    this.domain = domainFor(this.points);
    if (this.selected >= this.points.length) this.selected = this.points.length - 1;
    this.render();
  }

  /** Density counts over `range` (iso-level units) from the latest still image. */
  setHistogram(counts, range = [0, HISTOGRAM_X_MAX]) {
    this.histogram = counts ? Array.from(counts) : null;
    this.histRange = range;
    this.renderHistogram();
  }

  setEnabled(enabled) {
    this.enabled = enabled;
    this.root.setAttribute("aria-disabled", String(!enabled));
    this.syncButtons();
  }

  // ------------------------------------------------------------------ drawing

  render() {
    const box = this.box();
    const w = this.root.clientWidth || 300;
    const h = this.root.clientHeight || 140;
    this.root.setAttribute("viewBox", `0 0 ${w} ${h}`);
    this.gridLayer.replaceChildren();
    this.axisLayer.replaceChildren();
    const d = this.domain;
    for (let x = d[0]; x <= d[1] + 1e-9; x += 0.5) {
      const [sx] = toScreen({ x, alpha: 0 }, box, d);
      this.gridLayer.append(
        svg("line", { class: x === 1 ? "iso-mark" : "grid", x1: sx, x2: sx, y1: box.top, y2: box.top + box.height }),
      );
      if (Number.isInteger(x)) {
        const label = svg("text", {
          class: "axis",
          x: sx,
          y: h - 3,
          "text-anchor": x === d[0] ? "start" : x === d[1] ? "end" : "middle",
        });
        label.textContent = x === 1 ? "iso" : `${x}×`;
        this.axisLayer.append(label);
      }
    }
    this.renderHistogram(box);
    const path = curvePath(this.points, box, d);
    this.curve.setAttribute("d", path);
    this.area.setAttribute(
      "d",
      path ? `${path} L${box.left + box.width},${box.top + box.height} L${box.left},${box.top + box.height} Z` : "",
    );
    this.gradient.replaceChildren(
      ...this.points.map((p) =>
        svg("stop", { offset: `${((p.x - d[0]) / (d[1] - d[0])) * 100}%`, "stop-color": rgbToHex(p.color) }),
      ),
    );
    this.pointLayer.replaceChildren(
      ...this.points.map((p, i) => {
        const [cx, cy] = toScreen(p, box, d);
        return svg("circle", {
          class: i === this.selected ? "point selected" : "point",
          cx,
          cy,
          r: i === this.selected ? 7 : 6,
          fill: rgbToHex(p.color),
          "data-index": i,
        });
      }),
    );
    this.syncSelection();
  }

  renderHistogram(box = this.box()) {
    this.histLayer.replaceChildren(
      ...histogramBars(this.histogram, box, this.histRange, this.domain).map((b) =>
        svg("rect", { class: "hist", x: b.x, y: b.y, width: Math.max(0.5, b.width - 0.5), height: b.height }),
      ),
    );
  }

  syncSelection() {
    const p = this.points[this.selected];
    if (p) {
      setText(
        this.selectedLabel,
        `point ${this.selected + 1}/${this.points.length}: density ${p.x.toFixed(2)}, opacity ${p.alpha.toFixed(2)}`,
      );
      if (document.activeElement !== this.colorInput) this.colorInput.value = rgbToHex(p.color);
    } else {
      setText(this.selectedLabel, "no point selected");
    }
    this.syncButtons();
  }

  syncButtons() {
    const has = this.selected >= 0 && this.selected < this.points.length;
    this.colorInput.disabled = !this.enabled || !has;
    this.removeButton.disabled = !this.enabled || !has || this.points.length <= 2;
    this.addButton.disabled = !this.enabled;
  }

  // ------------------------------------------------------------------ editing

  commit(points, final) {
    this.points = points;
    this.render();
    this.onChange(
      points.map((p) => ({ x: p.x, color: [...p.color], alpha: p.alpha })),
      final,
    );
  }

  select(i) {
    this.selected = i;
    this.render();
  }

  local(e) {
    const rect = this.root.getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  }

  bind() {
    const r = this.root;
    r.addEventListener("pointerdown", (e) => {
      if (!this.enabled || e.button !== 0) return;
      r.focus({ preventScroll: true });
      const [px, py] = this.local(e);
      const i = nearestPoint(this.points, px, py, this.box(), HIT_RADIUS, this.domain);
      this.select(i);
      if (i >= 0) {
        this.drag = { index: i, moved: false };
        r.setPointerCapture(e.pointerId);
        e.preventDefault();
      }
    });
    r.addEventListener("pointermove", (e) => {
      if (!this.drag) return;
      const [px, py] = this.local(e);
      const { x, alpha } = fromScreen(px, py, this.box(), this.domain);
      this.drag.moved = true;
      this.commit(movePoint(this.points, this.drag.index, x, alpha, this.domain), false);
    });
    const end = () => {
      if (!this.drag) return;
      const moved = this.drag.moved;
      this.drag = null;
      if (moved) this.commit(this.points, true);
    };
    r.addEventListener("pointerup", end);
    r.addEventListener("pointercancel", end);
    r.addEventListener("dblclick", (e) => {
      if (!this.enabled) return;
      const [px, py] = this.local(e);
      if (nearestPoint(this.points, px, py, this.box(), HIT_RADIUS, this.domain) >= 0) return;
      const { x, alpha } = fromScreen(px, py, this.box(), this.domain);
      this.insertAt(x, alpha);
    });
    r.addEventListener("contextmenu", (e) => {
      e.preventDefault();
      if (!this.enabled) return;
      const [px, py] = this.local(e);
      const i = nearestPoint(this.points, px, py, this.box(), HIT_RADIUS, this.domain);
      if (i >= 0) this.removeAt(i);
    });
    r.addEventListener("keydown", (e) => this.key(e));
    this.colorInput.addEventListener("input", () => {
      const rgb = hexToRgb(this.colorInput.value);
      if (rgb && this.selected >= 0) this.commit(recolorPoint(this.points, this.selected, rgb), false);
    });
    this.colorInput.addEventListener("change", () => {
      if (this.selected >= 0) this.commit(this.points, true);
    });
    this.addButton.addEventListener("click", () => this.addBetween());
    this.removeButton.addEventListener("click", () => this.removeAt(this.selected));
  }

  insertAt(x, alpha = null) {
    const { points, index } = insertPoint(this.points, x, alpha, this.domain);
    if (index < 0) return;
    this.selected = index;
    this.commit(points, true);
  }

  /** Add a point in the middle of the widest gap after the selection (keyboard friendly). */
  addBetween() {
    if (!this.enabled) return;
    const pts = this.points;
    if (!pts.length) return this.insertAt(1);
    let best = 0;
    let gap = -1;
    for (let i = 0; i + 1 < pts.length; i++) {
      const g = pts[i + 1].x - pts[i].x;
      if (g > gap) [best, gap] = [i, g];
    }
    const start = this.selected >= 0 && this.selected + 1 < pts.length ? this.selected : best;
    const x = (pts[start].x + pts[start + 1 < pts.length ? start + 1 : start].x) / 2;
    this.insertAt(x === pts[start].x ? Math.min(this.domain[1], x + 0.1) : x);
  }

  removeAt(i) {
    if (!this.enabled || i < 0 || this.points.length <= 2) return;
    const points = removePoint(this.points, i);
    this.selected = Math.min(i, points.length - 1);
    this.commit(points, true);
  }

  key(e) {
    if (!this.enabled) return;
    const n = this.points.length;
    const sel = this.selected;
    const p = this.points[sel];
    const fine = e.shiftKey ? 5 : 1;
    let handled = true;
    switch (e.key) {
      case "PageDown":
        this.select(n ? (sel + 1) % n : -1);
        break;
      case "PageUp":
        this.select(n ? (sel - 1 + n) % n : -1);
        break;
      case "Home":
        this.select(n ? 0 : -1);
        break;
      case "End":
        this.select(n - 1);
        break;
      case "ArrowLeft":
      case "ArrowRight":
      case "ArrowUp":
      case "ArrowDown":
        if (!p) {
          this.select(n ? 0 : -1);
          break;
        }
        {
          const dx = e.key === "ArrowLeft" ? -KEY_STEP_X : e.key === "ArrowRight" ? KEY_STEP_X : 0;
          const da = e.key === "ArrowDown" ? -KEY_STEP_ALPHA : e.key === "ArrowUp" ? KEY_STEP_ALPHA : 0;
          this.commit(movePoint(this.points, sel, p.x + dx * fine, p.alpha + da * fine, this.domain), true);
        }
        break;
      case "Insert":
      case "a":
        this.addBetween();
        break;
      case "Delete":
      case "Backspace":
        this.removeAt(sel);
        break;
      default:
        handled = false;
    }
    if (handled) {
      e.preventDefault();
      e.stopPropagation();
    }
  }

  /** Opacity at density x of the curve being shown (for tests and readouts). */
  opacityAt(x) {
    return evaluate(this.points, x).alpha;
  }
}
