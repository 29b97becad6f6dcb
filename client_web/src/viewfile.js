// A whole session view as a small JSON file: camera, render parameters and the picked atoms,
// saved from the dashboard and opened again later (or by someone else, in another session of
// the same system).

import { cameraProblems } from "./camera.js";
import { renderProblems } from "./params.js";

export const VIEW_FILE_VERSION = 1;

/** The JSON object of a view. */
export function viewFile({ session, camera, render, atoms = [], savedAt = new Date() }) {
  return {
    scalesteer_view: VIEW_FILE_VERSION,
    saved_at: savedAt.toISOString(),
    session,
    camera,
    render_params: render,
    atoms,
  };
}

/** Read a view file's text; throws an Error naming what is wrong with it. */
export function readViewFile(text) {
  let data;
  try {
    data = JSON.parse(text);
  } catch (err) {
    throw new Error(`not a view file: ${err.message}`);
  }
  if (!data || typeof data !== "object" || data.scalesteer_view === undefined) {
    throw new Error("not a view file: it has no scalesteer_view field");
  }
  if (data.scalesteer_view > VIEW_FILE_VERSION) {
    throw new Error(`view file version ${data.scalesteer_view} is newer than this dashboard (${VIEW_FILE_VERSION})`);
  }
  const camera = data.camera && typeof data.camera === "object" ? data.camera : null;
  const render = data.render_params && typeof data.render_params === "object" ? data.render_params : null;
  const atoms = Array.isArray(data.atoms) ? data.atoms.filter((a) => Number.isInteger(a) && a >= 0).slice(0, 4) : [];
  if (!camera && !render) throw new Error("the view file has neither a camera nor render parameters");
  // a damaged file is refused whole, every problem named: nothing of it half-applied
  const problems = [
    ...(camera ? cameraProblems(camera) : []),
    ...(render ? renderProblems(render).map((why) => `render_params.${why}`) : []),
  ];
  if (problems.length) throw new Error(`the view file was not applied: ${problems.join("; ")}`);
  return { session: typeof data.session === "string" ? data.session : null, camera, render, atoms };
}

/** A file name for a view of `session`. */
export function viewFileName(session, now = new Date()) {
  const stamp = now
    .toISOString()
    .replace(/[:]/g, "")
    .replace(/\.\d+Z$/, "Z");
  return `scalesteer-view-${session}-${stamp}.json`;
}
