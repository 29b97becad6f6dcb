// The dashboard's view: the camera and the `view` message that carries it (size, tracked atoms,
// the video codecs this browser decodes), the images drawn and what the HUD says of them, and the
// URL hash that follows them.

import { DEFAULT_CAMERA, normalizeCamera, project, setProjection } from "./camera.js";
import { $, setText } from "./dom.js";
import { integer, milliseconds, sig } from "./format.js";
import { trackedAtoms } from "./measure.js";
import { clamp } from "./params.js";
import { encodeHash } from "./urlstate.js";
import { decodableCodecs, describeStream } from "./video.js";

export class DashboardView {
  resized(size) {
    this.viewSize = [size.viewW, size.viewH];
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
    setText($("hud-size"), imageSizeText(msg, this.viewSize));
    setText($("hud-step"), `step ${integer(msg.step)}`);
    setText($("hud-fps"), `${sig(this.shownRate.rate(t), 3)} fps`);
    setText($("hud-stream"), describeStream(msg, this.meter.rate(t)));
    vp.dataset.format = msg.format;
    this.viewport.drawOverlay();
  }


  /** CSS-pixel position of a world point in the view (for scripts and the devtools console). */
  projectToPage(point) {
    if (!this.camera) return null;
    const { viewW, viewH, cssW, cssH } = this.viewport.size;
    const [px, py, depth] = project(this.camera, point, viewW, viewH);
    const rect = $("view").getBoundingClientRect();
    return { x: rect.left + (px / viewW) * cssW, y: rect.top + (py / viewH) * cssH, depth };
  }
}

/** The HUD's size: the view's, or "520×313 of 1040×627" for an image drawn smaller than the
 * view (a live image shrunk to its time budget, scaled up until the full-size one comes). */
export function imageSizeText(msg, view) {
  if (!view) return `${msg.width}×${msg.height}`;
  const [w, h] = view;
  return msg.width === w && msg.height === h ? `${w}×${h}` : `${msg.width}×${msg.height} of ${w}×${h}`;
}
