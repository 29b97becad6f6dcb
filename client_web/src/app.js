// The dashboard: wires the connection, the live view, the panels and the plots together, and
// holds the session state they share. Its behaviour comes by concern (concerns.js composes them
// into it, each a set of methods on this one object, so they share its state): messages.js (what
// the server says), steer.js (what this page steers), view.js (camera, view, images), picking.js
// (picks and pulls), sessionpanel.js (the session panel), actions.js (buttons and shortcuts).
// Pure logic lives in the other modules.

import { compose } from "./concerns.js";
import { Connection, viewUrl } from "./connection.js";
import { $, setText, throttle } from "./dom.js";
import { LatencyTracker, RateMeter } from "./latency.js";
import { Picks } from "./measure.js";
import { Notices } from "./notices.js";
import { RENDER_DEFAULTS, mergeRender } from "./params.js";
import { LayersPanel } from "./layers.js";
import { Plots } from "./plots.js";
import { RenderPanel } from "./renderpanel.js";
import { TimePanel } from "./timepanel.js";
import { PeriodicPanel } from "./periodicpanel.js";
import { Shortcuts } from "./shortcuts.js";
import { MovieButton } from "./movies.js";
import { Recordings } from "./recordings.js";
import { Timeline } from "./timeline.js";
import { Unconfirmed } from "./unconfirmed.js";
import { SimPanel } from "./simpanel.js";
import { AckTracker } from "./steering.js";
import { TransferEditor } from "./tfeditor.js";
import { presetPoints } from "./transfer.js";
import { decodeHash, readQuery } from "./urlstate.js";
import { DeliveryMeter } from "./video.js";
import { Viewport } from "./viewport.js";
import { RunningWork, pageInstance } from "./work.js";

const RENDER_SEND_MS = 50;
const PULL_SEND_MS = 50;
const HASH_WRITE_MS = 300;

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
    this.hashHasLayers = fromHash.hasLayers;
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
    this.marksOf = null; // the replay whose steering marks the timeline has (replayIdentity)
    this.instance = pageInstance(); // names this tab to the server across reconnections

    this.flushRenderSoon = throttle(() => this.flushRender(), RENDER_SEND_MS);
    this.sendPullSoon = throttle(() => this.sendPull(), PULL_SEND_MS);
    this.writeHashSoon = throttle(() => this.writeHash(), HASH_WRITE_MS);
    this.sendViewSoon = throttle(() => this.sendView(false), 120);
    // video: what this browser decodes at the view's size, and whether the user or a decoder
    // failure asked for JPEG (`?transport=jpeg` in the address does too)
    this.transport = query.transport;
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
    const onInvalid = (text) => this.notices.notify({ level: "warning", code: "input", message: text });
    this.renderPanel = new RenderPanel({ onChange: (patch, final) => this.steerRender(patch, final), onInvalid });
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
      onInvalid,
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
}

compose(Dashboard);

window.scalesteer = new Dashboard();
