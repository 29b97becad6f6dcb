// Number and unit formatting for the panels.

export function fixed(v, digits = 1, fallback = "–") {
  return Number.isFinite(v) ? v.toFixed(digits) : fallback;
}

/** Significant digits without exponent for ordinary magnitudes. */
export function sig(v, digits = 4, fallback = "–") {
  if (!Number.isFinite(v)) return fallback;
  if (v !== 0 && (Math.abs(v) >= 1e6 || Math.abs(v) < 1e-3)) return v.toExponential(digits - 1);
  return String(Number(v.toPrecision(digits)));
}

export function integer(v, fallback = "–") {
  return Number.isFinite(v) ? Math.round(v).toLocaleString("en-US") : fallback;
}

/** Simulation time in ns from ps. */
export function nanoseconds(ps, fallback = "–") {
  return Number.isFinite(ps) ? `${(ps / 1000).toFixed(4)} ns` : fallback;
}

export function milliseconds(ms, fallback = "–") {
  if (!Number.isFinite(ms)) return fallback;
  return ms >= 100 ? `${Math.round(ms)} ms` : `${ms.toFixed(1)} ms`;
}

/** Position [x, y, z] in angstrom. */
export function position(p, fallback = "–") {
  if (!Array.isArray(p) || p.length !== 3) return fallback;
  return `(${p.map((v) => fixed(v, 2)).join(", ")}) Å`;
}

/** Readable name of an observable key: "potential_kJmol" -> "potential (kJ/mol)". */
export function observableLabel(key) {
  const units = [
    ["_kJmol", "kJ/mol"],
    ["_K", "K"],
    ["_bar", "bar"],
    ["_nm3", "nm³"],
    ["_A3", "Å³"],
    ["_A", "Å"],
    ["_ps", "ps"],
  ];
  for (const [suffix, unit] of units) {
    if (key.endsWith(suffix)) return `${key.slice(0, -suffix.length).replace(/_/g, " ")} (${unit})`;
  }
  return key.replace(/_/g, " ");
}
