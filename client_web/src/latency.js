// Steer-to-photon latency: the time from sending a view or render_params message (seq) until the
// first image that reflects it (image.ref = that seq, or a later one) is on screen.

/** Remembers when each steering message left and measures it once against the images. */
export class LatencyTracker {
  constructor({ maxPending = 256, window = 64 } = {}) {
    this.maxPending = maxPending;
    this.window = window;
    this.pending = new Map(); // seq -> {t, kind}
    this.samples = []; // recent latencies, ms
  }

  /** A message with `seq` of `kind` was sent at time `t` (ms, monotonic clock). */
  sent(seq, kind, t) {
    this.pending.set(seq, { t, kind });
    while (this.pending.size > this.maxPending) {
      this.pending.delete(this.pending.keys().next().value);
    }
  }

  /**
   * An image answering `ref` was shown at time `t`. Returns {latency, kind} for the first image
   * reflecting that message, or null (no ref, unknown ref, already measured). Messages sent
   * before `ref` are answered by the same image: they are settled without a sample, since the
   * server coalesced them into the newer one.
   */
  shown(ref, t) {
    if (ref === undefined || ref === null) return null;
    const entry = this.pending.get(ref);
    for (const seq of [...this.pending.keys()]) {
      if (seq <= ref) this.pending.delete(seq);
    }
    if (!entry) return null;
    const latency = Math.max(0, t - entry.t);
    this.samples.push(latency);
    if (this.samples.length > this.window) this.samples.shift();
    return { latency, kind: entry.kind };
  }

  /** Forget everything outstanding (a new connection numbers its messages afresh). */
  reset() {
    this.pending.clear();
  }

  /** Summary of recent samples: {count, last, mean, p95} in ms (null when none). */
  summary() {
    const n = this.samples.length;
    if (!n) return { count: 0, last: null, mean: null, p95: null };
    const sorted = [...this.samples].sort((a, b) => a - b);
    const mean = sorted.reduce((a, b) => a + b, 0) / n;
    const p95 = sorted[Math.min(n - 1, Math.ceil(0.95 * n) - 1)];
    return { count: n, last: this.samples[n - 1], mean, p95 };
  }
}

/** Events per second over a sliding window (frames shown, messages received). */
export class RateMeter {
  constructor(windowMs = 2000) {
    this.windowMs = windowMs;
    this.times = [];
  }

  tick(t) {
    this.times.push(t);
    this.prune(t);
  }

  prune(t) {
    while (this.times.length && t - this.times[0] > this.windowMs) this.times.shift();
  }

  rate(t) {
    this.prune(t);
    if (this.times.length < 2) return this.times.length ? 1000 / this.windowMs : 0;
    const span = Math.max(t - this.times[0], 1);
    return (this.times.length * 1000) / Math.max(span, this.windowMs / 2);
  }
}

/** Clock offset and round trip from ping/pong: server_time (s) against local wall time (s). */
export function clockSample(clientSent, serverTime, clientReceived) {
  const rtt = Math.max(0, clientReceived - clientSent);
  return { rtt, offset: serverTime - (clientSent + rtt / 2) };
}
