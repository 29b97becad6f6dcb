// The REST API from the dashboard: every call carries the page's token, and a refusal becomes an
// Error naming the server's reason (its `detail`).

/** fetch `path` with the token; resolves to the Response, throws with the server's reason. */
export async function apiFetch(path, { token, method = "GET", form = null, json = undefined, fetchImpl = fetch } = {}) {
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  let body = form ?? undefined;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  }
  const response = await fetchImpl(path, { method, body, headers });
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
  return response;
}

/** A FormData of plain values (objects as JSON), skipping null and undefined. */
export function formOf(fields) {
  const form = new FormData();
  for (const [k, v] of Object.entries(fields)) {
    if (v === null || v === undefined) continue;
    if (Array.isArray(v) && (!v.length || v[0] instanceof Blob)) for (const b of v) form.append(k, b, b.name);
    else if (v instanceof Blob) form.append(k, v, v.name);
    else form.append(k, typeof v === "object" ? JSON.stringify(v) : String(v));
  }
  return form;
}

/** Files that hold only coordinates (no atom names): they need a structure beside them. */
export const TRAJECTORY_FILE = /\.(dcd|xtc|trr|nc|ncdf|lammpstrj|lammpsdump)(\.gz|\.bz2)?$/i;

/** The structure and the trajectories among files picked together: the first file that is
 * not a trajectory format is the structure, the others follow it in the order picked (a
 * multi-model PDB plays as a trajectory too). Throws an Error naming the files when none can
 * be the structure. */
export function replayFiles(files) {
  const topology = files.find((f) => !TRAJECTORY_FILE.test(f.name));
  if (!topology)
    throw new Error(
      `${files.map((f) => f.name).join(", ")}: a trajectory holds coordinates only; pick a structure file (PDB, GRO, PSF, mmCIF...) with it`,
    );
  return { topology, trajectory: files.filter((f) => f !== topology) };
}

/** Open a structure alone, or with trajectories, as a replay session (a fresh session name
 * when one of the same files plays already). */
export async function openReplay({ token, files, fps = 30, fetchImpl = fetch }) {
  const { topology, trajectory } = replayFiles(files);
  const form = formOf({ topology, trajectory, fps });
  const response = await apiFetch("/api/replays", { token, method: "POST", form, fetchImpl });
  return response.json();
}

/** Start a movie of a session's frames with this camera and size, taking frames for at most
 * `maxS` seconds and ending when `owner` (this page's instance) leaves; resolves to the job. */
export async function startRecording({
  token,
  session,
  camera,
  width,
  height,
  fps = 30,
  maxS,
  owner,
  fetchImpl = fetch,
}) {
  const form = formOf({ camera, width: Math.round(width), height: Math.round(height), fps, max_s: maxS, owner });
  const path = `/api/sessions/${encodeURIComponent(session)}/movies`;
  const response = await apiFetch(path, { token, method: "POST", form, fetchImpl });
  return response.json();
}

/** Wait for a job to finish and resolve to its output as a Blob (throws with its failure); a
 * finished job's warning (a partial output: fewer frames than its input should have given) goes
 * to `onWarning`, and each answer while it runs to `onProgress`. */
export async function jobResult({
  token,
  job,
  fetchImpl = fetch,
  sleep = (ms) => new Promise((r) => setTimeout(r, ms)),
  onWarning = undefined,
  onProgress = undefined,
}) {
  const path = `/api/jobs/${encodeURIComponent(job)}`;
  for (;;) {
    const info = await (await apiFetch(path, { token, fetchImpl })).json();
    onProgress?.(info);
    if (info.state === "done") {
      if (info.warning && onWarning) onWarning(info.warning);
      break;
    }
    if (!["queued", "running"].includes(info.state)) throw new Error(`the job ${info.state}: ${info.error ?? ""}`);
    await sleep(300);
  }
  return (await apiFetch(`${path}/result`, { token, fetchImpl })).blob();
}
