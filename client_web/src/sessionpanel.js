// The session panel: the simulation's summary, who is connected, the active pulls, and the
// connection's and the server's figures, refreshed each second.

import { ConnState } from "./connection.js";
import { $, el, setText } from "./dom.js";
import { integer, milliseconds, nanoseconds, position, sig } from "./format.js";
import { describeStream } from "./video.js";

export class DashboardSessionPanel {
  showSimSummary() {
    const s = this.sim;
    if (!s) return;
    const parts = [s.state];
    if (s.state !== "waiting") parts.push(`step ${integer(s.step)}`, nanoseconds(s.time_ps));
    if (s.state === "running") parts.push(`${integer(s.steps_per_s)} steps/s`);
    setText($("sim-summary"), `simulation ${parts.join(" · ")}`);
  }

  showClients() {
    const me = this.welcome?.client_id;
    $("clients").replaceChildren(
      ...this.clients.map((c) =>
        el("li", { "data-role": c.role, "data-client": c.client_id }, [
          el("span", {
            className: c.client_id === me ? "you" : "",
            text: `${c.client || "client"}${c.client_id === me ? " (you)" : ""}`,
          }),
          el("span", { className: "meta", text: c.client_id }),
          el("span", { className: "role", text: c.role }),
        ]),
      ),
    );
  }

  showPulling() {
    const list = this.pulling.map((p) => `atom ${p.atom}${p.target ? ` → ${position(p.target)}` : ""}`);
    setText($("pulling-list"), list.length ? `pulling: ${list.join("; ")}` : "no active pulls");
  }

  showSession() {
    const s = this.connection?.status();
    if (!s) return;
    let conn = s.state;
    if (s.state === ConnState.RECONNECTING && s.retryAt) {
      const secs = Math.max(0, Math.ceil((s.retryAt - Date.now()) / 1000));
      conn = `reconnecting in ${secs} s (attempt ${s.attempt})`;
      setText($("conn-text"), `reconnecting in ${secs} s`);
    }
    if (s.reason && s.state !== ConnState.READY) conn += `: ${s.reason}`;
    setText($("session-conn"), conn);
    setText($("session-id"), this.welcome?.session_id ?? this.sessionName);
    setText($("session-you"), this.welcome ? `${this.welcome.client_id}, ${this.role}` : "–");
    const perDevice = Object.entries(this.stats?.device_ms ?? {})
      .map(([name, ms]) => `${name} ${milliseconds(ms)}`)
      .join(", ");
    setText(
      $("session-server"),
      this.stats?.device
        ? `${this.welcome?.server ?? "scalesteer"} on ${this.stats.device}${perDevice ? ` (${perDevice})` : ""}`
        : (this.welcome?.server ?? "–"),
    );
    setText($("session-rtt"), this.rtt === null ? "–" : milliseconds(this.rtt));
    const st = this.stats;
    setText(
      $("session-frames"),
      st
        ? `${integer(st.frames_sent)} sent, ${integer(st.frames_dropped)} dropped by the server, ${integer(this.viewport.skipped)} skipped here`
        : "–",
    );
  }

  tick() {
    this.showSession();
    const t = performance.now();
    setText($("hud-fps"), `${sig(this.shownRate.rate(t), 3)} fps`);
    if (this.lastImage) setText($("hud-stream"), describeStream(this.lastImage, this.meter.rate(t)));
  }
}
