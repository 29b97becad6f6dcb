import assert from "node:assert/strict";
import { test } from "node:test";

import { ConnState, Connection, backoff, viewUrl } from "../src/connection.js";
import { decodeMessage, encodeMessage } from "../src/wire.js";

/** A scripted stand-in for the browser's WebSocket. */
class FakeSocket {
  static all = [];
  constructor(url) {
    this.url = url;
    this.sent = [];
    this.readyState = 0;
    FakeSocket.all.push(this);
  }
  send(bytes) {
    this.sent.push(decodeMessage(bytes));
  }
  close(code = 1000, reason = "") {
    if (this.readyState === 3) return;
    this.readyState = 3;
    this.onclose?.({ code, reason });
  }
  // server side
  open() {
    this.readyState = 1;
    this.onopen?.();
  }
  deliver(message) {
    this.onmessage?.({ data: encodeMessage(message).slice().buffer });
  }
}

/** Timers that run only when told to. */
class ManualTimers {
  constructor() {
    this.now = 0;
    this.queue = [];
    this.next = 1;
  }
  setTimeout(fn, ms) {
    const id = this.next++;
    this.queue.push({ id, at: this.now + ms, fn });
    return id;
  }
  clearTimeout(id) {
    this.queue = this.queue.filter((t) => t.id !== id);
  }
  setInterval(fn, ms) {
    const id = this.next++;
    const tick = () => {
      fn();
      this.queue.push({ id, at: this.now + ms, fn: tick });
    };
    this.queue.push({ id, at: this.now + ms, fn: tick });
    return id;
  }
  clearInterval(id) {
    this.clearTimeout(id);
  }
  advance(ms) {
    const end = this.now + ms;
    for (;;) {
      this.queue.sort((a, b) => a.at - b.at);
      const due = this.queue[0];
      if (!due || due.at > end) break;
      this.queue.shift();
      this.now = due.at;
      due.fn();
    }
    this.now = end;
  }
}

function setup(role = "steerer") {
  FakeSocket.all = [];
  const timers = new ManualTimers();
  const messages = [];
  const statuses = [];
  const conn = new Connection({
    url: "ws://h/ws/view",
    token: "tok",
    role,
    session: "s1",
    WebSocketImpl: FakeSocket,
    timers,
    now: () => timers.now,
    random: () => 0.5,
    onMessage: (m) => messages.push(m),
    onStatus: (s) => statuses.push(s),
  });
  conn.start();
  return { conn, timers, messages, statuses, socket: () => FakeSocket.all.at(-1) };
}

const welcome = (role) => ({ type: "welcome", session_id: "s1", client_id: "c1", role });

test("hello names role, token, session and protocol version; welcome makes it ready", () => {
  const { conn, socket, statuses } = setup();
  socket().open();
  assert.deepEqual(socket().sent[0], {
    type: "hello",
    role: "steerer",
    token: "tok",
    client: "dashboard",
    session: "s1",
    protocol_version: "1.7",
  });
  assert.equal(conn.send({ type: "pick", x: 1, y: 1 }), null, "nothing is sent before welcome");
  socket().deliver(welcome("steerer"));
  assert.equal(conn.state, ConnState.READY);
  assert.equal(statuses.at(-1).state, "connected");
  assert.equal(conn.send({ type: "pick", x: 1, y: 1 }), 1);
  assert.equal(conn.send({ type: "pick", x: 2, y: 1 }), 2);
  assert.equal(socket().sent[2].seq, 2);
});

test("the viewer token, refused for steering by name, joins read-only", () => {
  const { conn, timers, socket } = setup();
  socket().open();
  socket().deliver({
    type: "error",
    code: "forbidden",
    path: "hello.role",
    message: "the viewer token is read-only: role steerer needs the server token",
  });
  socket().close(1008, "forbidden");
  timers.advance(0);
  socket().open();
  assert.equal(socket().sent[0].role, "viewer");
  socket().deliver(welcome("viewer"));
  assert.equal(conn.role, "viewer");
  assert.ok(conn.status().fellBack);
});

test("a refused steerer token falls back to viewer once", () => {
  const { conn, timers, socket } = setup();
  socket().open();
  socket().deliver({ type: "error", code: "unauthorized", message: "missing or wrong token" });
  socket().close(1008, "unauthorized");
  timers.advance(0);
  assert.equal(FakeSocket.all.length, 2);
  socket().open();
  assert.equal(socket().sent[0].role, "viewer");
  socket().deliver(welcome("viewer"));
  assert.equal(conn.role, "viewer");
  assert.ok(conn.status().fellBack);
  // refused again, as viewer: that is final
  socket().close(1006);
  timers.advance(10000);
  socket().open();
  socket().deliver({ type: "error", code: "unauthorized", message: "missing or wrong token" });
  socket().close(1008, "unauthorized");
  timers.advance(60000);
  assert.equal(conn.state, ConnState.CLOSED);
  assert.match(conn.reason, /unauthorized/);
  assert.equal(FakeSocket.all.length, 3);
});

test("a viewer of a session the server does not have is told so, and does not retry", () => {
  const { conn, timers, socket } = setup("viewer");
  socket().open();
  socket().deliver({ type: "error", code: "not_found", message: "no session named 's1'", path: "hello.session" });
  socket().close(1008, "not_found");
  timers.advance(60000);
  assert.equal(conn.state, ConnState.CLOSED);
  assert.match(conn.reason, /no session named/);
  assert.equal(FakeSocket.all.length, 1);
});

test("a lost connection reconnects with growing delays, then numbers afresh", () => {
  const { conn, timers, socket } = setup();
  socket().open();
  socket().deliver(welcome("steerer"));
  conn.send({ type: "ping" });
  socket().close(1006);
  assert.equal(conn.state, ConnState.RECONNECTING);
  timers.advance(499);
  assert.equal(FakeSocket.all.length, 1);
  timers.advance(1);
  assert.equal(FakeSocket.all.length, 2);
  socket().close(1006); // refused again
  timers.advance(500);
  assert.equal(FakeSocket.all.length, 2, "the second delay is longer");
  timers.advance(600);
  assert.equal(FakeSocket.all.length, 3);
  socket().open();
  socket().deliver(welcome("steerer"));
  assert.equal(conn.attempt, 0);
  assert.equal(conn.send({ type: "ping" }), 1);
});

test("replies resolve by ref; pings keep the connection alive; silence reconnects", async () => {
  const { conn, timers, socket } = setup();
  socket().open();
  socket().deliver(welcome("viewer"));
  const pending = conn.request({ type: "pick", x: 3, y: 4 });
  socket().deliver({ type: "picked", ref: 1, atom: 7, element: "C" });
  const { seq, reply } = await pending;
  assert.equal(seq, 1);
  assert.equal(reply.atom, 7);
  timers.advance(5000);
  assert.equal(socket().sent.at(-1).type, "ping");
  timers.advance(15000);
  assert.equal(conn.state, ConnState.RECONNECTING, "no message for 15 s closes and retries");
});

test("undecodable messages are reported back to the server", () => {
  const errors = [];
  const { conn, socket } = setup();
  conn.onProtocolError = (e) => errors.push(e);
  socket().open();
  socket().deliver(welcome("steerer"));
  socket().onmessage({ data: new Uint8Array([0x93, 1, 2, 3]).buffer });
  assert.equal(errors.length, 1);
  assert.equal(socket().sent.at(-1).type, "error");
  assert.equal(socket().sent.at(-1).code, "invalid_message");
});

test("backoff doubles up to a cap and the view URL follows the page", () => {
  assert.deepEqual(
    [1, 2, 3, 4, 5, 9].map((n) => backoff(n, () => 0.5)),
    [500, 1000, 2000, 4000, 8000, 8000],
  );
  assert.equal(viewUrl({ protocol: "http:", host: "127.0.0.1:8765" }), "ws://127.0.0.1:8765/ws/view");
  assert.equal(viewUrl({ protocol: "https:", host: "x.org" }), "wss://x.org/ws/view");
});

test("a page names its instance in every hello, reconnections included", () => {
  FakeSocket.all = [];
  const timers = new ManualTimers();
  const conn = new Connection({
    url: "ws://h/ws/view",
    token: "tok",
    session: "s1",
    instance: "page-1234abcd",
    WebSocketImpl: FakeSocket,
    timers,
    now: () => timers.now,
    random: () => 0.5,
  });
  conn.start();
  FakeSocket.all.at(-1).open();
  assert.equal(FakeSocket.all.at(-1).sent[0].instance, "page-1234abcd");
  FakeSocket.all.at(-1).close(1006, "");
  timers.advance(1000);
  FakeSocket.all.at(-1).open();
  assert.equal(FakeSocket.all.length, 2);
  assert.equal(FakeSocket.all.at(-1).sent[0].instance, "page-1234abcd");
});
