// The transfer function: control points {x, color [r,g,b], alpha} over density, with x in units
// of the iso level (x = 1 is the iso surface). Pure editing maths for the editor in tfeditor.js.

import { clamp } from "./params.js";

/** The editor's default density range (iso-level units); it widens to show farther points. */
export const TF_DOMAIN = Object.freeze([0, 4]);
/** The range the server's density histogram covers at least (wider in volume mode). */
export const HISTOGRAM_X_MAX = 3;
/** Minimum gap kept between neighbouring control points. */
export const MIN_GAP = 0.005;
export const MIN_POINTS = 2;
export const MAX_POINTS = 64;

const preset = (rows) =>
  Object.freeze(rows.map(([x, color, alpha]) => Object.freeze({ x, color: Object.freeze(color), alpha })));

/** The server's presets (server/render/transfer.py), shown when the session uses one. */
export const PRESETS = Object.freeze({
  cloud: preset([
    [0.0, [0.25, 0.45, 0.95], 0.0],
    [0.15, [0.25, 0.45, 0.95], 0.0],
    [0.5, [0.45, 0.65, 1.0], 0.06],
    [1.0, [0.8, 0.88, 1.0], 0.2],
    [2.0, [1.0, 1.0, 1.0], 0.45],
    [4.0, [1.0, 0.95, 0.85], 0.7],
  ]),
  shells: preset([
    [0.0, [0.2, 0.45, 1.0], 0.0],
    [0.25, [0.2, 0.45, 1.0], 0.0],
    [0.5, [0.2, 0.5, 1.0], 0.12],
    [0.75, [0.3, 0.8, 0.7], 0.0],
    [1.0, [0.3, 1.0, 0.4], 0.3],
    [1.3, [0.8, 0.7, 0.3], 0.0],
    [1.6, [1.0, 0.35, 0.2], 0.0],
    [2.0, [1.0, 0.35, 0.2], 0.7],
    [2.4, [1.0, 0.35, 0.2], 0.0],
  ]),
  "iso-like": preset([
    [0.0, [0.85, 0.85, 0.9], 0.0],
    [0.95, [0.85, 0.85, 0.9], 0.0],
    [1.0, [0.85, 0.85, 0.9], 1.0],
    [2.0, [0.85, 0.85, 0.9], 1.0],
  ]),
});

/** The editor's range for a set of points: the default, widened to the farthest point. */
export function domainFor(points) {
  const far = Math.max(0, ...points.map((p) => p.x));
  return [TF_DOMAIN[0], Math.max(TF_DOMAIN[1], Math.ceil(far))];
}

/**
 * The density range the server's histogram spans: [0, 3] iso levels, widened in volume mode
 * to the transfer function's last point.
 */
export function histogramRange(mode, points) {
  const far = points.length ? Math.max(...points.map((p) => p.x)) : 0;
  return [0, Math.max(HISTOGRAM_X_MAX, mode === "volume" ? far : 0)];
}

function copyPoint(p) {
  return { x: p.x, color: [p.color[0], p.color[1], p.color[2]], alpha: p.alpha };
}

/** The control points of a preset (copies). */
export function presetPoints(name) {
  return (PRESETS[name] ?? PRESETS.cloud).map(copyPoint);
}

/** Sanitise points: finite, clamped, sorted by x, at most MAX_POINTS, defaults filled in. */
export function normalizePoints(points) {
  const out = [];
  for (const p of points ?? []) {
    const x = Number(p?.x);
    if (!Number.isFinite(x)) continue;
    const c = Array.isArray(p.color) && p.color.length === 3 ? p.color : [1, 1, 1];
    out.push({
      x: Math.max(0, x),
      color: c.map((v) => clamp(Number.isFinite(Number(v)) ? Number(v) : 1, 0, 1)),
      alpha: clamp(Number.isFinite(Number(p.alpha)) ? Number(p.alpha) : 0, 0, 1),
    });
  }
  out.sort((a, b) => a.x - b.x);
  return out.slice(0, MAX_POINTS);
}

/** Opacity and colour at density x: piecewise linear between points, constant beyond them. */
export function evaluate(points, x) {
  if (!points.length) return { alpha: 0, color: [1, 1, 1] };
  if (x <= points[0].x) return { alpha: points[0].alpha, color: [...points[0].color] };
  const last = points[points.length - 1];
  if (x >= last.x) return { alpha: last.alpha, color: [...last.color] };
  let i = 1;
  while (points[i].x < x) i++;
  const a = points[i - 1];
  const b = points[i];
  const t = b.x > a.x ? (x - a.x) / (b.x - a.x) : 0;
  const lerp = (u, v) => u + (v - u) * t;
  return { alpha: lerp(a.alpha, b.alpha), color: a.color.map((c, k) => lerp(c, b.color[k])) };
}

/** Move point i to (x, alpha), kept between its neighbours and inside the domain. */
export function movePoint(points, i, x, alpha, domain = TF_DOMAIN) {
  if (i < 0 || i >= points.length) return points.map(copyPoint);
  const lo = i > 0 ? points[i - 1].x + MIN_GAP : domain[0];
  const hi = i < points.length - 1 ? points[i + 1].x - MIN_GAP : domain[1];
  const out = points.map(copyPoint);
  out[i].x = lo <= hi ? clamp(x, lo, hi) : points[i].x;
  out[i].alpha = clamp(alpha, 0, 1);
  return out;
}

/** Insert a point at density x (opacity given or interpolated; colour interpolated). */
export function insertPoint(points, x, alpha = null, domain = TF_DOMAIN) {
  if (points.length >= MAX_POINTS) return { points: points.map(copyPoint), index: -1 };
  const cx = clamp(x, domain[0], domain[1]);
  if (points.some((p) => Math.abs(p.x - cx) < MIN_GAP)) return { points: points.map(copyPoint), index: -1 };
  const here = evaluate(points, cx);
  const point = { x: cx, color: here.color, alpha: alpha === null ? here.alpha : clamp(alpha, 0, 1) };
  const out = points.map(copyPoint);
  let index = out.findIndex((p) => p.x > cx);
  if (index < 0) index = out.length;
  out.splice(index, 0, point);
  return { points: out, index };
}

/** Remove point i, keeping at least MIN_POINTS. */
export function removePoint(points, i) {
  if (points.length <= MIN_POINTS || i < 0 || i >= points.length) return points.map(copyPoint);
  return points.filter((_, k) => k !== i).map(copyPoint);
}

/** Set the colour of point i. */
export function recolorPoint(points, i, color) {
  const out = points.map(copyPoint);
  if (out[i]) out[i].color = color.map((v) => clamp(v, 0, 1));
  return out;
}

/** Editor box {left, top, width, height} in pixels: data -> pixel and back. */
export function toScreen(point, box, domain = TF_DOMAIN) {
  const u = (point.x - domain[0]) / (domain[1] - domain[0]);
  return [box.left + u * box.width, box.top + (1 - point.alpha) * box.height];
}
export function fromScreen(px, py, box, domain = TF_DOMAIN) {
  const u = clamp((px - box.left) / box.width, 0, 1);
  const v = clamp((py - box.top) / box.height, 0, 1);
  return { x: domain[0] + u * (domain[1] - domain[0]), alpha: 1 - v };
}

/** Index of the point nearest (px, py) within `radius` pixels, or -1. */
export function nearestPoint(points, px, py, box, radius = 10, domain = TF_DOMAIN) {
  let best = -1;
  let bestD = radius * radius;
  points.forEach((p, i) => {
    const [sx, sy] = toScreen(p, box, domain);
    const d = (sx - px) ** 2 + (sy - py) ** 2;
    if (d <= bestD) {
      best = i;
      bestD = d;
    }
  });
  return best;
}

/** The opacity curve as an SVG path through the points across the whole domain. */
export function curvePath(points, box, domain = TF_DOMAIN) {
  if (!points.length) return "";
  const xs = [domain[0], ...points.map((p) => p.x).filter((x) => x > domain[0] && x < domain[1]), domain[1]];
  return xs
    .map((x, k) => {
      const [sx, sy] = toScreen({ x, alpha: evaluate(points, x).alpha }, box, domain);
      return `${k ? "L" : "M"}${sx.toFixed(1)},${sy.toFixed(1)}`;
    })
    .join(" ");
}

/**
 * Histogram bars over the box: `counts` are bins spread evenly over `range` (density), drawn
 * on the editor's `domain` and scaled by log(1 + count) so both the sparse dense core and the
 * vast empty space stay visible.
 */
export function histogramBars(counts, box, range = [0, HISTOGRAM_X_MAX], domain = TF_DOMAIN) {
  const values = Array.from(counts ?? [], (c) => (Number.isFinite(c) && c > 0 ? Math.log1p(c) : 0));
  const peak = Math.max(0, ...values);
  if (!values.length || peak <= 0) return [];
  const span = domain[1] - domain[0];
  const binX = (range[1] - range[0]) / values.length;
  const bars = [];
  values.forEach((v, i) => {
    const x0 = range[0] + i * binX;
    if (x0 >= domain[1]) return;
    const x1 = Math.min(domain[1], x0 + binX);
    const h = (v / peak) * box.height;
    const left = box.left + ((x0 - domain[0]) / span) * box.width;
    bars.push({ x: left, y: box.top + box.height - h, width: ((x1 - x0) / span) * box.width, height: h });
  });
  return bars;
}

export function rgbToHex(rgb) {
  return `#${rgb
    .map((v) =>
      Math.round(clamp(Number(v) || 0, 0, 1) * 255)
        .toString(16)
        .padStart(2, "0"),
    )
    .join("")}`;
}

export function hexToRgb(hex) {
  const m = /^#?([0-9a-f]{6})$/i.exec(String(hex).trim());
  if (!m) return null;
  const n = parseInt(m[1], 16);
  return [(n >> 16) & 255, (n >> 8) & 255, n & 255].map((v) => Math.round((v / 255) * 1000) / 1000);
}
