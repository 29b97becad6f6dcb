// The dashboard's WebSocket to /ws/view: hello/welcome, numbered messages, replies by ref,
// liveness pings, automatic reconnect with backoff, and the one-time fallback from steerer to
// viewer when the token is refused for steering.

import { PROTOCOL_VERSION, WireError, decodeMessage, encodeMessage } from "./wire.js";

export const ConnState = Object.freeze({
  CONNECTING: "connecting",
  HANDSHAKE: "handshake",
  READY: "connected",
  RECONNECTING: "reconnecting",
  CLOSED: "closed",
});

/** Errors after which retrying cannot help. */
const FATAL_CODES = new Set(["unauthorized", "version_mismatch", "not_found"]);
const REPLY_TYPES = new Set(["picked", "selected", "params_ack", "pong", "error"]);

/** Reconnect delay (ms) before attempt `n` (1, 2, ...): 0.5 s doubling up to 8 s, +-20% jitter. */
export function backoff(n, random = Math.random) {
  const base = Math.min(8000, 500 * 2 ** Math.max(0, n - 1));
  return Math.round(base * (0.8 + 0.4 * random()));
}

/** ws:// or wss:// URL of the view endpoint for a page at `location`. */
export function viewUrl(location) {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/ws/view`;
}

export class Connection {
  constructor({
    url,
    token = null,
    role = "steerer",
    session = "default",
    client = "dashboard",
    instance = null,
    WebSocketImpl = globalThis.WebSocket,
    timers = globalThis,
    now = () => Date.now(),
    random = Math.random,
    pingIntervalMs = 5000,
    staleMs = 15000,
    onMessage = () => {},
    onStatus = () => {},
    onProtocolError = () => {},
  }) {
    Object.assign(this, { url, token, client, session, instance, WebSocketImpl, timers, now, random });
    Object.assign(this, { pingIntervalMs, staleMs, onMessage, onStatus, onProtocolError });
    this.requestedRole = role;
    this.role = role;
    this.fellBack = false;
    this.state = ConnState.CLOSED;
    this.ws = null;
    this.seq = 0;
    this.attempt = 0;
    this.welcome = null;
    this.reason = "";
    this.fatal = false;
    this.stopped = true;
    this.lastReceived = 0;
    this.replies = new Map(); // seq -> {resolve, reject, timer}
    this.retryTimer = null;
    this.pingTimer = null;
    this.retryAt = null;
    this.retryImmediately = false;
  }

  start() {
    this.stopped = false;
    this.fatal = false;
    this.open();
  }

  stop() {
    this.stopped = true;
    this.clearTimers();
    if (this.ws) this.ws.close(1000, "closed by the user");
    this.setState(ConnState.CLOSED, "closed");
  }

  /** Connect now (also skips a pending reconnect delay). */
  reconnectNow() {
    if (this.stopped || this.state === ConnState.READY || this.state === ConnState.HANDSHAKE) return;
    this.fatal = false;
    this.open();
  }

  status() {
    return {
      state: this.state,
      role: this.role,
      requestedRole: this.requestedRole,
      fellBack: this.fellBack,
      attempt: this.attempt,
      retryAt: this.retryAt,
      reason: this.reason,
      welcome: this.welcome,
    };
  }

  setState(state, reason = this.reason) {
    this.state = state;
    this.reason = reason;
    this.onStatus(this.status());
  }

  clearTimers() {
    if (this.retryTimer !== null) this.timers.clearTimeout(this.retryTimer);
    if (this.pingTimer !== null) this.timers.clearInterval(this.pingTimer);
    this.retryTimer = null;
    this.pingTimer = null;
    this.retryAt = null;
  }

  open() {
    this.clearTimers();
    if (this.ws) {
      const old = this.ws;
      this.ws = null;
      old.onclose = old.onmessage = old.onopen = old.onerror = null;
      old.close();
    }
    this.seq = 0;
    this.welcome = null;
    this.setState(ConnState.CONNECTING, this.attempt ? `attempt ${this.attempt + 1}` : "");
    let ws;
    try {
      ws = new this.WebSocketImpl(this.url);
    } catch (err) {
      this.scheduleRetry(`cannot open the WebSocket: ${err.message}`);
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => {
      if (this.ws !== ws) return;
      this.lastReceived = this.now();
      this.setState(ConnState.HANDSHAKE, "");
      this.sendRaw({
        type: "hello",
        role: this.role,
        token: this.token ?? undefined,
        client: this.client,
        session: this.session,
        instance: this.instance ?? undefined,
        protocol_version: PROTOCOL_VERSION,
      });
    };
    ws.onmessage = (event) => {
      if (this.ws === ws) this.receive(event.data);
    };
    ws.onerror = () => {};
    ws.onclose = (event) => {
      if (this.ws !== ws) return;
      this.ws = null;
      this.closed(event?.code, event?.reason);
    };
  }

  closed(code, reason) {
    if (this.pingTimer !== null) this.timers.clearInterval(this.pingTimer);
    this.pingTimer = null;
    for (const [, pending] of this.replies) {
      this.timers.clearTimeout(pending.timer);
      pending.reject(new Error("connection closed"));
    }
    this.replies.clear();
    if (this.stopped) {
      this.setState(ConnState.CLOSED, "closed");
      return;
    }
    if (this.fatal) {
      this.setState(ConnState.CLOSED, this.reason);
      return;
    }
    const why = this.reason || (reason ? `closed: ${reason}` : `connection lost${code ? ` (code ${code})` : ""}`);
    this.scheduleRetry(why);
  }

  scheduleRetry(reason) {
    this.attempt += 1;
    const delay = this.retryImmediately ? 0 : backoff(this.attempt, this.random);
    this.retryImmediately = false;
    this.retryAt = this.now() + delay;
    this.state = ConnState.RECONNECTING;
    this.reason = reason;
    this.onStatus(this.status());
    this.retryTimer = this.timers.setTimeout(() => {
      this.retryTimer = null;
      this.retryAt = null;
      if (!this.stopped) this.open();
    }, delay);
  }

  receive(data) {
    this.lastReceived = this.now();
    let message;
    try {
      message = decodeMessage(data);
    } catch (err) {
      const e = err instanceof WireError ? err : new WireError("invalid_message", String(err?.message ?? err));
      this.onProtocolError(e);
      this.sendRaw({ type: "error", code: e.code, message: e.message.slice(0, 4000), path: e.path || undefined });
      return;
    }
    if (message.type === "welcome") {
      this.welcome = message;
      this.role = message.role;
      this.attempt = 0;
      this.setState(ConnState.READY, this.fellBack ? "read-only: the token does not allow steering" : "");
      this.startPings();
    } else if (message.type === "error" && this.state === ConnState.HANDSHAKE) {
      this.handshakeError(message);
    }
    if (message.ref !== undefined && REPLY_TYPES.has(message.type)) {
      const pending = this.replies.get(message.ref);
      if (pending) {
        this.replies.delete(message.ref);
        this.timers.clearTimeout(pending.timer);
        pending.resolve(message);
      }
    }
    this.onMessage(message);
  }

  handshakeError(message) {
    // the token was refused for steering: a wrong one, or the viewer token (read-only)
    const notSteering =
      message.code === "unauthorized" || (message.code === "forbidden" && message.path === "hello.role");
    if (notSteering && this.role === "steerer" && !this.fellBack) {
      this.fellBack = true;
      this.role = "viewer";
      this.retryImmediately = true;
      this.reason = "the token was refused for steering; joining read-only";
      this.attempt = 0;
      return;
    }
    if (FATAL_CODES.has(message.code)) {
      this.fatal = true;
      this.reason = `${message.code}: ${message.message}`;
    } else {
      this.reason = `${message.code}: ${message.message}`;
    }
  }

  startPings() {
    if (this.pingTimer !== null) this.timers.clearInterval(this.pingTimer);
    this.pingTimer = this.timers.setInterval(() => {
      if (this.state !== ConnState.READY) return;
      if (this.now() - this.lastReceived > this.staleMs) {
        this.reason = "no message from the server for a while";
        this.ws?.close(4000, "stale");
        return;
      }
      this.send({ type: "ping", client_time: Date.now() / 1000 });
    }, this.pingIntervalMs);
  }

  sendRaw(message) {
    if (!this.ws || this.ws.readyState !== 1) return false;
    this.ws.send(encodeMessage(message));
    return true;
  }

  get ready() {
    return this.state === ConnState.READY;
  }

  /** Send a numbered message; returns its seq, or null when not connected. */
  send(message) {
    if (!this.ready) return null;
    const seq = ++this.seq;
    return this.sendRaw({ ...message, seq }) ? seq : null;
  }

  /** Send and wait for the reply that carries ref = its seq (picked, selected, params_ack, pong, error). */
  request(message, timeoutMs = 10000) {
    const seq = this.send(message);
    if (seq === null) return Promise.reject(new Error("not connected"));
    return new Promise((resolve, reject) => {
      const timer = this.timers.setTimeout(() => {
        this.replies.delete(seq);
        reject(new Error(`no reply to ${message.type} within ${timeoutMs / 1000} s`));
      }, timeoutMs);
      this.replies.set(seq, { resolve, reject, timer });
    }).then((reply) => ({ seq, reply }));
  }
}
