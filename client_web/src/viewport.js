// The live view: a canvas sized to its container and the device pixel ratio, streamed images
// drawn as they arrive (stale ones skipped), an overlay for the selected atom and the pull
// arrow, and the pointer, wheel, touch and keyboard gestures that move the camera.

import { orbit, pan, project, zoom } from "./camera.js";
import { cellEdges } from "./cell.js";
import { placeLabels } from "./labels.js";
import { VIDEO_FORMATS, VideoPipe } from "./video.js";

const CLICK_SLOP_PX = 4;
const WHEEL_END_MS = 180;
const KEY_TURN_PX = 24;
const KEY_PAN_PX = 24;

export class Viewport {
  constructor({
    container,
    canvas,
    overlay,
    placeholder,
    getCamera,
    canPull = () => false,
    pullWithoutModifier = () => false,
    onResize = () => {},
    onCamera = () => {},
    onClick = () => {},
    onPullStart = () => {},
    onPullMove = () => {},
    onPullEnd = () => {},
    onDrawn = () => {},
    onDecodeError = () => {},
    onVideoDecoded = () => {},
    onImageDecoded = () => {},
    onVideoError = () => {},
    makeVideoPipe = (handlers) => new VideoPipe(handlers),
  }) {
    Object.assign(this, { container, canvas, overlay, placeholder, getCamera, canPull, pullWithoutModifier });
    Object.assign(this, { onResize, onCamera, onClick, onPullStart, onPullMove, onPullEnd, onDrawn, onDecodeError });
    Object.assign(this, { onVideoDecoded, onImageDecoded, onVideoError, makeVideoPipe });
    this.video = null; // the decoder pipe, made with the first video frame
    this.ctx = canvas.getContext("2d", { alpha: false });
    this.octx = overlay.getContext("2d");
    this.resolution = 1;
    this.limits = { side: 4096, pixels: 3840 * 2160 };
    this.size = { cssW: 1, cssH: 1, dpr: 1, viewW: 1, viewH: 1 };
    this.drawnId = -1;
    this.decoding = false;
    this.queued = null;
    this.skipped = 0;
    this.drawn = 0;
    this.bitmap = null;
    this.marker = null; // world position of the selected atom
    this.pullLine = null; // {from: world position, to: [viewX, viewY]}
    this.pointers = new Map();
    this.gesture = null;
    this.wheelTimer = null;
    this.bind();
    this.observer = new ResizeObserver(() => this.measure());
    this.observer.observe(container);
    window.addEventListener("resize", () => this.measure()); // also catches device pixel ratio changes
    this.measure();
  }

  // ------------------------------------------------------------------ size

  setResolution(factor) {
    this.resolution = factor;
    this.measure(true);
  }

  setLimits(limits) {
    if (limits) this.limits = { side: limits.max_image_side ?? 4096, pixels: limits.max_image_pixels ?? 3840 * 2160 };
    this.measure(true);
  }

  /** Full-resolution size (CSS pixels times device pixel ratio), within the server's limits. */
  fullSize() {
    const { cssW, cssH, dpr } = this.size;
    return this.fit(Math.round(cssW * dpr), Math.round(cssH * dpr));
  }

  fit(w, h) {
    let s = Math.min(1, this.limits.side / Math.max(w, h), Math.sqrt(this.limits.pixels / Math.max(1, w * h)));
    if (!Number.isFinite(s) || s <= 0) s = 1;
    return [Math.max(1, Math.floor(w * s)), Math.max(1, Math.floor(h * s))];
  }

  measure(force = false) {
    const rect = this.container.getBoundingClientRect();
    const cssW = Math.max(1, Math.round(rect.width));
    const cssH = Math.max(1, Math.round(rect.height));
    const dpr = window.devicePixelRatio || 1;
    const [viewW, viewH] = this.fit(Math.round(cssW * dpr * this.resolution), Math.round(cssH * dpr * this.resolution));
    const s = this.size;
    if (!force && s.cssW === cssW && s.cssH === cssH && s.dpr === dpr && s.viewW === viewW && s.viewH === viewH) return;
    this.size = { cssW, cssH, dpr, viewW, viewH };
    this.canvas.width = viewW;
    this.canvas.height = viewH;
    this.overlay.width = Math.round(cssW * dpr);
    this.overlay.height = Math.round(cssH * dpr);
    this.redraw();
    this.drawOverlay();
    this.onResize(this.size);
  }

  /** Pointer position (client coordinates) in view pixels and CSS pixels. */
  locate(event) {
    const rect = this.canvas.getBoundingClientRect();
    const cx = event.clientX - rect.left;
    const cy = event.clientY - rect.top;
    const { cssW, cssH, viewW, viewH } = this.size;
    return {
      cssX: cx,
      cssY: cy,
      x: Math.min(viewW - 1, Math.max(0, Math.floor((cx / cssW) * viewW))),
      y: Math.min(viewH - 1, Math.max(0, Math.floor((cy / cssH) * viewH))),
    };
  }

  // ------------------------------------------------------------------ images

  /** Forget frame numbering (a new connection, possibly to a restarted server). */
  resetFrames() {
    this.drawnId = -1;
    this.queued = null;
  }

  /** Decode and draw an image message; older frames than the one on screen are skipped.
   * Video frames all go to the decoder (each depends on the last) and are drawn when
   * decoded, unless a newer image was drawn meanwhile. */
  async show(msg) {
    if (VIDEO_FORMATS.has(msg.format)) {
      if (!this.video) {
        this.video = this.makeVideoPipe({
          onFrame: (frame, m, decodeMs) => this.showVideoFrame(frame, m, decodeMs),
          onError: (message) => this.onVideoError(message),
        });
      }
      this.video.push(msg);
      return;
    }
    if (msg.frame_id <= this.drawnId) {
      this.skipped += 1;
      return;
    }
    if (this.decoding) {
      if (this.queued) this.skipped += 1;
      this.queued = msg;
      return;
    }
    this.decoding = true;
    let bitmap = null;
    const t0 = performance.now();
    try {
      bitmap = await createImageBitmap(new Blob([msg.data], { type: `image/${msg.format}` }));
    } catch (err) {
      this.onDecodeError(err, msg);
    }
    this.decoding = false;
    if (bitmap) {
      this.present(bitmap, msg);
      // acknowledged as video frames are: the server paces images by the link
      this.onImageDecoded(msg, performance.now() - t0);
    }
    const next = this.queued;
    this.queued = null;
    if (next) await this.show(next);
  }

  showVideoFrame(frame, msg, decodeMs) {
    this.onVideoDecoded(msg, decodeMs);
    this.present(frame, msg);
  }

  /** Put a decoded picture (ImageBitmap or VideoFrame) on screen, unless a newer one is
   * there already; the one it replaces, or itself when it is older, is closed. */
  present(picture, msg) {
    if (msg.frame_id <= this.drawnId) {
      picture.close();
      this.skipped += 1;
      return;
    }
    this.drawnId = msg.frame_id;
    this.bitmap?.close();
    this.bitmap = picture;
    this.redraw();
    this.drawn += 1;
    this.placeholder.hidden = true;
    this.onDrawn(msg, performance.now());
  }

  /** Start the video decoder over (a new connection, or back from a failure). */
  resetVideo() {
    this.video?.reset();
  }

  /** Draw the latest image over the canvas (letterboxed if its shape is not the view's). */
  redraw() {
    if (!this.bitmap) return;
    const { width: cw, height: ch } = this.canvas;
    // an ImageBitmap (JPEG) or a VideoFrame (video)
    const iw = this.bitmap.displayWidth ?? this.bitmap.width;
    const ih = this.bitmap.displayHeight ?? this.bitmap.height;
    const g = this.ctx;
    g.imageSmoothingEnabled = true;
    g.imageSmoothingQuality = "high";
    if (Math.abs(Math.log((iw / ih) * (ch / cw))) < 0.03) {
      g.drawImage(this.bitmap, 0, 0, cw, ch);
      return;
    }
    const s = Math.min(cw / iw, ch / ih);
    const w = iw * s;
    const h = ih * s;
    g.fillStyle = "#000";
    g.fillRect(0, 0, cw, ch);
    g.drawImage(this.bitmap, (cw - w) / 2, (ch - h) / 2, w, h);
  }

  // ------------------------------------------------------------------ overlay

  setMarker(position) {
    this.marker = position;
    this.drawOverlay();
  }

  /** Labelled atoms and the measurement joining them: [{position, label}], {kind, text}. */
  setAnnotations(atoms, measured) {
    this.annotations = atoms;
    this.measured = measured;
    this.drawOverlay();
  }

  /** The periodic box {origin, vectors} drawn as an outline (null: none). */
  setCell(cell) {
    this.cellEdges = cellEdges(cell);
    this.drawOverlay();
  }

  setPullLine(line) {
    this.pullLine = line;
    this.drawOverlay();
  }

  /** A dashed ring at view pixel [x, y] while a pick is on its way (null clears it): the pull
   * shows at mouse-down, before the server has said which atom is under the pointer. */
  setPending(point) {
    this.pending = point;
    this.drawOverlay();
  }

  /** Project a world point to overlay pixels with the current camera. */
  toOverlay(point) {
    const cam = this.getCamera();
    if (!cam) return null;
    const { viewW, viewH } = this.size;
    const [px, py, depth] = project(cam, point, viewW, viewH);
    if (!(depth > 0)) return null;
    return [(px / viewW) * this.overlay.width, (py / viewH) * this.overlay.height];
  }

  drawOverlay() {
    const g = this.octx;
    const { dpr } = this.size;
    g.clearRect(0, 0, this.overlay.width, this.overlay.height);
    if (this.cellEdges?.length) {
      g.save();
      g.strokeStyle = "rgba(200, 205, 215, 0.8)";
      g.lineWidth = dpr;
      g.beginPath();
      for (const [a, b] of this.cellEdges) {
        const p = this.toOverlay(a);
        const q = this.toOverlay(b);
        if (!p || !q) continue; // an edge behind the camera
        g.moveTo(p[0], p[1]);
        g.lineTo(q[0], q[1]);
      }
      g.stroke();
      g.restore();
    }
    if (this.marker) {
      const p = this.toOverlay(this.marker);
      if (p) {
        g.strokeStyle = "#ffd166";
        g.lineWidth = 2 * dpr;
        g.beginPath();
        g.arc(p[0], p[1], 9 * dpr, 0, 2 * Math.PI);
        g.stroke();
      }
    }
    const shown = (this.annotations ?? []).map((a) => ({ ...a, at: a.position ? this.toOverlay(a.position) : null }));
    const labels = []; // {anchor, text, color}: placed together below, none over another
    let measuredLabel = null;
    if (shown.length > 1 && shown.every((a) => a.at)) {
      g.save();
      g.strokeStyle = "#7fd1a6";
      g.lineWidth = 2 * dpr;
      g.setLineDash([6 * dpr, 4 * dpr]);
      g.beginPath();
      shown.forEach((a, i) => (i ? g.lineTo(a.at[0], a.at[1]) : g.moveTo(a.at[0], a.at[1])));
      g.stroke();
      g.restore();
      if (this.measured) {
        const mid = shown.length === 2 ? midpoint(shown[0].at, shown[1].at) : shown[1].at;
        measuredLabel = { anchor: mid, text: this.measured.text, color: "#7fd1a6" };
      }
    }
    shown.forEach((a, i) => {
      if (!a.at) return;
      g.save();
      g.strokeStyle = "#ffd166";
      g.lineWidth = 2 * dpr;
      g.beginPath();
      g.arc(a.at[0], a.at[1], 7 * dpr, 0, 2 * Math.PI);
      g.stroke();
      g.restore();
      labels.push({ anchor: a.at, text: shown.length > 1 ? `${i + 1} ${a.label}` : a.label, color: "#ffd166" });
    });
    if (measuredLabel) labels.push(measuredLabel);
    this.drawLabels(g, labels, shown, dpr);
    if (this.pending) {
      const { viewW, viewH } = this.size;
      g.save();
      g.strokeStyle = "#ef476f";
      g.lineWidth = 2 * dpr;
      g.setLineDash([4 * dpr, 3 * dpr]);
      g.beginPath();
      g.arc((this.pending[0] / viewW) * this.overlay.width, (this.pending[1] / viewH) * this.overlay.height, 11 * dpr, 0, 2 * Math.PI);
      g.stroke();
      g.restore();
    }
    if (this.pullLine) {
      const a = this.toOverlay(this.pullLine.from);
      const { viewW, viewH } = this.size;
      const b = [
        (this.pullLine.to[0] / viewW) * this.overlay.width,
        (this.pullLine.to[1] / viewH) * this.overlay.height,
      ];
      if (a) drawArrow(g, a, b, dpr);
      this.arrowFrom = a; // overlay pixels, for automation
    } else this.arrowFrom = null;
  }

  /** The labels, placed beside their anchors without covering each other or the markers;
   * their rectangles (overlay pixels) stay in `labelRects` for automation. */
  drawLabels(g, labels, shown, dpr) {
    g.save();
    g.font = `${12 * dpr}px system-ui, sans-serif`;
    const items = labels
      .filter((l) => l.text)
      .map((l) => ({ ...l, w: g.measureText(l.text).width + 8 * dpr, h: 16 * dpr }));
    const r = 8 * dpr; // an atom's marker
    const obstacles = shown.filter((a) => a.at).map((a) => ({ x: a.at[0] - r, y: a.at[1] - r, w: 2 * r, h: 2 * r }));
    const rects = placeLabels(items, { w: this.overlay.width, h: this.overlay.height }, { gap: 6 * dpr, obstacles });
    items.forEach((item, i) => {
      const rect = rects[i];
      if (rect.moved) {
        g.strokeStyle = "rgba(230, 230, 230, 0.6)";
        g.lineWidth = dpr;
        g.beginPath();
        g.moveTo(item.anchor[0], item.anchor[1]);
        g.lineTo(rect.x + rect.w / 2, rect.y + rect.h / 2);
        g.stroke();
      }
      g.fillStyle = "rgba(10, 12, 14, 0.75)";
      g.fillRect(rect.x, rect.y, rect.w, rect.h);
      g.fillStyle = item.color;
      g.fillText(item.text, rect.x + 4 * dpr, rect.y + rect.h - 4 * dpr);
    });
    g.restore();
    this.labelRects = rects.map(({ x, y, w, h }, i) => ({ x, y, w, h, text: items[i].text }));
  }

  // ------------------------------------------------------------------ gestures

  bind() {
    const c = this.canvas;
    c.addEventListener("pointerdown", (e) => this.pointerDown(e));
    c.addEventListener("pointermove", (e) => this.pointerMove(e));
    c.addEventListener("pointerup", (e) => this.pointerUp(e));
    c.addEventListener("pointercancel", (e) => this.pointerUp(e, true));
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
    c.addEventListener("keydown", (e) => this.key(e));
    window.addEventListener("keydown", (e) => this.modifier(e));
    window.addEventListener("keyup", (e) => this.modifier(e));
  }

  modifier(e) {
    const ready = (e.ctrlKey || e.metaKey || this.pullWithoutModifier()) && this.canPull();
    this.canvas.classList.toggle("pull-ready", ready && !this.gesture);
  }

  pointerDown(e) {
    this.canvas.focus({ preventScroll: true });
    const at = this.locate(e);
    this.pointers.set(e.pointerId, { cssX: at.cssX, cssY: at.cssY });
    try {
      this.canvas.setPointerCapture(e.pointerId);
    } catch {
      /* the pointer is already gone */
    }
    if (this.pointers.size === 2) {
      if (this.gesture?.kind === "pull") this.onPullEnd();
      this.gesture = { kind: "pinch", camera: this.getCamera(), ...this.pinchState() };
      return;
    }
    if (this.pointers.size > 2) return;
    const wantsPull = e.button === 0 && (e.ctrlKey || e.metaKey || this.pullWithoutModifier());
    let kind = "orbit";
    if (wantsPull && this.canPull()) kind = "pull";
    else if (e.button === 2 || e.button === 1 || e.shiftKey) kind = "pan";
    this.gesture = {
      kind,
      start: at,
      last: at,
      camera: this.getCamera(),
      moved: false,
      button: e.button,
      shift: e.shiftKey,
    };
    if (kind === "pull") {
      e.preventDefault();
      this.canvas.classList.add("pulling");
      this.onPullStart(at.x, at.y);
    }
  }

  pinchState() {
    const [a, b] = [...this.pointers.values()];
    return {
      dist: Math.hypot(a.cssX - b.cssX, a.cssY - b.cssY) || 1,
      mid: [(a.cssX + b.cssX) / 2, (a.cssY + b.cssY) / 2],
    };
  }

  pointerMove(e) {
    if (!this.pointers.has(e.pointerId)) return;
    const at = this.locate(e);
    this.pointers.set(e.pointerId, { cssX: at.cssX, cssY: at.cssY });
    const g = this.gesture;
    if (!g) return;
    const h = this.size.cssH;
    if (g.kind === "pinch") {
      if (this.pointers.size < 2 || !g.camera) return;
      const now = this.pinchState();
      let cam = zoom(g.camera, now.dist / g.dist);
      cam = pan(cam, now.mid[0] - g.mid[0], now.mid[1] - g.mid[1], h);
      this.onCamera(cam, true);
      return;
    }
    if (g.kind === "pull") {
      this.onPullMove(at.x, at.y);
      return;
    }
    const dx = at.cssX - g.start.cssX;
    const dy = at.cssY - g.start.cssY;
    if (!g.moved && Math.hypot(dx, dy) < CLICK_SLOP_PX) return;
    if (!g.camera) return;
    g.moved = true;
    this.canvas.classList.add("dragging");
    const cam = g.kind === "pan" ? pan(g.camera, dx, dy, h) : orbit(g.camera, dx, dy, h);
    g.latest = cam;
    this.onCamera(cam, true);
  }

  pointerUp(e, cancelled = false) {
    if (!this.pointers.has(e.pointerId)) return;
    this.pointers.delete(e.pointerId);
    const g = this.gesture;
    if (!g) return;
    if (g.kind === "pinch") {
      if (this.pointers.size === 0) {
        this.gesture = null;
        this.onCamera(this.getCamera(), false);
      }
      return;
    }
    this.gesture = null;
    this.canvas.classList.remove("dragging", "pulling");
    if (g.kind === "pull") {
      this.onPullEnd();
      return;
    }
    if (g.moved) {
      this.onCamera(g.latest ?? this.getCamera(), false);
    } else if (!cancelled && g.button === 0 && (g.kind === "orbit" || (g.kind === "pan" && g.shift))) {
      this.onClick(g.start.x, g.start.y, { add: g.shift });
    }
  }

  wheel(e) {
    e.preventDefault();
    const cam = this.getCamera();
    if (!cam) return;
    const unit = e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? this.size.cssH : 1;
    const k = e.ctrlKey ? 0.01 : 0.0015; // ctrl+wheel is a trackpad pinch
    const factor = Math.exp(-e.deltaY * unit * k);
    this.onCamera(zoom(cam, factor), true);
    clearTimeout(this.wheelTimer);
    this.wheelTimer = setTimeout(() => this.onCamera(this.getCamera(), false), WHEEL_END_MS);
  }

  /** Keyboard camera control while the view has focus. */
  key(e) {
    const cam = this.getCamera();
    if (!cam || e.altKey || e.ctrlKey || e.metaKey) return;
    const h = this.size.cssH;
    const arrows = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] };
    let next = null;
    if (arrows[e.key]) {
      const [sx, sy] = arrows[e.key];
      next = e.shiftKey
        ? pan(cam, sx * KEY_PAN_PX, sy * KEY_PAN_PX, h)
        : orbit(cam, sx * KEY_TURN_PX, sy * KEY_TURN_PX, h);
    } else if (e.key === "+" || e.key === "=") {
      next = zoom(cam, 1.15);
    } else if (e.key === "-" || e.key === "_") {
      next = zoom(cam, 1 / 1.15);
    } else if (e.key === "Enter" || e.key === " ") {
      if (e.key === " ") return; // space belongs to the simulation shortcut
      const { viewW, viewH } = this.size;
      this.onClick(Math.floor(viewW / 2), Math.floor(viewH / 2));
      e.preventDefault();
      return;
    }
    if (next) {
      e.preventDefault();
      e.stopPropagation();
      this.onCamera(next, false);
    }
  }
}

function midpoint(a, b) {
  return [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
}

function drawArrow(g, a, b, dpr) {
  const dx = b[0] - a[0];
  const dy = b[1] - a[1];
  const len = Math.hypot(dx, dy);
  g.save();
  g.strokeStyle = "#e06c5a";
  g.fillStyle = "#e06c5a";
  g.lineWidth = 3 * dpr;
  g.beginPath();
  g.arc(a[0], a[1], 6 * dpr, 0, 2 * Math.PI);
  g.fill();
  if (len > 2) {
    const ux = dx / len;
    const uy = dy / len;
    const head = Math.min(14 * dpr, len * 0.6);
    g.beginPath();
    g.moveTo(a[0], a[1]);
    g.lineTo(b[0] - ux * head * 0.8, b[1] - uy * head * 0.8);
    g.stroke();
    g.beginPath();
    g.moveTo(b[0], b[1]);
    g.lineTo(b[0] - ux * head - uy * head * 0.5, b[1] - uy * head + ux * head * 0.5);
    g.lineTo(b[0] - ux * head + uy * head * 0.5, b[1] - uy * head - ux * head * 0.5);
    g.closePath();
    g.fill();
  }
  g.restore();
}
