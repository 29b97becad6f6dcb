// The video decoder, off the main thread: one WebCodecs VideoDecoder per stream, configured for
// latency, fed the server's frames in order; decoded VideoFrames go back to the page (moved,
// not copied), each tagged with its frame_id and the time its decode took. A stream changes
// size at a keyframe (smaller while someone steers): the decoder is configured again there.

let decoder = null;
let stream = null;
let size = "";
const started = new Map(); // frame_id -> performance.now() when it went into the decoder

/** Drop the decoder (an error may have closed it already) and what was in it. */
function closeDecoder() {
  try {
    decoder?.close();
  } catch {
    // closed by an error
  }
  decoder = null;
  stream = null;
  size = "";
  started.clear();
}

function fail(message) {
  closeDecoder();
  self.postMessage({ type: "error", message });
}

function open(m) {
  closeDecoder();
  decoder = new VideoDecoder({
    output(frame) {
      const frameId = frame.timestamp;
      const t0 = started.get(frameId);
      started.delete(frameId);
      const decodeMs = t0 === undefined ? 0 : performance.now() - t0;
      self.postMessage({ type: "frame", frame, frameId, decodeMs }, [frame]);
    },
    error(err) {
      fail(`${err.name}: ${err.message}`);
    },
  });
  stream = m.stream;
  configure(m);
}

/** (Re)configure for the size of keyframe `m`; frames already queued decode first. */
function configure(m) {
  decoder.configure({
    codec: m.codec,
    codedWidth: m.width + (m.width % 2),
    codedHeight: m.height + (m.height % 2),
    optimizeForLatency: true,
  });
  size = `${m.width}x${m.height}`;
}

self.onmessage = (e) => {
  const m = e.data;
  if (m.type === "reset") {
    closeDecoder();
    return;
  }
  if (m.type !== "chunk") return;
  if (m.stream !== stream || !decoder || (m.key && `${m.width}x${m.height}` !== size)) {
    if (!m.key) return; // a stream is joined at its keyframe
    try {
      if (m.stream === stream && decoder) configure(m);
      else open(m);
    } catch (err) {
      fail(`${err.name}: ${err.message}`);
      return;
    }
  }
  started.set(m.frameId, performance.now());
  try {
    decoder.decode(new EncodedVideoChunk({ type: m.key ? "key" : "delta", timestamp: m.frameId, data: m.data }));
  } catch (err) {
    fail(`${err.name}: ${err.message}`);
  }
};
