// The dashboard's side of the conversation: each message the server sends, applied to the page's
// state (render parameters, simulation, roster, engine, camera), and the connection's and the
// role's changes shown.

import { normalizeCamera } from "./camera.js";
import { apiFetch } from "./api.js";
import { ConnState } from "./connection.js";
import { $, setText } from "./dom.js";
import { clockSample } from "./latency.js";
import { showLegend } from "./legend.js";
import { trackedPosition } from "./measure.js";
import { RENDER_DEFAULTS, diffRender, mergeRender } from "./params.js";
import { applyRoster } from "./roster.js";
import { histogramRange } from "./transfer.js";
import { replayIdentity } from "./timeline.js";

const VIEWER_REASON =
  "Read-only: this page joined with the viewer link, so steering is disabled. Open the steering link (with the server token) to change the rendering or the simulation.";

export class DashboardMessages {
  receive(m) {
    switch (m.type) {
      case "welcome":
        return this.welcomed(m);
      case "state":
        return this.state(m);
      case "image":
        this.meter.add(performance.now(), m.data.byteLength);
        if (m.histogram)
          this.tfEditor.setHistogram(m.histogram.values, histogramRange(this.render.mode, this.transferPoints()));
        return this.viewport.show(m);
      case "stats":
        this.stats = m;
        this.plots.pushStats(m, this.shownRate.rate(performance.now()));
        return this.showSession();
      case "params_ack": {
        if (m.applied) this.timeline.acknowledged(m.applied);
        const r = this.acks.ack(m);
        if (r) this.simPanel.showAck(r.key, r.status, r.key === "control" ? r.status.label : "");
        return undefined;
      }
      case "error": {
        if (m.ref !== undefined && m.ref !== null && this.unconfirmed.refused(m.ref)) this.showRender();
        const r = this.acks.error(m);
        if (r) this.simPanel.showAck(r.key, r.status, r.key === "control" ? r.status.label : "");
        // a refused parameter: its field shows the value in effect again, not the one refused
        if (r && r.key !== "control") this.simPanel.restoreParam(r.key);
        this.notices.serverError(m);
        return undefined;
      }
      case "tracked": {
        if (this.picks.track(m)) this.showPicks();
        const pulled = this.pull?.state === "active" ? trackedPosition(m, this.pull.atom) : null;
        if (pulled) {
          this.pull.position = pulled; // the arrow starts at the atom as it moves
          this.viewport.setPullLine({ from: pulled, to: this.pull.pointer });
        }
        return undefined;
      }
      case "event":
        this.notices.notify({
          level: m.level,
          code: m.code,
          message: m.step !== undefined && m.step !== null ? `${m.message} (step ${m.step})` : m.message,
        });
        return undefined;
      case "pong": {
        const s = clockSample(m.client_time, m.server_time, Date.now() / 1000);
        this.rtt = s.rtt * 1000;
        return this.showSession();
      }
      default:
        return undefined; // picked and selected are answered through request(); other types are not for us
    }
  }

  welcomed(m) {
    this.welcome = m;
    this.marksOf = null;
    this.unconfirmed.clear();
    this.viewport.resetFrames();
    this.viewport.resetVideo();
    this.viewport.setLimits(m.limits);
    this.latency.reset();
    this.applyRole(m.role, true);
    if (m.role === "steerer") {
      this.recordings.refresh();
      this.work.start();
    } else this.work.stop();
    if (this.camera) this.sendView(false);
    this.showSession();
  }

  state(m) {
    if (m.ref !== undefined && m.ref !== null && m.by === this.welcome?.client_id) this.unconfirmed.answered(m.ref);
    if (m.render_params) {
      this.sessionRender = mergeRender(RENDER_DEFAULTS, m.render_params);
      if (this.hashRender) {
        this.render = this.renderShown(); // what the link's parameters are compared with
        this.applyLinkRender();
      }
      this.showRender();
    }
    if (m.sim_params) {
      this.simParams = m.sim_params;
      this.simPanel.updateParams(m.sim_params);
    }
    if (m.sim) {
      if (m.sim.n_atoms && this.nAtoms && m.sim.n_atoms !== this.nAtoms) this.cameraCustom = false; // a new molecule
      if (m.sim.n_atoms) this.nAtoms = m.sim.n_atoms;
      this.sim = m.sim;
      if (m.sim.state === "disconnected") this.marksOf = null; // the next replay's are its own
      this.simPanel.updateStatus(m.sim);
      this.timeline.update(m.sim);
      if (!this.lastImage) {
        setText(
          $("view-placeholder"),
          m.sim.state === "running" || m.sim.state === "paused"
            ? "Waiting for the first image…"
            : `No simulation in session “${this.sessionName}” yet: start an adapter to see it here.`,
        );
      }
      this.plots.pushSim(m.sim, this.simParams?.temperature_K);
      this.showSimSummary();
    }
    if (m.clients || m.joined || m.left) {
      this.clients = applyRoster(this.clients, m);
      this.showClients();
    }
    if (m.pulling) {
      this.pulling = m.pulling;
      this.showPulling();
    }
    if (m.engine) {
      this.engine = m.engine;
      this.simPanel.setEngine(m.engine);
      this.timeline.setEngine(m.engine);
      this.showPullLimits();
      // a replay's marks are asked for once, not again with each change of its speed or loop
      if (m.engine.kind === "replay" && replayIdentity(m.engine) !== this.marksOf) {
        this.marksOf = replayIdentity(m.engine);
        this.loadMarks();
      }
    }
    if (m.legend) {
      this.legend = m.legend;
      this.showLegend();
    }
    if (m.cell) {
      this.cell = m.cell;
      this.showCell();
    }
    if (m.camera) {
      this.sessionCamera = normalizeCamera(m.camera);
      if (!this.camera || !this.cameraCustom) {
        this.camera = this.sessionCamera;
        this.afterCameraChange();
        this.sendView(false);
      }
    }
  }

  /** The render parameters the page shows: the session's, with this page's edits on their way
   * (sent and not answered, or not sent yet) over them. */
  renderShown() {
    return mergeRender(this.unconfirmed.over(this.sessionRender), this.pendingRender);
  }

  showRender() {
    this.render = this.renderShown();
    this.renderPanel.update(this.render);
    this.layersPanel.update(this.render.layers);
    this.timePanel.update(this.render);
    this.periodicPanel.update(this.render);
    this.showCell();
    this.showTransferFunction();
    this.showLegend();
    this.writeHashSoon();
  }

  /** The colour legend of what the picture draws now (the session's or the transfer function's). */
  showLegend() {
    showLegend($("legend"), this.legend ?? null, this.render);
  }

  /** The periodic box's outline over the picture, when the session shows it. */
  showCell() {
    this.viewport.setCell(this.render?.show_cell ? this.cell : null);
  }

  /** A shared link named render params: make the session use them (steerers only). */
  applyLinkRender() {
    const wanted = this.hashRender;
    this.hashRender = null;
    const patch = diffRender(this.render, wanted);
    if (!this.hashHasLayers) delete patch.layers;
    if (!Object.keys(patch).length) return;
    if (this.role !== "steerer") {
      this.notices.notify({
        level: "info",
        code: "link",
        message: "this link's render settings need the steering token; showing the session's settings",
      });
      return;
    }
    this.render = mergeRender(this.render, patch);
    Object.assign(this.pendingRender, patch);
    this.flushRender();
  }

  connectionStatus(s) {
    const badge = $("conn-badge");
    badge.dataset.state = s.state;
    const text = {
      [ConnState.CONNECTING]: "connecting…",
      [ConnState.HANDSHAKE]: "joining…",
      [ConnState.READY]: "connected",
      [ConnState.RECONNECTING]: "reconnecting…",
      [ConnState.CLOSED]: `disconnected${s.reason ? `: ${s.reason}` : ""}`,
    }[s.state];
    setText($("conn-text"), text);
    if (s.state === ConnState.READY) {
      if (this.link === "lost") this.notices.notify({ level: "info", code: "connection", message: "reconnected" });
      if (s.fellBack) this.notices.notify({ level: "warning", code: "read-only", message: s.reason });
      this.link = "up";
    } else if (this.link === "up" && (s.state === ConnState.RECONNECTING || s.state === ConnState.CLOSED)) {
      this.link = "lost";
      this.connectionLost(s.reason);
    } else if (s.state === ConnState.CLOSED && s.reason && s.reason !== "closed") {
      this.notices.notify({ level: "error", code: "connection", message: s.reason });
    }
    this.showSession();
  }

  connectionLost(reason) {
    this.notices.notify({
      level: "warning",
      code: "connection",
      message: `connection to the server lost (${reason}); reconnecting`,
    });
    for (const { key, status } of this.acks.abandon()) {
      this.simPanel.showAck(key, status, key === "control" ? status.label : "");
    }
    if (this.pull) this.pullEnd(true);
  }

  applyRole(role, granted) {
    this.role = role;
    const steering = role === "steerer";
    for (const fieldset of document.querySelectorAll("fieldset.steer")) fieldset.disabled = !steering;
    for (const reason of document.querySelectorAll("p.reason")) {
      reason.hidden = steering;
      setText(reason, steering ? "" : VIEWER_REASON);
    }
    this.tfEditor.setEnabled(steering);
    this.renderPanel.setDisabled(!steering);
    this.periodicPanel.setDisabled(!steering);
    this.layersPanel.setDisabled(!steering);
    this.simPanel.setDisabled(!steering);
    $("pull-release-all").disabled = !steering;
    this.timeline.setDisabled(!steering);
    for (const id of ["btn-record", "btn-record-run", "btn-open-files"]) {
      $(id).disabled = !steering;
      $(id).title = steering ? $(id).title : "needs the steering link (the server token)";
    }
    const badge = $("role-badge");
    badge.dataset.role = role;
    setText(badge, granted ? (steering ? "steerer" : "viewer (read-only)") : `${role}…`);
  }

  /** A replay of a recorded run: its steering marks go on the timeline. */
  async loadMarks() {
    const session = this.welcome?.session_id ?? this.sessionName;
    try {
      const response = await apiFetch(`/api/replays/${encodeURIComponent(session)}`, { token: this.token });
      const replay = await response.json();
      if (replay.marks) this.timeline.setMarks(replay.marks);
    } catch (err) {
      if (err.status !== 404) this.notices.notify({ level: "warning", code: "replay", message: err.message });
    }
  }
}
