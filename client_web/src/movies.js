// Record movie: a movie of what this view shows, filmed on the server (a job of the batch
// pipeline, `POST /api/sessions/{id}/movies`). Every frame the simulation sends while it records
// is in the movie; a device that renders them slower than they come finishes them after the
// stop, and the button says how far it is. The movie ends with this page (it names itself as
// the owner) unless the page asked to keep its work running, and after MOVIE_MAX_S at most.

import { apiFetch, jobResult, startRecording } from "./api.js";
import { $, downloadBlob, setText } from "./dom.js";
import { formatElapsed } from "./recordings.js";

export const MOVIE_MAX_S = 600;
const POLL_MS = 1000;

/** The button's text for a movie job's description while it records or finishes. */
export function movieLabel(info, elapsedS) {
  const m = info?.movie;
  if (!m || m.recording) return `Stop recording ${formatElapsed(elapsedS)} / ${formatElapsed(m?.max_s ?? MOVIE_MAX_S)}`;
  const left = m.eta_s ? `, about ${formatElapsed(m.eta_s)} left` : "";
  return `Saving… ${info.progress.done} / ${m.taken} frames${left}`;
}

export class MovieButton {
  /** `session()`, `camera()`, `size()` ({width, height}) describe the view; `owner()` names the
   * page (undefined: keep the movie running when the page closes); `steering()` whether this
   * page may start one. */
  constructor({ token, session, camera, size, owner, steering, notify }) {
    Object.assign(this, { token, session, camera, size, owner, steering, notify });
    this.button = $("btn-record");
    this.active = null; // {job, started, timer, info}
    this.saving = false;
    this.button.addEventListener("click", () => (this.active && !this.saving ? this.stop() : this.start()));
  }

  async start() {
    if (this.active) return;
    try {
      const { width, height } = this.size();
      const job = await startRecording({
        token: this.token,
        session: this.session(),
        camera: this.camera(),
        width,
        height,
        maxS: MOVIE_MAX_S,
        owner: this.owner(),
      });
      this.follow(job, performance.now());
      this.notify({ level: "info", code: "record", message: "recording this view on the server" });
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
  }

  /** Show a movie job that records (one this page started, or found again after a reload). */
  follow(info, started) {
    clearInterval(this.active?.timer);
    this.active = { job: info.id, started, info, timer: setInterval(() => this.tick(), POLL_MS / 2), polled: 0 };
    this.button.setAttribute("aria-pressed", "true");
    this.tick();
  }

  /** A movie of this page's session, still recording, that names this page its owner. */
  adopt(jobs, instance, session) {
    if (this.active) return;
    const mine = jobs.find(
      (j) => j.kind === "live" && j.owner === instance && j.session === session && j.movie?.recording,
    );
    if (mine) this.follow(mine, performance.now() - Math.max(0, Date.now() / 1000 - mine.started) * 1000);
  }

  async tick() {
    const active = this.active;
    if (!active || this.saving) return;
    setText(this.button, movieLabel(active.info, (performance.now() - active.started) / 1000));
    if (performance.now() - active.polled < POLL_MS) return;
    active.polled = performance.now();
    try {
      active.info = await (await apiFetch(`/api/jobs/${active.job}`, { token: this.token })).json();
    } catch {
      return; // a lost connection shows elsewhere; the next tick asks again
    }
    if (this.active === active && !active.info.movie?.recording) {
      // ended without this button: its length, another page's Stop, the session closing
      const why = active.info.movie?.ended_because;
      if (why) this.notify({ level: "info", code: "record", message: `the movie stopped taking frames: ${why}` });
      this.finish();
    }
  }

  async stop() {
    if (!this.active) return;
    try {
      const info = await // never DELETE: a movie that ended meanwhile would be deleted, not kept
      (
        await apiFetch(`/api/jobs/${this.active.job}/cancel`, { token: this.token, method: "POST" })
      ).json();
      this.active.info = info;
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    }
    this.finish();
  }

  /** Wait for the frames still waiting to be rendered, then download the movie. */
  async finish() {
    if (!this.active || this.saving) return;
    const { job, timer } = this.active;
    clearInterval(timer);
    this.saving = true;
    this.button.setAttribute("aria-pressed", "false");
    this.button.disabled = true;
    try {
      const onWarning = (message) => this.notify({ level: "warning", code: "record", message });
      const onProgress = (info) => setText(this.button, movieLabel(info, 0));
      const blob = await jobResult({ token: this.token, job, onWarning, onProgress });
      downloadBlob(blob, `scalesteer-${this.session()}-${job}.mp4`);
      this.notify({ level: "info", code: "record", message: "movie downloaded" });
    } catch (err) {
      this.notify({ level: "error", code: "record", message: err.message });
    } finally {
      this.active = null;
      this.saving = false;
      this.button.disabled = !this.steering();
      setText(this.button, "Record movie");
    }
  }
}
