// Shareable state in the URL. The query names the connection (token, role, session); the hash
// holds the render parameters (only those that differ from the defaults) and the camera, in a
// short readable form: #v=1&sigma=2.5&mode=volume&cam=0,0,0,50,1,0,0,0&proj=o&oh=40

import { normalizeCamera } from "./camera.js";
import { ENUMS, RENDER_DEFAULTS, clampParam, mergeRender } from "./params.js";
import { normalizeLayers } from "./layers.js";
import { hexToRgb, normalizePoints, rgbToHex } from "./transfer.js";

export const HASH_VERSION = "1";

/** Hash key -> render parameter path and kind. */
const FIELDS = [
  ["mode", "mode", "enum"],
  ["sigma", "sigma_A", "num"],
  ["radius", "radius_mode", "enum"],
  ["iso", "iso_level", "num"],
  ["cutoff", "cutoff_sigmas", "num"],
  ["step", "step_sigmas", "num"],
  ["preset", "tf_preset", "enum"],
  ["tf", "transfer_function", "tf"],
  ["color", "color_by", "enum"],
  ["ucolor", "uniform_color", "rgb"],
  ["bg", "background", "rgb"],
  ["quality", "quality", "num"],
  ["jpeg", "jpeg_quality", "num"],
  ["amb", "lighting.ambient", "num"],
  ["dif", "lighting.diffuse", "num"],
  ["spec", "lighting.specular", "num"],
  ["shin", "lighting.shininess", "num"],
  ["key", "lighting.key_light", "bool"],
  ["ao", "lighting.ambient_occlusion", "bool"],
  ["cue", "lighting.depth_cue", "num"],
  ["space", "scale_space", "enum"],
  ["warp", "warp_strength", "num"],
  ["smooth", "geodesic_smoothing", "num"],
  ["weights", "density_weights", "enum"],
  ["levels", "level_scale", "enum"],
  ["ts", "time_smoothing", "enum"],
  ["tau", "tau_frames", "num"],
  ["tw", "time_window", "num"],
  ["twarp", "time_warp_per_A", "num"],
  ["tk", "time_kernel", "enum"],
  ["fit", "rigid_fit", "bool"],
  ["layers", "layers", "layers"],
  ["pbc", "periodic", "enum"],
  ["ctr", "center", "enum"],
  ["pfit", "fit", "enum"],
  ["csel", "center_selection", "text"],
  ["fsel", "fit_selection", "text"],
  ["cell", "show_cell", "bool"],
];

/** The longest selection text a link carries (the server checks it again). */
const MAX_TEXT = 2000;

/** A number in at most `digits` significant digits, without trailing zeros. */
export function shortNumber(v, digits = 4) {
  if (!Number.isFinite(v)) return "0";
  if (v === 0) return "0";
  const s = Number(v.toPrecision(digits)).toString();
  return s === "-0" ? "0" : s;
}

function getPath(obj, path) {
  return path.split(".").reduce((o, k) => (o == null ? undefined : o[k]), obj);
}

function encodeValue(kind, value) {
  switch (kind) {
    case "num":
      return shortNumber(value, 4);
    case "bool":
      return value ? "1" : "0";
    case "rgb":
      return rgbToHex(value).slice(1);
    case "tf":
      return value
        .map((p) => `${shortNumber(p.x, 4)}:${rgbToHex(p.color).slice(1)}:${shortNumber(p.alpha, 3)}`)
        .join(",");
    case "layers":
      return encodeURIComponent(JSON.stringify(normalizeLayers(value) ?? []));
    case "text":
      return encodeURIComponent(String(value));
    default:
      return String(value);
  }
}

function decodeValue(kind, path, text) {
  switch (kind) {
    case "num":
      return text.trim() === "" ? null : clampParam(path, Number(text));
    case "bool":
      return text === "1" ? true : text === "0" ? false : null;
    case "rgb":
      return hexToRgb(text);
    case "enum":
      return ENUMS[path]?.includes(text) ? text : null;
    case "tf": {
      if (text === "") return [];
      const points = text.split(",").map((part) => {
        const [x, hex, alpha] = part.split(":");
        const color = hexToRgb(hex ?? "");
        return color ? { x: Number(x), color, alpha: Number(alpha) } : null;
      });
      return points.includes(null) ? null : normalizePoints(points);
    }
    case "layers": {
      try {
        return normalizeLayers(JSON.parse(text));
      } catch {
        return null;
      }
    }
    case "text":
      return text.trim() && text.length <= MAX_TEXT ? text : null;
    default:
      return null;
  }
}

/** Camera as `cam=tx,ty,tz,distance,qw,qx,qy,qz` plus `proj`, `fov`, `oh` when not default. */
function encodeCamera(cam) {
  const c = normalizeCamera(cam);
  const parts = [
    ...c.target.map((v) => shortNumber(v, 6)),
    shortNumber(c.distance, 5),
    ...c.orientation.map((v) => shortNumber(v, 5)),
  ];
  const out = [["cam", parts.join(",")]];
  if (c.projection === "orthographic") out.push(["proj", "o"]);
  if (c.fov_deg !== 40) out.push(["fov", shortNumber(c.fov_deg, 4)]);
  out.push(["oh", shortNumber(c.ortho_height, 5)]);
  return out;
}

function decodeCamera(params) {
  const raw = params.get("cam");
  if (raw === null) return null;
  const v = raw.split(",").map(Number);
  if (v.length !== 8 || !v.every(Number.isFinite)) return null;
  return normalizeCamera({
    target: v.slice(0, 3),
    distance: v[3],
    orientation: v.slice(4, 8),
    projection: params.get("proj") === "o" ? "orthographic" : "perspective",
    fov_deg: params.has("fov") ? Number(params.get("fov")) : 40,
    ortho_height: params.has("oh") ? Number(params.get("oh")) : 40,
  });
}

/** The hash (without '#') for render params (full RenderParams) and an optional camera. */
export function encodeHash({ render = null, camera = null } = {}) {
  const pairs = [["v", HASH_VERSION]];
  if (render) {
    for (const [key, path, kind] of FIELDS) {
      const value = getPath(render, path);
      const base = getPath(RENDER_DEFAULTS, path);
      if (value === undefined || value === null) continue;
      if (encodeValue(kind, value) !== encodeValue(kind, base)) pairs.push([key, encodeValue(kind, value)]);
    }
  }
  if (camera) pairs.push(...encodeCamera(camera));
  return pairs.map(([k, v]) => `${k}=${v}`).join("&");
}

/**
 * Parse a hash. Returns {render, camera, invalid, hasLayers}: `render` is a full RenderParams
 * (defaults plus what the hash names) or null when the hash holds no state; `invalid` lists keys
 * ignored; `hasLayers` says whether the link names layers (layers belong to one system: a link
 * without them keeps the session's).
 */
export function decodeHash(hash) {
  const text = String(hash ?? "").replace(/^#/, "");
  const params = new URLSearchParams(text);
  const invalid = [];
  const hasLayers = params.has("layers");
  if (params.get("v") !== HASH_VERSION) return { render: null, camera: decodeCamera(params), invalid, hasLayers };
  const patch = {};
  const lighting = {};
  for (const [key, path, kind] of FIELDS) {
    if (!params.has(key)) continue;
    const value = decodeValue(kind, path, params.get(key));
    if (value === null) {
      invalid.push(key);
      continue;
    }
    if (path.startsWith("lighting.")) lighting[path.slice(9)] = value;
    else patch[path] = value;
  }
  if (Object.keys(lighting).length) patch.lighting = lighting;
  let camera = null;
  if (params.has("cam")) {
    camera = decodeCamera(params);
    if (!camera) invalid.push("cam");
  }
  return { render: mergeRender(RENDER_DEFAULTS, patch), camera, invalid, hasLayers };
}

/**
 * Connection parameters from the page's query string; `transport` is "jpeg" when the address
 * asks for JPEG images (`?transport=jpeg`), else "auto" (video where the browser decodes it).
 */
export function readQuery(search) {
  const q = new URLSearchParams(String(search ?? "").replace(/^\?/, ""));
  const session = q.get("session");
  return {
    token: q.get("token") || null,
    role: q.get("role") === "viewer" ? "viewer" : "steerer",
    session: session && /^[A-Za-z0-9_.-]{1,64}$/.test(session) ? session : "default",
    transport: q.get("transport") === "jpeg" ? "jpeg" : "auto",
  };
}
