// Video streaming in the browser: which codecs this browser decodes (WebCodecs), a decoder in a
// Worker that turns the server's stream into VideoFrames, and a meter of what arrives (bit rate,
// frames per second) for the overlay. JPEG stays the fallback: no WebCodecs, a codec the server
// cannot encode, or any decoder error (the dashboard then asks for JPEG without a reload).

/** The server's wire codecs with the WebCodecs codec string each is decoded with (the same
 * table as server/pipeline/video.py). Order: the dashboard's preference, best first. */
export const CODECS = [
  ["h264", "avc1.640033"],
  ["av1", "av01.0.13M.08"],
  ["vp9", "vp09.00.51.08"],
  ["h264-baseline", "avc1.42E033"],
];

export const VIDEO_FORMATS = new Set(["h264", "av1", "vp9"]);

const NAMES = { h264: "H.264", av1: "AV1", vp9: "VP9", jpeg: "JPEG", png: "PNG" };

export function formatName(format) {
  return NAMES[format] ?? String(format).toUpperCase();
}

/**
 * The wire codecs `decoderClass` (WebCodecs' VideoDecoder) decodes at this size, in preference
 * order; [] without WebCodecs. Cached per size: the browser answers quickly but not instantly.
 */
export async function decodableCodecs(width, height, decoderClass = globalThis.VideoDecoder, cache = new Map()) {
  if (!decoderClass?.isConfigSupported) return [];
  const key = `${width}x${height}`;
  if (cache.has(key)) return cache.get(key);
  const out = [];
  for (const [name, codec] of CODECS) {
    try {
      const { supported } = await decoderClass.isConfigSupported({
        codec,
        codedWidth: width + (width % 2),
        codedHeight: height + (height % 2),
        optimizeForLatency: true,
      });
      if (supported) out.push(name);
    } catch {
      // an unknown codec string is "not supported"
    }
  }
  cache.set(key, out);
  return out;
}

/** What the stream delivers: bytes and frames over the last second, for the overlay. */
export class DeliveryMeter {
  constructor(windowMs = 1000) {
    this.windowMs = windowMs;
    this.events = []; // [t, bytes]
  }

  add(t, bytes) {
    this.events.push([t, bytes]);
    this.trim(t);
  }

  trim(t) {
    while (this.events.length && this.events[0][0] < t - this.windowMs) this.events.shift();
  }

  /** { kbps, fps } over the window ending at `t`. */
  rate(t) {
    this.trim(t);
    const bytes = this.events.reduce((s, [, b]) => s + b, 0);
    const seconds = this.windowMs / 1000;
    return { kbps: (bytes * 8) / 1000 / seconds, fps: this.events.length / seconds };
  }
}

/** One line for the overlay: "H.264 (libx264) · 4.2 Mbit/s of 9.3 · 59 fps". */
export function describeStream(msg, rate) {
  const mbit = (kbps) => (kbps >= 1000 ? `${(kbps / 1000).toFixed(1)} Mbit/s` : `${Math.round(kbps)} kbit/s`);
  const name = formatName(msg.format) + (msg.encoder ? ` (${msg.encoder})` : "");
  const target = msg.bitrate_kbps ? ` of ${mbit(msg.bitrate_kbps)}` : "";
  return `${name} · ${mbit(rate.kbps)}${target} · ${Math.round(rate.fps)} fps`;
}

/**
 * The decoder, in a Worker: `push(msg)` sends it a video image message; `onFrame(frame, msg,
 * decodeMs)` gets each decoded VideoFrame (the receiver closes it), `onError(message)` a
 * decoder failure (the pipe then stops; the dashboard falls back to JPEG).
 */
export class VideoPipe {
  constructor({ onFrame, onError, workerUrl = new URL("./video.worker.js", import.meta.url) }) {
    this.onFrame = onFrame;
    this.onError = onError;
    this.pending = new Map(); // frame_id -> image message, until its frame comes back
    this.worker = new Worker(workerUrl, { type: "module" });
    this.worker.onmessage = (e) => this.received(e.data);
    this.worker.onerror = (e) => this.onError(e.message || "the video worker failed");
    this.failed = false;
  }

  push(msg) {
    if (this.failed) return;
    this.pending.set(msg.frame_id, msg);
    if (this.pending.size > 64) this.pending.delete(this.pending.keys().next().value);
    const data = msg.data.slice().buffer; // its own buffer, moved to the worker
    this.worker.postMessage(
      {
        type: "chunk",
        stream: msg.stream,
        codec: msg.codec,
        key: msg.key !== false,
        frameId: msg.frame_id,
        width: msg.width,
        height: msg.height,
        data,
      },
      [data],
    );
  }

  received(m) {
    if (m.type === "frame") {
      const msg = this.pending.get(m.frameId);
      this.pending.delete(m.frameId);
      if (msg) this.onFrame(m.frame, msg, m.decodeMs);
      else m.frame.close();
    } else if (m.type === "error") {
      this.failed = true;
      this.pending.clear();
      this.onError(m.message);
    }
  }

  /** Start over (a new connection): the next frame must be a keyframe of some stream. */
  reset() {
    this.failed = false;
    this.pending.clear();
    this.worker.postMessage({ type: "reset" });
  }

  close() {
    this.worker.terminate();
  }
}
