// The scalesteer notebook widget (anywidget): the live view of a session, drawn by the
// dashboard's own Viewport (client_web/src/viewport.js: JPEG images and WebCodecs video, the
// orbit / pan / zoom / pick gestures), fed by the kernel: the kernel's link to the server sends
// each image here as a custom message with its bytes, and the views and picks made here go
// back the same way. The dashboard's modules arrive as the `_modules` trait, [name, source]
// pairs in dependency order, and load from blob: URLs.

const SILENCE_MS = 4000; // the kernel sends at least one message a second while it lives

/** Load [name, source] modules in order, each one's `./name` imports pointing at the blob
 * URLs of those before it; returns {name: blob URL}. */
function blobUrls(modules) {
  const urls = {};
  for (const [name, source] of modules) {
    let text = source;
    for (const [dep, url] of Object.entries(urls)) {
      text = text.replaceAll(`from "./${dep}"`, `from "${url}"`);
    }
    urls[name] = URL.createObjectURL(new Blob([text], { type: "text/javascript" }));
  }
  return urls;
}

function element(tag, className, parent) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  parent?.append(node);
  return node;
}

async function render({ model, el }) {
  const urls = blobUrls(model.get("_modules"));
  const { Viewport } = await import(urls["viewport.js"]);
  const video = await import(urls["video.js"]);
  const { normalizeCamera, sameCamera } = await import(urls["camera.js"]);

  const root = element("div", "scalesteer-view", el);
  const stage = element("div", "scalesteer-stage", root);
  const canvas = element("canvas", "scalesteer-canvas", stage);
  const overlay = element("canvas", "scalesteer-overlay", stage);
  const placeholder = element("div", "scalesteer-placeholder", stage);
  placeholder.textContent = "waiting for the first picture…";
  const banner = element("div", "scalesteer-banner", stage);
  banner.hidden = true;
  const hud = element("div", "scalesteer-hud", root);
  canvas.tabIndex = 0;

  const meter = new video.DeliveryMeter(1000);
  let camera = model.get("camera") ? normalizeCamera(model.get("camera")) : null;
  let codecs = [];
  let lastFromKernel = performance.now();
  let gone = false; // the kernel's comm is closed
  let last = null; // the last image message drawn
  let drawn = 0;
  let picked = null;
  let videoProblem = "";

  const current = () => camera ?? (model.get("session_camera") ? normalizeCamera(model.get("session_camera")) : null);

  let viewport = null; // its constructor measures the stage and reports the size at once
  viewport = new Viewport({
    container: stage,
    canvas,
    overlay,
    placeholder,
    getCamera: current,
    onResize: () => viewport && sendView(false),
    onCamera: (cam, interacting) => {
      camera = cam;
      viewport.drawOverlay();
      sendView(interacting);
    },
    onClick: (x, y) => {
      const { viewW, viewH } = viewport.size;
      const [iw, ih] = last ? [last.width, last.height] : [viewW, viewH];
      toKernel({ type: "pick", x: Math.floor((x / viewW) * iw), y: Math.floor((y / viewH) * ih) });
    },
    onDrawn: (msg, t) => {
      drawn += 1;
      last = msg;
      meter.add(t, msg.data.byteLength);
      if (root.dataset.firstFrameAt === undefined) root.dataset.firstFrameAt = String(t); // page clock
      root.dataset.frames = String(drawn);
      root.dataset.frameId = String(msg.frame_id);
      root.dataset.format = msg.format;
      root.dataset.step = String(msg.step ?? "");
      root.dataset.imageSize = `${msg.width}x${msg.height}`;
      root.dataset.still = String(msg.still !== false);
    },
    onVideoError: (message) => {
      videoProblem = message;
      codecs = [];
      viewport.resetVideo();
      sendView(false);
    },
    makeVideoPipe: (handlers) => {
      try {
        return new video.VideoPipe({ ...handlers, workerUrl: urls["video.worker.js"] });
      } catch (err) {
        // no worker from a blob: URL here (a strict Content-Security-Policy): JPEG instead
        setTimeout(() => handlers.onError(`no video decoder worker (${err.message})`));
        return { push() {}, reset() {}, close() {} };
      }
    },
  });

  // the cameras this page sent: the kernel sets the `camera` trait to each, and those echoes
  // must not be taken for a camera set from Python (the page would go back along its drag)
  const sent = [];

  function toKernel(message) {
    if (!gone) model.send(message);
  }

  function sendView(interacting) {
    const { viewW, viewH } = viewport.size;
    if (camera) {
      sent.push(camera);
      if (sent.length > 64) sent.shift();
    }
    toKernel({
      type: "view",
      camera,
      width: viewW,
      height: viewH,
      interacting,
      video: model.get("video") ? codecs : [],
    });
  }

  function sizeStage() {
    stage.style.width = `${model.get("width")}px`;
    stage.style.height = `${model.get("height")}px`;
  }

  function describe() {
    const rate = meter.rate(performance.now());
    root.dataset.fps = rate.fps.toFixed(1);
    const parts = [model.get("session_name")];
    if (last) parts.push(video.describeStream(last, rate));
    if (picked && picked.atom !== null && picked.atom !== undefined) {
      parts.push(`atom ${picked.atom} ${picked.name} ${picked.residue_name}${picked.residue_id}`);
    }
    if (videoProblem) parts.push(`video off: ${videoProblem}`);
    hud.textContent = parts.join(" · ");
  }

  // the kernel's comm closed (a restart): say so now, and send nothing more into it
  model.on("comm_live_update", () => {
    gone = true;
    frozen();
  });
  model.on("msg:custom", (msg, buffers) => {
    lastFromKernel = performance.now();
    gone = false;
    if (msg.type === "image") {
      const view = buffers[0];
      const data = new Uint8Array(view.buffer, view.byteOffset, view.byteLength).slice();
      viewport.show({ ...msg, data });
    } else if (msg.type === "picked") {
      picked = msg;
      viewport.setMarker(msg.atom === null || msg.atom === undefined ? null : msg.position);
    } else if (msg.type === "status") {
      root.dataset.status = msg.status;
      banner.hidden = msg.status === "connected";
      banner.textContent = msg.message ?? "";
    }
  });
  model.on("change:camera", () => {
    const given = model.get("camera");
    const next = given ? normalizeCamera(given) : null;
    if (next === camera || (next && sent.some((c) => sameCamera(next, c)))) return;
    camera = next;
    sendView(false);
  });
  model.on("change:session_camera", () => viewport.drawOverlay());
  model.on("change:width", () => sizeStage());
  model.on("change:height", () => sizeStage());
  model.on("change:video", () => sendView(false));

  function frozen() {
    root.dataset.status = "kernel-gone";
    banner.hidden = false;
    banner.textContent =
      "No word from the kernel (restarted, stopped or disconnected): this view is frozen. " +
      "Run the cell again for a live one.";
  }

  const timer = setInterval(() => {
    if (gone || performance.now() - lastFromKernel > SILENCE_MS) frozen();
    describe();
    toKernel({ type: "shown", frames: drawn, fps: Number(root.dataset.fps) });
  }, 1000);

  sizeStage();
  codecs = await video.decodableCodecs(model.get("width"), model.get("height"));
  root.dataset.codecs = codecs.join(" ");
  viewport.measure(true);
  sendView(false);

  return () => {
    clearInterval(timer);
    viewport.video?.close();
    viewport.observer.disconnect();
    for (const url of Object.values(urls)) URL.revokeObjectURL(url);
  };
}

export default { render };
