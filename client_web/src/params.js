// Render and simulation parameters as the protocol defines them (protocol/messages.py):
// defaults, ranges, and merging of partial updates.

export const LIGHTING_DEFAULTS = Object.freeze({
  ambient: 0.25,
  diffuse: 0.7,
  specular: 0.35,
  shininess: 32.0,
  key_light: true,
  ambient_occlusion: false,
  depth_cue: 0.0,
});

export const RENDER_DEFAULTS = Object.freeze({
  mode: "iso",
  sigma_A: 1.5,
  radius_mode: "uniform",
  iso_level: 0.25,
  cutoff_sigmas: 4.0,
  step_sigmas: 0.25,
  transfer_function: Object.freeze([]),
  tf_preset: "cloud",
  color_by: "element",
  uniform_color: Object.freeze([0.85, 0.85, 0.9]),
  lighting: LIGHTING_DEFAULTS,
  background: Object.freeze([0.08, 0.09, 0.11]),
  quality: 1.0,
  jpeg_quality: 85,
  scale_space: "classical",
  warp_strength: 1.0,
  geodesic_smoothing: 0.6,
  density_weights: "uniform",
  level_scale: "mean",
  time_smoothing: "off",
  tau_frames: 3.0,
  time_window: 16,
  time_warp_per_A: 1.0,
  time_kernel: "auto",
  rigid_fit: false,
  layers: Object.freeze([]),
  periodic: "molecules",
  center: "auto",
  center_selection: "protein",
  fit: "off",
  fit_selection: "backbone",
  show_cell: false,
});

export const ENUMS = Object.freeze({
  mode: ["iso", "volume"],
  radius_mode: ["uniform", "vdw"],
  tf_preset: ["cloud", "shells", "iso-like"],
  color_by: ["element", "residue", "chain", "uniform", "bfactor", "charge", "motion"],
  projection: ["perspective", "orthographic"],
  scale_space: ["classical", "geodesic", "carved", "warped"],
  density_weights: ["uniform", "electrons"],
  level_scale: ["mean", "absolute"],
  time_smoothing: ["off", "classical", "warped"],
  time_kernel: ["auto", "causal", "centred"],
  periodic: ["off", "whole", "wrap", "molecules", "unwrap"],
  center: ["off", "auto", "selection"],
  fit: ["off", "translation", "rotation"],
});

/** Numeric ranges [min, max] (inclusive where the protocol allows; open ends nudged in). */
export const RANGES = Object.freeze({
  sigma_A: [0.05, 50],
  iso_level: [0.001, 100],
  cutoff_sigmas: [1, 6],
  step_sigmas: [0.02, 2],
  quality: [0.1, 2],
  jpeg_quality: [10, 100],
  warp_strength: [0, 1],
  geodesic_smoothing: [0.05, 2],
  tau_frames: [0.1, 32],
  time_window: [1, 64],
  time_warp_per_A: [0, 100],
  "lighting.ambient": [0, 1],
  "lighting.diffuse": [0, 1],
  "lighting.specular": [0, 1],
  "lighting.shininess": [1, 512],
  "lighting.depth_cue": [0, 1],
  temperature_K: [0.01, 10000],
  timestep_fs: [0.01, 20],
  friction_per_ps: [0, 1000],
  frame_interval: [1, 1000000],
});

/** The sigma slider's range: a log scale over the scales a chemist looks at. */
export const SIGMA_SLIDER = Object.freeze({ min: 0.3, max: 12 });

export function clamp(x, lo, hi) {
  return Math.min(hi, Math.max(lo, x));
}

/** Clamp a value to the protocol's range for `key`; non-finite values give null. */
export function clampParam(key, value) {
  const v = Number(value);
  if (!Number.isFinite(v)) return null;
  const range = RANGES[key];
  const out = range ? clamp(v, range[0], range[1]) : v;
  return ["jpeg_quality", "frame_interval", "time_window"].includes(key) ? Math.round(out) : out;
}

/** Slider position t in [0, 1] -> sigma (log scale) and back. */
export function sigmaFromSlider(t, { min, max } = SIGMA_SLIDER) {
  return min * (max / min) ** clamp(t, 0, 1);
}
export function sliderFromSigma(sigma, { min, max } = SIGMA_SLIDER) {
  return clamp(Math.log(sigma / min) / Math.log(max / min), 0, 1);
}

function cloneDeep(value) {
  return value === undefined ? undefined : JSON.parse(JSON.stringify(value));
}

/** A full RenderParams from the defaults plus `patch` (lighting merges field by field). */
export function mergeRender(base, patch) {
  const out = cloneDeep(base ?? RENDER_DEFAULTS);
  for (const [key, value] of Object.entries(patch ?? {})) {
    if (value === undefined || value === null || !(key in RENDER_DEFAULTS)) continue;
    if (key === "lighting") out.lighting = { ...out.lighting, ...cloneDeep(value) };
    else out[key] = cloneDeep(value);
  }
  return out;
}

function equalValue(a, b) {
  return JSON.stringify(a) === JSON.stringify(b);
}

/** The fields of `params` that differ from `base` (for `lighting`, the whole object). */
export function diffRender(base, params) {
  const out = {};
  for (const key of Object.keys(RENDER_DEFAULTS)) {
    if (params[key] !== undefined && !equalValue(base[key], params[key])) out[key] = cloneDeep(params[key]);
  }
  return out;
}

/** The scale-space choice a session's value shows as: "warped" is the carved density's name
 * before protocol 1.8 (saved views and recordings still say it). */
export function shownSpace(value) {
  return value === "warped" ? "carved" : value;
}

function describe(value) {
  return typeof value === "string" ? JSON.stringify(value) : String(value);
}

/** What is wrong with a value `key` of the render parameters takes (null: nothing). */
function problemOf(key, value, base) {
  if (Array.isArray(base)) {
    if (!Array.isArray(value)) return `${key} ${describe(value)} is not a list`;
    if (base.length === 3 && typeof base[0] === "number") {
      const ok = value.length === 3 && value.every((v) => typeof v === "number" && v >= 0 && v <= 1);
      return ok ? null : `${key} must be three numbers from 0 to 1`;
    }
    return null; // points and layers: the server checks each one
  }
  if (typeof base === "number") {
    if (typeof value !== "number" || !Number.isFinite(value)) return `${key} ${describe(value)} is not a number`;
    const range = RANGES[key];
    if (range && (value < range[0] || value > range[1])) return `${key} ${value} is outside [${range[0]}, ${range[1]}]`;
    return null;
  }
  if (typeof base === "boolean")
    return typeof value === "boolean" ? null : `${key} ${describe(value)} is not true or false`;
  const choices = ENUMS[key.split(".").pop()];
  if (choices) return choices.includes(value) ? null : `${key} ${describe(value)} is not one of ${choices.join(", ")}`;
  return typeof value === "string" ? null : `${key} ${describe(value)} is not text`;
}

/**
 * Everything wrong with `render`, a whole or partial set of render parameters from a file or a
 * link (unknown keys, wrong types, values out of range), each naming its key; empty when none.
 */
export function renderProblems(render) {
  const problems = [];
  for (const [key, value] of Object.entries(render ?? {})) {
    if (!(key in RENDER_DEFAULTS)) {
      problems.push(`${key} is not a render parameter`);
    } else if (key === "lighting") {
      if (!value || typeof value !== "object" || Array.isArray(value)) {
        problems.push(`lighting ${describe(value)} is not an object`);
        continue;
      }
      for (const [name, v] of Object.entries(value)) {
        if (!(name in LIGHTING_DEFAULTS)) problems.push(`lighting.${name} is not a lighting parameter`);
        else {
          const why = problemOf(`lighting.${name}`, v, LIGHTING_DEFAULTS[name]);
          if (why) problems.push(why);
        }
      }
    } else {
      const why = problemOf(key, value, RENDER_DEFAULTS[key]);
      if (why) problems.push(why);
    }
  }
  return problems;
}

/**
 * Whether the session's `color_by` colours anything drawn: volume mode draws the transfer
 * function's colours, so it applies only to parts drawn as surfaces, sticks or tubes that do not
 * set a colouring of their own (layers).
 */
export function sessionColourApplies(render) {
  const r = render ?? RENDER_DEFAULTS;
  const layers = (r.layers ?? []).filter((layer) => layer.visible !== false);
  if (!layers.length) return r.mode !== "volume";
  return layers.some((layer) => (layer.mode ?? r.mode) !== "volume" && !layer.color_by);
}
