// Recordings of steered runs: the session's frames and steering, recorded on the server
// (`/api/sessions/{id}/recordings`), listed in the Session panel with what can be done with
// each: replay it (with its steering marks on the timeline), render it to a movie with the
// steering drawn on it, or download its files.

import { apiFetch, jobResult } from "./api.js";
import { $, downloadBlob, el, setText } from "./dom.js";

const POLL_MS = 1000;

/** "1.2 MB" */
export function formatBytes(n) {
  if (n < 1024) return `${n} B`;
  const units = ["kB", "MB", "GB", "TB"];
  let v = n;
  let i = -1;
  do {
    v /= 1024;
    i += 1;
  } while (v >= 1024 && i < units.length - 1);
  return `${v < 10 ? v.toFixed(1) : Math.round(v)} ${units[i]}`;
}

/** "m:ss" */
export function formatElapsed(seconds) {
  const s = Math.max(0, Math.round(seconds));
  return `${Math.floor(s / 60)}:${String(s % 60).padStart(2, "0")}`;
}

export class Recordings {
  /** `session()` names the session, `viewSize()` gives the movie size, `owner()` the page to
   * name as the recording's owner (undefined: keep it running when the page closes), `notify`
   * shows notices. */
  constructor({ token, session, viewSize, owner = () => undefined, notify }) {
    this.token = token;
    this.session = session;
    this.viewSize = viewSize;
    this.owner = owner;
    this.notify = notify;
    this.active = null; // {id, timer, started}
    this.button = $("btn-record-run");
    this.list = $("recordings");
    this.button.addEventListener("click", () => (this.active ? this.stop() : this.start()));
  }

  async start() {
    try {
      const path = `/api/sessions/${encodeURIComponent(this.session())}/recordings`;
      const rec = await (
        await apiFetch(path, { token: this.token, method: "POST", json: { owner: this.owner() } })
      ).json();
      this.follow(rec.id, performance.now());
      this.notify({ level: "info", code: "record", message: "recording this run (frames and steering) on the server" });
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
  }

  follow(id, started) {
    this.active = { id, started, timer: setInterval(() => this.poll(), POLL_MS) };
    this.button.setAttribute("aria-pressed", "true");
    setText(this.button, `Stop run ${formatElapsed((performance.now() - started) / 1000)}`);
  }

  /** A recording of this page's session that names this page its owner (found again after a
   * reload): the button stops it. */
  adopt(recordings, instance) {
    if (this.active) return;
    const mine = recordings.find(
      (r) => r.state === "recording" && r.owner === instance && r.session === this.session(),
    );
    if (mine) this.follow(mine.id, performance.now() - Math.max(0, Date.now() / 1000 - mine.started) * 1000);
  }

  async poll() {
    if (!this.active) return;
    const { id, started } = this.active;
    try {
      const rec = await (await apiFetch(`/api/recordings/${id}`, { token: this.token })).json();
      if (rec.state !== "recording") {
        this.ended(rec);
        return;
      }
      setText(
        this.button,
        `Stop run ${formatElapsed((performance.now() - started) / 1000)} · ${formatBytes(rec.bytes)}`,
      );
    } catch (err) {
      this.notify({ level: "warning", code: "record", message: err.message });
    }
  }

  async stop() {
    if (!this.active) return;
    const { id } = this.active;
    this.button.disabled = true;
    try {
      const rec = await (await apiFetch(`/api/recordings/${id}/stop`, { token: this.token, method: "POST" })).json();
      this.ended(rec);
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    } finally {
      this.button.disabled = false;
    }
  }

  ended(rec) {
    clearInterval(this.active?.timer);
    this.active = null;
    this.button.setAttribute("aria-pressed", "false");
    setText(this.button, "Record run");
    const why =
      rec.state === "capped" ? " (stopped at its size limit)" : rec.ended_because ? ` (${rec.ended_because})` : "";
    this.notify({
      level: "info",
      code: "record",
      message: `recorded ${rec.frames} frames, ${formatBytes(rec.bytes)}${why}`,
    });
    if (rec.warning) this.notify({ level: "warning", code: "record", message: rec.warning });
    // show where the new recording can be replayed, filmed or downloaded
    $("panel-session").open = true;
    this.refresh().then(() => this.list.scrollIntoView({ block: "nearest" }));
  }

  async refresh() {
    let recs;
    try {
      recs = await (await apiFetch("/api/recordings", { token: this.token })).json();
    } catch {
      this.list.replaceChildren(); // viewers may not list recordings
      return;
    }
    this.list.replaceChildren(
      ...recs.map((rec) => {
        const when = new Date(rec.started * 1000).toLocaleTimeString();
        const label = `${rec.session} ${when} · ${rec.frames} frames · ${formatBytes(rec.bytes)}${rec.state === "recording" ? " · recording" : ""}`;
        const actions =
          rec.state === "recording" || !rec.frames
            ? []
            : [
                this.action("Replay", `Replay ${rec.id}`, () => this.replay(rec)),
                this.action("Movie", `Render ${rec.id} to an MP4 with its steering`, () => this.movie(rec)),
                this.action("Download", `Download ${rec.id} (PDB, XTC, steering log)`, () => this.download(rec)),
              ];
        return el("li", { "data-recording": rec.id }, [el("span", { text: label }), ...actions]);
      }),
    );
  }

  action(text, label, run) {
    const button = el("button", { type: "button", text, "aria-label": label });
    button.addEventListener("click", run);
    return button;
  }

  async replay(rec) {
    try {
      const opened = await (
        await apiFetch(`/api/recordings/${rec.id}/replay`, { token: this.token, method: "POST" })
      ).json();
      const url = new URL(window.location.href);
      url.searchParams.set("session", opened.session);
      url.hash = "";
      window.location.assign(url.toString());
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
  }

  async movie(rec) {
    const { width, height } = this.viewSize();
    this.notify({ level: "info", code: "record", message: `rendering ${rec.frames} frames to an MP4…` });
    try {
      const job = await (
        await apiFetch(`/api/recordings/${rec.id}/movie`, {
          token: this.token,
          method: "POST",
          json: { width, height },
        })
      ).json();
      const onWarning = (message) => this.notify({ level: "warning", code: "record", message });
      downloadBlob(await jobResult({ token: this.token, job: job.id, onWarning }), `scalesteer-${rec.id}.mp4`);
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
  }

  async download(rec) {
    try {
      downloadBlob(
        await (await apiFetch(`/api/recordings/${rec.id}/download`, { token: this.token })).blob(),
        `${rec.id}.zip`,
      );
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
  }
}
