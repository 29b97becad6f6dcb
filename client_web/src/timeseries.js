// Time series for the live plots: rows of (time, values...) over a sliding window, laid out as
// the column arrays uPlot draws, and exported together as one CSV.

/** One plot's data: a time column (unix seconds) and named value columns. */
export class SeriesTable {
  constructor(names, { windowS = 300, maxRows = 20000 } = {}) {
    this.names = [...names];
    this.windowS = windowS;
    this.maxRows = maxRows;
    this.t = [];
    this.cols = this.names.map(() => []);
  }

  /** Append a row; `values` maps column names to numbers (others stay empty). */
  push(t, values) {
    if (!Number.isFinite(t)) return;
    if (this.t.length && t < this.t[this.t.length - 1]) return; // keep time ascending
    this.t.push(t);
    this.names.forEach((name, k) => {
      const v = values[name];
      this.cols[k].push(Number.isFinite(v) ? v : null);
    });
    this.prune(t);
  }

  /** Drop rows older than the window (relative to `now`) and beyond the row cap. */
  prune(now) {
    let cut = 0;
    while (cut < this.t.length && now - this.t[cut] > this.windowS) cut++;
    cut = Math.max(cut, this.t.length - this.maxRows);
    if (cut > 0) {
      this.t.splice(0, cut);
      for (const col of this.cols) col.splice(0, cut);
    }
  }

  setWindow(windowS, now) {
    this.windowS = windowS;
    this.prune(now);
  }

  get length() {
    return this.t.length;
  }

  /** Latest finite value of a column, or null. */
  last(name) {
    const col = this.cols[this.names.indexOf(name)];
    if (!col) return null;
    for (let i = col.length - 1; i >= 0; i--) if (col[i] !== null) return col[i];
    return null;
  }

  /** Data in uPlot's layout: [times, column 1, column 2, ...]. */
  data() {
    return [this.t, ...this.cols];
  }

  clear() {
    this.t = [];
    this.cols = this.names.map(() => []);
  }
}

function csvCell(v) {
  if (v === null || v === undefined) return "";
  if (typeof v === "number") return Number.isFinite(v) ? String(v) : "";
  const s = String(v);
  return /[",\n]/.test(s) ? `"${s.replace(/"/g, '""')}"` : s;
}

/**
 * One CSV of several tables: a `time_unix_s` column, then each table's columns (named
 * `column`); rows merged by time, cells empty where a table has no row at that time.
 */
export function toCSV(tables) {
  const header = ["time_unix_s"];
  const rows = new Map();
  let offset = 0;
  for (const table of tables) {
    header.push(...table.names);
    table.t.forEach((t, i) => {
      let row = rows.get(t);
      if (!row) rows.set(t, (row = []));
      table.cols.forEach((col, k) => {
        row[offset + k] = col[i];
      });
    });
    offset += table.names.length;
  }
  const lines = [header.map(csvCell).join(",")];
  for (const t of [...rows.keys()].sort((a, b) => a - b)) {
    const row = rows.get(t);
    const cells = [t.toFixed(3)];
    for (let k = 0; k < offset; k++) cells.push(csvCell(row[k]));
    lines.push(cells.join(","));
  }
  return `${lines.join("\n")}\n`;
}
