// Full-resolution screenshots through the REST API: POST /api/render renders the session's
// latest frame with the given camera and render parameters and returns a PNG.

/** Request a PNG; resolves to a Blob or throws an Error naming the server's reason. */
export async function requestScreenshot({ token, session, width, height, params, camera, fetchImpl = fetch }) {
  const form = new FormData();
  form.append("session", session);
  form.append("width", String(Math.round(width)));
  form.append("height", String(Math.round(height)));
  form.append("format", "png");
  if (params) form.append("params", JSON.stringify(params));
  if (camera) form.append("camera", JSON.stringify(camera));
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  const response = await fetchImpl("/api/render", { method: "POST", body: form, headers });
  if (!response.ok) {
    let detail = response.statusText;
    try {
      const body = await response.json();
      detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail ?? body);
    } catch {
      /* not JSON: keep the status text */
    }
    const err = new Error(`HTTP ${response.status}: ${detail}`);
    err.status = response.status;
    throw err;
  }
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
