// The dashboard: wires the connection, the live view, the panels and the plots together.
// Pure logic lives in the other modules; this one holds the session state and the DOM wiring.

import { DEFAULT_CAMERA, lookAlong, normalizeCamera, project, setProjection, unprojectToPlane } from "./camera.js";
import { apiFetch, openReplay, replayFiles } from "./api.js";
import { ConnState, Connection, viewUrl } from "./connection.js";
import { $, downloadBlob, el, setText, throttle } from "./dom.js";
import { integer, milliseconds, nanoseconds, position, sig } from "./format.js";
import { LatencyTracker, RateMeter, clockSample } from "./latency.js";
import { showLegend } from "./legend.js";
import { Picks, atomLabel, measurement, trackedAtoms, trackedPosition } from "./measure.js";
import { Notices } from "./notices.js";
import { RENDER_DEFAULTS, SIGMA_SLIDER, clamp, diffRender, mergeRender } from "./params.js";
import { LayersPanel } from "./layers.js";
import { Plots } from "./plots.js";
import { applyRoster } from "./roster.js";
import { RenderPanel } from "./renderpanel.js";
import { TimePanel } from "./timepanel.js";
import { PeriodicPanel } from "./periodicpanel.js";
import { requestScreenshot, screenshotName } from "./screenshot.js";
import { Shortcuts } from "./shortcuts.js";
import { MovieButton } from "./movies.js";
import { Recordings } from "./recordings.js";
import { Timeline } from "./timeline.js";
import { Unconfirmed } from "./unconfirmed.js";
import { SimPanel } from "./simpanel.js";
import { AckTracker } from "./steering.js";
import { TransferEditor } from "./tfeditor.js";
import { histogramRange, normalizePoints, presetPoints } from "./transfer.js";
import { decodeHash, encodeHash, readQuery } from "./urlstate.js";
import { readViewFile, viewFile, viewFileName } from "./viewfile.js";
import { DeliveryMeter, decodableCodecs, describeStream } from "./video.js";
import { Viewport } from "./viewport.js";
import { RunningWork, pageInstance } from "./work.js";

const RENDER_SEND_MS = 50;
const PULL_SEND_MS = 50;
const HASH_WRITE_MS = 300;
const VIEWER_REASON =
  "Read-only: this page joined with the viewer link, so steering is disabled. Open the steering link (with the server token) to change the rendering or the simulation.";

class Dashboard {
  constructor() {
    const query = readQuery(window.location.search);
    const fromHash = decodeHash(window.location.hash);
    this.token = query.token;
    this.sessionName = query.session;
    this.role = query.role;
    this.render = mergeRender(RENDER_DEFAULTS, {}); // what the page shows (renderShown)
    this.sessionRender = mergeRender(RENDER_DEFAULTS, {}); // the session's, from its states
    this.unconfirmed = new Unconfirmed(); // this page's edits the session has not answered
    this.hashRender = fromHash.render; // a shared link's render params, applied once as steerer
    // layers belong to one system: a link that does not name them keeps the session's
    this.hashHasLayers = new URLSearchParams(window.location.hash.replace(/^#/, "")).has("layers");
    this.camera = fromHash.camera;
    this.cameraCustom = Boolean(fromHash.camera);
    this.sessionCamera = null;
    this.simParams = {};
    this.sim = null;
    this.nAtoms = 0;
    this.clients = [];
    this.pulling = [];
    this.welcome = null;
    this.stats = null;
    this.rtt = null;
    this.link = "never"; // the connection: "never" up yet, "up", or "lost" since it was up
    this.pendingRender = {};
    this.pull = null;
    this.lastImage = null;
    this.viewFrame = null;
    this.screenshotBusy = false;
    this.picks = new Picks();
    this.engine = null;
    this.instance = pageInstance(); // names this tab to the server across reconnections

    this.flushRenderSoon = throttle(() => this.flushRender(), RENDER_SEND_MS);
    this.sendPullSoon = throttle(() => this.sendPull(), PULL_SEND_MS);
    this.writeHashSoon = throttle(() => this.writeHash(), HASH_WRITE_MS);
    this.sendViewSoon = throttle(() => this.sendView(false), 120);
    // video: what this browser decodes at the view's size, and whether the user or a decoder
    // failure asked for JPEG (`?transport=jpeg` in the address does too)
    this.transport = new URLSearchParams(window.location.search).get("transport") === "jpeg" ? "jpeg" : "auto";
    this.videoCodecs = [];
    this.videoSize = "";
    this.videoFailed = false;
    this.codecCache = new Map();
    this.meter = new DeliveryMeter();
    this.notices = new Notices($("notices"));
    if (fromHash.invalid.length) {
      this.notices.notify({
        level: "warning",
        code: "link",
        message: `ignored unreadable link fields: ${fromHash.invalid.join(", ")}`,
      });
    }
    this.latency = new LatencyTracker();
    this.shownRate = new RateMeter(2000);
    this.acks = new AckTracker();
    this.plots = new Plots({ windowS: Number($("plot-window").value) });
    this.renderPanel = new RenderPanel({ onChange: (patch, final) => this.steerRender(patch, final) });
    this.layersPanel = new LayersPanel({
      onChange: (layers) => this.steerRender({ layers }, true),
      select: (text) => this.connection.request({ type: "select", text }),
    });
    this.timePanel = new TimePanel({
      onChange: (patch, final) => this.steerRender(patch, final),
      replay: () => this.engine?.kind === "replay",
    });
    this.periodicPanel = new PeriodicPanel({ onChange: (patch, final) => this.steerRender(patch, final) });
    this.cell = null;
    this.tfEditor = new TransferEditor({
      svgRoot: $("tf-editor"),
      colorInput: $("tf-color"),
      selectedLabel: $("tf-selected"),
      addButton: $("tf-add"),
      removeButton: $("tf-remove"),
      onChange: (points, final) => this.steerRender({ transfer_function: points }, final),
    });
    this.simPanel = new SimPanel({
      onControl: (action, extra, label) => this.control(action, extra, label),
      onParam: (key, value) => this.simParam(key, value),
      onInvalid: (text) => this.notices.notify({ level: "warning", code: "input", message: text }),
    });
    this.timeline = new Timeline({
      onControl: (action, extra, label) => this.control(action, extra, label),
      onApplyRender: (changes) => this.steerRender(changes, true),
    });
    const session = () => this.welcome?.session_id ?? this.sessionName;
    const movieSize = () => {
      const { viewW, viewH } = this.viewport.size;
      const scale = Math.min(1, 1920 / viewW, 1080 / viewH);
      return { width: 2 * Math.round((viewW * scale) / 2), height: 2 * Math.round((viewH * scale) / 2) };
    };
    const notify = (n) => this.notices.notify(n);
    this.work = new RunningWork({
      token: this.token,
      instance: this.instance,
      notify,
      onUpdate: (work) => {
        this.movie.adopt(work.jobs, this.instance, session());
        this.recordings.adopt(work.recordings, this.instance);
      },
    });
    const owner = () => this.work.owner();
    this.recordings = new Recordings({ token: this.token, session, viewSize: movieSize, owner, notify });
    this.movie = new MovieButton({
      token: this.token,
      session,
      camera: () => this.camera,
      size: movieSize,
      owner,
      steering: () => this.role === "steerer",
      notify,
    });
    this.viewport = new Viewport({
      container: $("viewport"),
      canvas: $("view"),
      overlay: $("overlay"),
      placeholder: $("view-placeholder"),
      getCamera: () => this.camera,
      canPull: () => this.role === "steerer",
      pullWithoutModifier: () => $("pull-mode").checked,
      onResize: (size) => this.resized(size),
      onCamera: (cam, interacting) => this.setCamera(cam, interacting),
      onClick: (x, y, how) => this.pick(x, y, how),
      onPullStart: (x, y) => this.pullStart(x, y),
      onPullMove: (x, y) => this.pullMove(x, y),
      onPullEnd: () => this.pullEnd(),
      onDrawn: (msg, t) => this.drawn(msg, t),
      onVideoDecoded: (msg, decodeMs) => this.acknowledge(msg, decodeMs),
      onImageDecoded: (msg, decodeMs) => this.acknowledge(msg, decodeMs),
      onVideoError: (message) => this.videoError(message),
      onDecodeError: (err, msg) =>
        this.notices.notify({
          level: "error",
          code: "image",
          message: `frame ${msg.frame_id} could not be decoded: ${err.message}`,
        }),
    });

    this.connection = new Connection({
      url: viewUrl(window.location),
      token: this.token,
      role: this.role,
      session: this.sessionName,
      client: "dashboard",
      instance: this.instance,
      onMessage: (m) => this.receive(m),
      onStatus: (s) => this.connectionStatus(s),
      onProtocolError: (e) =>
        this.notices.notify({
          level: "error",
          code: e.code,
          message: `unreadable message from the server: ${e.message}`,
          path: e.path,
        }),
    });
    this.bindButtons();
    this.shortcuts = new Shortcuts({ dialog: $("help-dialog"), table: $("shortcut-table"), bindings: this.bindings() });
    setText($("session-label"), `session ${this.sessionName}`);
    this.applyRole(this.role, false);
    this.tfEditor.setPoints(presetPoints(this.render.tf_preset));
    this.connection.start();
    setInterval(() => this.tick(), 1000);
  }

  // ------------------------------------------------------------------ messages

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
      if (m.engine.kind === "replay") this.loadMarks();
    }
    if (m.legend) showLegend($("legend"), m.legend);
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
    this.writeHashSoon();
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

  // ------------------------------------------------------------------ connection and roles

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

  // ------------------------------------------------------------------ steering

  steerRender(patch, final) {
    if (this.role !== "steerer") return;
    this.render = mergeRender(this.render, patch);
    Object.assign(this.pendingRender, patch);
    if (patch.transfer_function !== undefined || patch.tf_preset !== undefined) this.showTransferFunction();
    if (patch.color_by !== undefined) this.timePanel.update(this.render);
    this.writeHashSoon();
    if (final) {
      this.flushRenderSoon.cancel();
      this.flushRender();
    } else {
      this.flushRenderSoon();
    }
  }

  flushRender() {
    const params = this.pendingRender;
    this.pendingRender = {};
    if (!Object.keys(params).length) return;
    const seq = this.role === "steerer" ? this.connection.send({ type: "render_params", params }) : null;
    if (seq === null) {
      this.showRender(); // not sent: the page shows the session's values again
      return;
    }
    this.latency.sent(seq, "render_params", performance.now());
    this.unconfirmed.sent(seq, params);
  }

  /** The transfer function in effect: the session's points, or its preset's when it has none. */
  transferPoints() {
    const explicit = normalizePoints(this.render.transfer_function);
    return explicit.length ? explicit : presetPoints(this.render.tf_preset);
  }

  showTransferFunction() {
    this.tfEditor.setPoints(this.transferPoints());
    const preset = $("tf-preset");
    const edited = normalizePoints(this.render.transfer_function).length > 0;
    if (document.activeElement !== preset) preset.value = edited ? "custom" : this.render.tf_preset;
  }

  simParam(key, value) {
    const seq = this.connection.send({ type: "sim_params", [key]: value });
    if (seq === null) {
      this.simPanel.showAck(key, { state: "failed", text: "not connected" });
      return;
    }
    this.simPanel.showAck(key, this.acks.sent(seq, key, key));
  }

  control(action, extra, label) {
    const seq = this.connection.send({ type: "control", action, ...extra });
    if (seq === null) {
      this.simPanel.showAck("control", { state: "failed", text: "not connected" }, label);
      return;
    }
    this.simPanel.showAck("control", this.acks.sent(seq, "control", label), label);
  }

  // ------------------------------------------------------------------ camera and view

  resized(size) {
    setText($("hud-size"), `${size.viewW}×${size.viewH}`);
    this.probeVideo(size.viewW, size.viewH);
    this.sendViewSoon();
  }

  /** Ask WebCodecs what it decodes at this size; a changed answer goes to the server. */
  async probeVideo(width, height) {
    const key = `${width}x${height}`;
    this.videoSize = key;
    const codecs = await decodableCodecs(width, height, globalThis.VideoDecoder, this.codecCache);
    if (this.videoSize !== key) return; // the view was resized again meanwhile
    if (codecs.join() !== this.videoCodecs.join()) {
      this.videoCodecs = codecs;
      this.sendViewSoon();
    }
    document.body.dataset.videoCodecs = codecs.join(" ");
  }

  /** The codecs to offer the server: none when JPEG is chosen or video failed here. */
  offeredVideo() {
    return this.transport === "jpeg" || this.videoFailed ? [] : this.videoCodecs;
  }

  setTransport(value) {
    this.transport = value === "jpeg" ? "jpeg" : "auto";
    if (this.transport === "auto" && this.videoFailed) {
      this.videoFailed = false; // the user asks to try again
      this.viewport.resetVideo();
    }
    this.sendView(false);
  }

  /** A video frame or image is on screen: acknowledge it (the server paces both by these). */
  acknowledge(msg, decodeMs) {
    this.connection.send({ type: "frame_ack", frame_id: msg.frame_id, decode_ms: Math.max(0, decodeMs) });
  }

  videoError(message) {
    if (this.videoFailed) return;
    this.videoFailed = true;
    document.body.dataset.videoFailed = "true";
    this.notices.notify({
      level: "warning",
      code: "video",
      message: `video decoding failed (${message}); showing JPEG images instead`,
    });
    this.sendView(false);
  }

  setCamera(cam, interacting) {
    if (!cam) return;
    this.camera = normalizeCamera(cam);
    this.cameraCustom = true;
    this.afterCameraChange();
    if (interacting) {
      if (this.viewFrame === null) {
        this.viewFrame = requestAnimationFrame(() => {
          this.viewFrame = null;
          this.sendView(true);
        });
      }
    } else {
      if (this.viewFrame !== null) cancelAnimationFrame(this.viewFrame);
      this.viewFrame = null;
      this.sendView(false);
    }
  }

  afterCameraChange() {
    this.viewport.drawOverlay();
    const ortho = this.camera?.projection === "orthographic";
    $("btn-projection").setAttribute("aria-pressed", String(ortho));
    this.writeHashSoon();
    if (this.pull?.state === "active") this.sendPullSoon();
  }

  sendView(interacting) {
    if (!this.camera || !this.connection.ready) return;
    const { viewW, viewH, dpr } = this.viewport.size;
    const seq = this.connection.send({
      type: "view",
      camera: this.camera,
      width: viewW,
      height: viewH,
      device_pixel_ratio: clamp(dpr, 0.1, 8),
      interacting,
      track: trackedAtoms(this.picks.indices, this.pull?.state === "active" ? this.pull.atom : null),
      video: this.offeredVideo(),
    });
    if (seq !== null) this.latency.sent(seq, "view", performance.now());
  }

  resetView() {
    const cam = this.sessionCamera ?? normalizeCamera(DEFAULT_CAMERA);
    const projection = this.camera?.projection ?? cam.projection;
    this.setCamera(setProjection(cam, projection), false);
    this.cameraCustom = false;
  }

  toggleProjection() {
    if (!this.camera) return;
    const next = this.camera.projection === "orthographic" ? "perspective" : "orthographic";
    this.setCamera(setProjection(this.camera, next), false);
  }

  writeHash() {
    const hash = encodeHash({ render: this.render, camera: this.camera });
    const url = `${window.location.pathname}${window.location.search}#${hash}`;
    if (window.location.hash !== `#${hash}`) window.history.replaceState(null, "", url);
  }

  // ------------------------------------------------------------------ images

  drawn(msg, t) {
    this.lastImage = msg;
    this.shownRate.tick(t);
    const lat = this.latency.shown(msg.ref, t);
    if (lat) {
      this.plots.pushLatency(lat.latency);
      setText($("hud-latency"), `latency ${milliseconds(lat.latency)}`);
    }
    const vp = $("viewport");
    vp.dataset.frame = String(msg.frame_id);
    vp.dataset.still = String(msg.still !== false);
    vp.dataset.ref = String(msg.ref ?? "");
    vp.dataset.imageSize = `${msg.width}x${msg.height}`;
    setText($("hud-step"), `step ${integer(msg.step)}`);
    setText($("hud-fps"), `${sig(this.shownRate.rate(t), 3)} fps`);
    setText($("hud-stream"), describeStream(msg, this.meter.rate(t)));
    vp.dataset.format = msg.format;
    this.viewport.drawOverlay();
  }

  // ------------------------------------------------------------------ picking and pulling

  async pick(x, y, how = {}) {
    if (!this.connection.ready) return;
    let reply;
    try {
      ({ reply } = await this.connection.request({ type: "pick", x, y }));
    } catch (err) {
      this.notices.notify({ level: "warning", code: "pick", message: err.message });
      return;
    }
    if (reply.type !== "picked") return;
    if (how.add) this.picks.extend(reply);
    else this.picks.pick(reply);
    this.showPicks();
    this.sendView(false); // track the picked atoms: markers and measurements follow them
  }

  /** The picked atoms: details of the last, labels and the measurement on the view. */
  showPicks() {
    const atoms = this.picks.atoms;
    const last = atoms.at(-1) ?? { atom: null };
    this.showPicked(last);
    const m = measurement(atoms);
    const text = m ? `${m.kind} ${sig(m.value, 4)} ${m.unit}` : "";
    const details = $("pick-details");
    details.dataset.measure = m ? `${m.kind}:${m.value}` : "";
    setText(
      $("pick-measure"),
      m
        ? `${text} (atoms ${atoms.map((a) => a.atom).join(", ")})`
        : "Shift-click more atoms: two give a distance, three an angle, four a dihedral",
    );
    this.viewport.setMarker(null);
    this.viewport.setAnnotations(
      atoms.map((a) => ({ position: a.position, label: atomLabel(a) })),
      m ? { kind: m.kind, text } : null,
    );
  }

  showPicked(p) {
    const details = $("pick-details");
    details.dataset.atom = p.atom ?? "";
    if (p.atom === null || p.atom === undefined) {
      setText($("pick-atom"), "background (no atom here)");
      for (const id of ["pick-element", "pick-name", "pick-residue", "pick-chain", "pick-layer", "pick-position"])
        setText($(id), "–");
      this.viewport.setMarker(null);
      return;
    }
    setText($("pick-atom"), `index ${p.atom}`);
    setText($("pick-element"), p.element || "–");
    setText($("pick-name"), p.name || "–");
    setText($("pick-residue"), `${p.residue_name || "?"} ${p.residue_id ?? ""}`.trim());
    setText($("pick-chain"), p.chain || "–");
    setText($("pick-layer"), p.layer || "–");
    setText($("pick-position"), position(p.position));
  }

  clearSelection() {
    this.picks.clear();
    this.showPicks();
    setText($("pick-atom"), "click an atom");
    this.sendView(false);
  }

  /** The engine's pull limits beside the pull fields; pulling off where it takes no forces. */
  showPullLimits() {
    const e = this.engine;
    const k = $("pull-k");
    const max = $("pull-max");
    if (e?.pull) {
      k.max = String(e.pull.max_spring_k);
      max.max = String(e.pull.max_force);
      if (Number(k.value) > e.pull.max_spring_k) k.value = String(e.pull.max_spring_k);
      if (Number(max.value) > e.pull.max_force) max.value = String(e.pull.max_force);
      setText($("range-pull-k"), `≤ ${sig(e.pull.max_spring_k, 4)}`);
      setText($("range-pull-max"), `≤ ${sig(e.pull.max_force, 4)}`);
    } else if (e) {
      setText($("range-pull-k"), "not available");
      setText($("range-pull-max"), "not available");
    }
    const why =
      e && !e.pull ? `${e.name} cannot be pulled: ${e.unavailable?.pull || "it takes no external forces"}` : "";
    $("pull-reason").hidden = !why;
    setText($("pull-reason"), why);
  }

  async pullStart(x, y) {
    if (this.role !== "steerer") return;
    if (this.engine && !this.engine.pull) {
      this.notices.notify({ level: "info", code: "pull", message: $("pull-reason").textContent });
      return;
    }
    const pull = { state: "picking", pointer: [x, y], atom: null, position: null };
    this.pull = pull;
    this.viewport.setPending([x, y]);
    let reply;
    try {
      ({ reply } = await this.connection.request({ type: "pick", x, y }));
    } catch (err) {
      this.viewport.setPending(null);
      this.notices.notify({ level: "warning", code: "pull", message: err.message });
      if (this.pull === pull) this.pull = null;
      return;
    }
    this.viewport.setPending(null);
    if (this.pull !== pull || reply.type !== "picked") return; // released meanwhile, or refused
    if (reply.atom === null || reply.atom === undefined || !reply.position) {
      this.notices.notify({ level: "info", code: "pull", message: "no atom under the pointer to pull" });
      this.pull = null;
      return;
    }
    this.showPicked(reply);
    Object.assign(pull, { state: "active", atom: reply.atom, position: reply.position });
    setText($("pull-atom"), `${reply.atom} (${reply.element} ${reply.name})`);
    $("pull-hint").hidden = false;
    this.viewport.setPullLine({ from: pull.position, to: pull.pointer });
    this.sendPull();
    this.sendView(false); // track the pulled atom
  }

  pullMove(x, y) {
    if (!this.pull) return;
    this.pull.pointer = [x, y];
    if (this.pull.state !== "active") return;
    this.viewport.setPullLine({ from: this.pull.position, to: this.pull.pointer });
    this.sendPullSoon();
  }

  sendPull() {
    const pull = this.pull;
    if (!pull || pull.state !== "active" || !this.camera) return;
    const { viewW, viewH } = this.viewport.size;
    const target = unprojectToPlane(
      this.camera,
      pull.pointer[0] + 0.5,
      pull.pointer[1] + 0.5,
      viewW,
      viewH,
      pull.position,
    );
    if (!target) return;
    this.connection.send({
      type: "pull",
      atom: pull.atom,
      target,
      spring_k: clamp(Number($("pull-k").value) || 1, 0.01, this.engine?.pull?.max_spring_k ?? 10000),
      max_force: clamp(Number($("pull-max").value) || 50, 0.01, this.engine?.pull?.max_force ?? 100000),
    });
  }

  pullEnd(silent = false) {
    const pull = this.pull;
    this.pull = null;
    this.sendPullSoon.cancel();
    $("pull-hint").hidden = true;
    this.viewport.setPullLine(null);
    this.viewport.setPending(null);
    if (pull?.state === "active" && !silent) {
      this.connection.send({ type: "pull", atom: pull.atom, release: true });
      this.sendView(false); // no longer tracked
    }
  }

  releaseAll() {
    for (const p of this.pulling) this.connection.send({ type: "pull", atom: p.atom, release: true });
  }

  // ------------------------------------------------------------------ panels

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

  // ------------------------------------------------------------------ buttons and shortcuts

  async screenshot() {
    if (this.screenshotBusy) return;
    const button = $("btn-screenshot");
    this.screenshotBusy = true;
    button.disabled = true;
    const [width, height] = this.viewport.fullSize();
    try {
      const blob = await requestScreenshot({
        token: this.token,
        session: this.welcome?.session_id ?? this.sessionName,
        width,
        height,
        params: this.render,
        camera: this.camera,
      });
      downloadBlob(blob, screenshotName(this.sessionName, this.sim?.step));
      this.notices.notify({ level: "info", code: "screenshot", message: `saved a ${width}×${height} PNG` });
    } catch (err) {
      this.notices.notify({ level: "error", code: "screenshot", message: err.message });
    } finally {
      this.screenshotBusy = false;
      button.disabled = false;
    }
  }

  async copyLink() {
    this.writeHash();
    const url = window.location.href;
    const what = this.role === "steerer" ? "steer" : "view";
    try {
      await navigator.clipboard.writeText(url);
      this.notices.notify({
        level: "info",
        code: "link",
        message: `link copied; it carries your token, so whoever opens it can ${what}`,
      });
    } catch {
      this.notices.notify({ level: "info", code: "link", message: `copy this link: ${url}` });
    }
  }

  exportCsv() {
    const blob = new Blob([this.plots.csv()], { type: "text/csv" });
    downloadBlob(blob, `scalesteer-${this.sessionName}-plots.csv`);
  }

  nudgeSigma(factor) {
    const sigma = clamp(Number((this.render.sigma_A * factor).toPrecision(3)), SIGMA_SLIDER.min, SIGMA_SLIDER.max);
    this.renderPanel.update({ ...this.render, sigma_A: sigma });
    this.steerRender({ sigma_A: sigma }, true);
  }

  nudgeIso(delta) {
    const iso = clamp(Number((this.render.iso_level + delta).toFixed(3)), 0.01, 100);
    this.renderPanel.update({ ...this.render, iso_level: iso });
    this.steerRender({ iso_level: iso }, true);
  }

  bindButtons() {
    $("btn-reset-view").addEventListener("click", () => this.resetView());
    $("btn-projection").addEventListener("click", () => this.toggleProjection());
    $("btn-screenshot").addEventListener("click", () => this.screenshot());
    $("btn-copy-link").addEventListener("click", () => this.copyLink());
    $("btn-help").addEventListener("click", () => this.shortcuts.open());
    $("btn-export-csv").addEventListener("click", () => this.exportCsv());
    $("btn-clear-plots").addEventListener("click", () => this.plots.clear());
    $("btn-reconnect").addEventListener("click", () => this.connection.reconnectNow());
    $("btn-save-view").addEventListener("click", () => this.saveView());
    $("btn-open-view").addEventListener("click", () => $("open-view-file").click());
    $("open-view-file").addEventListener("change", (e) => this.openView(e.target));
    $("btn-open-files").addEventListener("click", () => $("open-files").click());
    $("open-files").addEventListener("change", (e) => this.openFiles(e.target));
    $("plot-window").addEventListener("change", (e) => this.plots.setWindow(Number(e.target.value)));
    $("resolution").addEventListener("change", (e) => this.viewport.setResolution(Number(e.target.value)));
    $("transport").value = this.transport;
    $("transport").addEventListener("change", (e) => this.setTransport(e.target.value));
    $("pull-release-all").addEventListener("click", () => this.releaseAll());
    $("tf-preset").addEventListener("change", (e) =>
      this.steerRender({ tf_preset: e.target.value, transfer_function: [] }, true),
    );
    $("tf-reset").addEventListener("click", () =>
      this.steerRender({ tf_preset: this.render.tf_preset, transfer_function: [] }, true),
    );
  }

  saveView() {
    const session = this.welcome?.session_id ?? this.sessionName;
    const data = viewFile({ session, camera: this.camera, render: this.render, atoms: this.picks.indices });
    downloadBlob(new Blob([JSON.stringify(data, null, 2)], { type: "application/json" }), viewFileName(session));
    this.notices.notify({ level: "info", code: "view", message: "view saved" });
  }

  async openView(input) {
    const file = input.files?.[0];
    input.value = "";
    if (!file) return;
    let view;
    try {
      view = readViewFile(await file.text());
    } catch (err) {
      this.notices.notify({ level: "error", code: "view", message: `${file.name}: ${err.message}` });
      return;
    }
    if (view.camera) this.setCamera(normalizeCamera(view.camera), false);
    if (view.render) {
      if (this.role === "steerer") {
        const patch = diffRender(this.render, mergeRender(RENDER_DEFAULTS, view.render));
        if (Object.keys(patch).length) this.steerRender(patch, true);
        this.renderPanel.update(this.render);
        this.timePanel.update(this.render);
      } else {
        this.notices.notify({
          level: "info",
          code: "view",
          message: "the view's render settings need the steering token; only its camera was applied",
        });
      }
    }
    this.picks.atoms = view.atoms.map((atom) => ({ atom, name: `#${atom}` }));
    this.showPicks();
    this.sendView(false);
    this.notices.notify({ level: "info", code: "view", message: `opened ${file.name}` });
  }

  async openFiles(input) {
    const files = [...(input.files ?? [])];
    input.value = "";
    if (!files.length) return;
    try {
      replayFiles(files); // refused here, naming the files, before anything is uploaded
      this.notices.notify({
        level: "info",
        code: "open",
        message: `uploading ${files.map((f) => f.name).join(", ")}…`,
      });
      const opened = await openReplay({ token: this.token, files });
      const url = new URL(window.location.href);
      url.searchParams.set("session", opened.session);
      url.hash = "";
      window.location.assign(url.toString());
    } catch (err) {
      this.notices.notify({ level: "error", code: "open", message: err.message });
    }
  }

  bindings() {
    const steer = () => this.role === "steerer";
    return [
      { keys: ["?"], label: "?", description: "Show or hide this help", run: () => this.shortcuts.toggle() },
      {
        keys: ["r", "R"],
        label: "R",
        description: "Reset the view to the session's default camera",
        run: () => this.resetView(),
      },
      {
        keys: ["o", "O"],
        label: "O",
        description: "Toggle orthographic / perspective projection",
        run: () => this.toggleProjection(),
      },
      {
        keys: ["x"],
        label: "X / Y / Z",
        description: "View from +x, +y, +z (with Shift: from −x, −y, −z)",
        run: () => this.look("x"),
      },
      { keys: ["X"], hidden: true, run: () => this.look("-x") },
      { keys: ["y"], hidden: true, run: () => this.look("y") },
      { keys: ["Y"], hidden: true, run: () => this.look("-y") },
      { keys: ["z"], hidden: true, run: () => this.look("z") },
      { keys: ["Z"], hidden: true, run: () => this.look("-z") },
      {
        keys: ["["],
        label: "[ / ]",
        description: "Smaller / larger scale σ",
        run: () => this.nudgeSigma(1 / 1.15),
        when: steer,
      },
      { keys: ["]"], hidden: true, run: () => this.nudgeSigma(1.15), when: steer },
      {
        keys: [","],
        label: ", / .",
        description: "Lower / raise the iso level",
        run: () => this.nudgeIso(-0.05),
        when: steer,
      },
      { keys: ["."], hidden: true, run: () => this.nudgeIso(0.05), when: steer },
      {
        keys: ["m", "M"],
        label: "M",
        description: "Switch isosurface / volume mode",
        run: () => {
          const mode = this.render.mode === "iso" ? "volume" : "iso";
          this.renderPanel.update({ ...this.render, mode });
          this.steerRender({ mode }, true);
        },
        when: steer,
      },
      {
        keys: [" "],
        label: "Space",
        description: "Pause or resume the simulation",
        run: () => this.simPanel.togglePlay(),
        when: steer,
      },
      {
        keys: ["n", "N"],
        label: "N",
        description: "Advance the simulation by the step count",
        run: () => this.simPanel.step(),
        when: steer,
      },
      {
        keys: ["S"],
        label: "Shift+S",
        description: "Download a full-resolution screenshot",
        run: () => this.screenshot(),
      },
      { keys: ["l", "L"], label: "L", description: "Copy a link to this view", run: () => this.copyLink() },
      { keys: ["e", "E"], label: "E", description: "Export the plots as CSV", run: () => this.exportCsv() },
      {
        keys: ["v", "V"],
        label: "V",
        description: "Focus the live view (then arrows rotate, Shift+arrows pan, +/− zoom, Enter picks the centre)",
        run: () => $("view").focus(),
      },
      { keys: ["Escape"], label: "Esc", description: "Clear the selected atom", run: () => this.clearSelection() },
    ];
  }

  look(axis) {
    if (this.camera) this.setCamera(lookAlong(this.camera, axis), false);
  }

  // ------------------------------------------------------------------ automation

  /** CSS-pixel position of a world point in the view (for scripts and the devtools console). */
  projectToPage(point) {
    if (!this.camera) return null;
    const { viewW, viewH, cssW, cssH } = this.viewport.size;
    const [px, py, depth] = project(this.camera, point, viewW, viewH);
    const rect = $("view").getBoundingClientRect();
    return { x: rect.left + (px / viewW) * cssW, y: rect.top + (py / viewH) * cssH, depth };
  }
}

window.scalesteer = new Dashboard();
