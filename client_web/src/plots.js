// Live plots with uPlot: temperature, potential energy, render rate and steer-to-photon
// latency over a sliding window, redrawn a few times a second, exported together as CSV.

import uPlot from "uplot";

import { el, setText } from "./dom.js";
import { sig } from "./format.js";
import { SeriesTable, toCSV } from "./timeseries.js";

const REDRAW_MS = 250;

const PLOTS = [
  {
    id: "plot-temperature",
    columns: ["temperature_K", "target_temperature_K"],
    labels: ["T (K)", "target (K)"],
    keys: ["T", "target"],
    colors: ["#e06c5a", "#9aa3b2"],
    dash: [null, [4, 4]],
    unit: "K",
  },
  {
    id: "plot-energy",
    columns: ["potential_kJmol"],
    labels: ["potential (kJ/mol)"],
    keys: ["potential"],
    colors: ["#5b9bd5"],
    dash: [null],
    unit: "kJ/mol",
  },
  {
    id: "plot-fps",
    columns: ["render_fps", "shown_fps"],
    labels: ["rendered (fps)", "shown here (fps)"],
    keys: ["rendered", "shown here"],
    colors: ["#ffd166", "#c792ea"],
    dash: [null, null],
    unit: "fps",
  },
  {
    id: "plot-latency",
    columns: ["latency_ms"],
    labels: ["latency (ms)"],
    keys: ["steer → photon"],
    colors: ["#7fb6ea"],
    dash: [null],
    unit: "ms",
    points: true,
  },
];

function clockTime(t) {
  const d = new Date(t * 1000);
  return [d.getHours(), d.getMinutes(), d.getSeconds()].map((v) => String(v).padStart(2, "0")).join(":");
}

export class Plots {
  constructor({ windowS = 300 } = {}) {
    this.windowS = windowS;
    this.plots = PLOTS.map((spec) => this.create(spec));
    this.timer = null;
    this.lastStep = null;
  }

  create(spec) {
    const figure = document.getElementById(spec.id);
    const body = figure.querySelector(".plot-body");
    const table = new SeriesTable(spec.columns, { windowS: this.windowS });
    const axis = {
      stroke: "#9aa3b2",
      grid: { stroke: "#2b313a", width: 1 },
      ticks: { stroke: "#2b313a", width: 1 },
      font: "11px system-ui",
    };
    const opts = {
      width: Math.max(120, body.clientWidth),
      height: Math.max(60, body.clientHeight),
      legend: { show: false },
      cursor: { drag: { x: false, y: false } },
      scales: {
        x: {
          time: true,
          range: () => {
            // from the oldest point (at least 20 s back) to now, at most the window
            const now = Date.now() / 1000;
            const oldest = Math.min(now - 20, ...(this.plots ?? []).map((p) => p.table.t[0] ?? now));
            return [Math.max(now - this.windowS, oldest), now];
          },
        },
      },
      axes: [
        { ...axis, space: 70, values: (u, vals) => vals.map(clockTime) },
        { ...axis, size: 48, values: (u, vals) => vals.map((v) => sig(v, 3)) },
      ],
      series: [
        {},
        ...spec.columns.map((_, k) => ({
          label: spec.labels[k],
          stroke: spec.colors[k],
          width: 1.5,
          dash: spec.dash[k] ?? undefined,
          spanGaps: true,
          points: { show: Boolean(spec.points), size: 4 },
        })),
      ],
    };
    const chart = new uPlot(opts, table.data(), body);
    new ResizeObserver(() => {
      const w = Math.max(120, Math.floor(body.clientWidth));
      const h = Math.max(60, Math.floor(body.clientHeight));
      if (w !== chart.width || h !== chart.height) chart.setSize({ width: w, height: h });
    }).observe(body);
    const legend = el("div", { className: "plot-keys", "aria-hidden": "true" });
    spec.keys.forEach((key, k) =>
      legend.append(
        el("span", { className: spec.dash[k] ? "key dashed" : "key", style: `--c:${spec.colors[k]}`, text: key }),
      ),
    );
    figure.insertBefore(legend, body);
    figure.setAttribute(
      "aria-label",
      `${figure.querySelector("figcaption span").textContent}: ${spec.labels.join(", ")}`,
    );
    return { spec, figure, table, chart, last: figure.querySelector(".plot-last") };
  }

  byId(id) {
    return this.plots.find((p) => p.spec.id === id);
  }

  push(id, t, values) {
    const plot = this.byId(id);
    plot.table.push(t, values);
    this.schedule();
  }

  /** A simulation status update (observables), once per new step. */
  pushSim(sim, targetTemperature, t = Date.now() / 1000) {
    if (!sim || sim.step === this.lastStep) return;
    this.lastStep = sim.step;
    const obs = sim.observables ?? {};
    if (Number.isFinite(obs.temperature_K)) {
      this.push("plot-temperature", t, { temperature_K: obs.temperature_K, target_temperature_K: targetTemperature });
    }
    if (Number.isFinite(obs.potential_kJmol)) {
      this.push("plot-energy", t, { potential_kJmol: obs.potential_kJmol });
    }
  }

  pushStats(stats, shownFps, t = Date.now() / 1000) {
    this.push("plot-fps", t, { render_fps: stats.render_fps, shown_fps: shownFps });
  }

  pushLatency(ms, t = Date.now() / 1000) {
    this.push("plot-latency", t, { latency_ms: ms });
  }

  schedule() {
    if (this.timer !== null) return;
    this.timer = setTimeout(() => {
      this.timer = null;
      this.redraw();
    }, REDRAW_MS);
  }

  redraw() {
    const now = Date.now() / 1000;
    // every plot, not only those with new points: their time axes end now together (the
    // latency plot, which gains a point only when a steer is shown, lagged the others)
    for (const plot of this.plots) {
      plot.table.prune(now);
      plot.chart.setData(plot.table.data());
      plot.figure.dataset.points = String(plot.table.length);
      const v = plot.table.last(plot.spec.columns[0]);
      setText(plot.last, v === null ? "–" : `${sig(v, 4)} ${plot.spec.unit}`);
    }
  }

  setWindow(windowS) {
    this.windowS = windowS;
    const now = Date.now() / 1000;
    for (const plot of this.plots) plot.table.setWindow(windowS, now);
    this.redraw();
  }

  clear() {
    for (const plot of this.plots) plot.table.clear();
    this.lastStep = null;
    this.redraw();
  }

  csv() {
    return toCSV(this.plots.map((p) => p.table));
  }
}
