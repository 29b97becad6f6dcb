// What runs on the server: recordings of runs, movies of live sessions and batch jobs, listed
// in the Session panel with Stop or Cancel, whoever started them. The page names itself (a
// random instance per browser tab, kept across reloads) as the owner of what it starts, so the
// server ends that work once the tab has closed (docs/server.md, "Work that ends with its page").

import { apiFetch } from "./api.js";
import { $, el, setText } from "./dom.js";
import { formatBytes } from "./recordings.js";

const POLL_MS = 2000;
const INSTANCE_KEY = "scalesteer.instance";
const KEEP_KEY = "scalesteer.keepRunning";

/** This tab's identity across its reconnections and reloads (random, in sessionStorage: a new
 * tab is a new page, a reload the same one). */
export function pageInstance(storage = globalThis.sessionStorage, random = () => globalThis.crypto.randomUUID()) {
  let id = null;
  try {
    id = storage?.getItem(INSTANCE_KEY) ?? null;
  } catch {
    /* storage refused (a sandboxed page): a fresh one per load */
  }
  if (!id || !/^[A-Za-z0-9-]{8,64}$/.test(id)) {
    id = `page-${random()}`.slice(0, 64);
    try {
      storage?.setItem(INSTANCE_KEY, id);
    } catch {
      /* see above */
    }
  }
  return id;
}

/** The rows of the list: [{id, kind, label, mine, actions: [{text, title, method, path}]}]. */
export function runningWork(jobs, recordings, instance) {
  const rows = [];
  for (const rec of recordings) {
    if (rec.state !== "recording") continue;
    const mine = rec.owner === instance;
    rows.push({
      id: rec.id,
      kind: "recording",
      mine,
      label: `recording ${rec.session} · ${rec.frames} frames · ${formatBytes(rec.bytes)}${owned(rec.owner, mine)}`,
      actions: [
        {
          text: "Stop",
          title: `Stop recording ${rec.id}, keeping it`,
          method: "POST",
          path: `/api/recordings/${rec.id}/stop`,
        },
      ],
    });
  }
  for (const job of jobs) {
    if (job.state !== "queued" && job.state !== "running") continue;
    const mine = job.owner === instance;
    const { done, total } = job.progress;
    const path = `/api/jobs/${job.id}`;
    if (job.kind === "live") {
      const m = job.movie ?? {};
      const stage = m.recording ? `${m.taken} frames taken, ${done} rendered` : `rendering ${done} / ${m.taken}`;
      const actions = m.recording
        ? [
            {
              text: "Stop",
              title: `Stop movie ${job.id}; the frames taken are rendered and kept`,
              // never DELETE: a movie that ended meanwhile would be deleted, not kept
              method: "POST",
              path: `${path}/cancel`,
            },
          ]
        : [];
      actions.push({
        text: "Cancel",
        title: `Cancel movie ${job.id}, discarding it`,
        method: "DELETE",
        path,
        cancel: true,
      });
      rows.push({
        id: job.id,
        kind: "movie",
        mine,
        label: `movie of ${job.session} · ${stage}${owned(job.owner, mine)}`,
        actions,
      });
    } else {
      const what = job.kind === "recording" ? "movie of a recorded run" : "trajectory job";
      const progress = total ? `${done} / ${total} frames` : (job.stage ?? job.state);
      rows.push({
        id: job.id,
        kind: "job",
        mine,
        label: `${what} · ${progress}`,
        actions: [{ text: "Cancel", title: `Cancel job ${job.id}`, method: "POST", path: `${path}/cancel` }],
      });
    }
  }
  return rows;
}

function owned(owner, mine) {
  if (mine) return " · this page";
  return owner ? " · another page" : " · kept running";
}

/** The Session panel's "Running on the server" list, polled while this page may steer. */
export class RunningWork {
  constructor({ token, instance, notify, onUpdate = () => {} }) {
    Object.assign(this, { token, instance, notify, onUpdate });
    this.list = $("running-work");
    this.keep = $("keep-running");
    this.timer = null;
    this.jobs = [];
    this.recordings = [];
    try {
      this.keep.checked = globalThis.localStorage?.getItem(KEEP_KEY) === "1";
    } catch {
      /* no storage: unticked */
    }
    this.keep.addEventListener("change", () => {
      try {
        globalThis.localStorage?.setItem(KEEP_KEY, this.keep.checked ? "1" : "0");
      } catch {
        /* no storage: this page only */
      }
    });
  }

  /** The owner to name in a request: this page, unless it asked to keep its work running. */
  owner() {
    return this.keep.checked ? undefined : this.instance;
  }

  start() {
    if (this.timer === null) this.timer = setInterval(() => this.refresh(), POLL_MS);
    return this.refresh();
  }

  stop() {
    clearInterval(this.timer);
    this.timer = null;
    this.list.replaceChildren();
  }

  async refresh() {
    try {
      const [jobs, recordings] = await Promise.all([
        apiFetch("/api/jobs?active=true", { token: this.token }).then((r) => r.json()),
        apiFetch("/api/recordings", { token: this.token }).then((r) => r.json()),
      ]);
      this.jobs = jobs;
      this.recordings = recordings;
    } catch {
      return; // a viewer may not list them; a lost connection shows elsewhere
    }
    const rows = runningWork(this.jobs, this.recordings, this.instance);
    setText($("running-work-empty"), rows.length ? "" : "nothing");
    this.list.replaceChildren(
      ...rows.map((row) =>
        el("li", { "data-work": row.id, "data-kind": row.kind, className: row.mine ? "mine" : "" }, [
          el("span", { text: row.label }),
          ...row.actions.map((a) => this.button(row, a)),
        ]),
      ),
    );
    this.onUpdate(this);
  }

  button(row, action) {
    const button = el("button", { type: "button", text: action.text, title: action.title, "aria-label": action.title });
    button.addEventListener("click", async () => {
      button.disabled = true;
      try {
        // a live movie's DELETE stops it the first time and cancels it once it stopped
        if (action.cancel && row.kind === "movie") await this.cancelMovie(action.path);
        else await apiFetch(action.path, { token: this.token, method: action.method });
      } catch (err) {
        this.notify({ level: "error", code: "work", message: err.message });
      }
      await this.refresh();
    });
    return button;
  }

  async cancelMovie(path) {
    const info = await (await apiFetch(path, { token: this.token, method: "DELETE" })).json();
    if (info.finishing) await apiFetch(path, { token: this.token, method: "DELETE" });
  }
}
