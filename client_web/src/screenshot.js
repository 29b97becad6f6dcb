// Full-resolution screenshots through the REST API: POST /api/render renders the session's
// latest frame with the given camera and render parameters and returns a PNG.

import { apiFetch, formOf } from "./api.js";

/** Request a PNG; resolves to a Blob or throws an Error naming the server's reason. */
export async function requestScreenshot({ token, session, width, height, params, camera, fetchImpl = fetch }) {
  const form = formOf({
    session,
    width: Math.round(width),
    height: Math.round(height),
    format: "png",
    params,
    camera,
  });
  const response = await apiFetch("/api/render", { token, method: "POST", form, fetchImpl });
  return response.blob();
}

/** File name for a screenshot of `session` at simulation `step`. */
export function screenshotName(session, step, now = new Date()) {
  const stamp = now
    .toISOString()
    .replace(/[:]/g, "")
    .replace(/\.\d+Z$/, "Z");
  return `scalesteer-${session}-step${Number.isFinite(step) ? step : 0}-${stamp}.png`;
}
