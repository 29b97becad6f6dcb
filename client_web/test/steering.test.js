import assert from "node:assert/strict";
import { test } from "node:test";

import { APPLIED, AckTracker, FAILED, PENDING } from "../src/steering.js";

test("a change is pending until its ack names the step", () => {
  const acks = new AckTracker();
  assert.equal(acks.sent(4, "temperature_K").state, PENDING);
  assert.equal(acks.status("temperature_K").text, "pending…");
  assert.equal(acks.ack({ type: "params_ack", ref: 99, ok: true, step: 1 }), null, "not ours");
  const { key, status } = acks.ack({ type: "params_ack", ref: 4, ok: true, step: 12345, time_ps: 24.69 });
  assert.equal(key, "temperature_K");
  assert.equal(status.state, APPLIED);
  assert.equal(status.text, "applied at step 12,345 (24.69 ps)");
  assert.equal(acks.pendingCount, 0);
});

test("failures show the detail; errors show code and message", () => {
  const acks = new AckTracker();
  acks.sent(1, "timestep_fs");
  acks.sent(2, "control");
  assert.equal(
    acks.ack({ ref: 1, ok: false, detail: "time step too large" }).status.text,
    "failed: time step too large",
  );
  const e = acks.error({ type: "error", ref: 2, code: "not_ready", message: "no simulation is connected" });
  assert.equal(e.status.state, FAILED);
  assert.equal(e.status.text, "failed: not_ready: no simulation is connected");
});

test("an older ack does not hide a newer pending change", () => {
  const acks = new AckTracker();
  acks.sent(1, "temperature_K");
  acks.sent(2, "temperature_K");
  acks.ack({ ref: 1, ok: true, step: 10 });
  assert.equal(acks.status("temperature_K").state, PENDING);
  acks.ack({ ref: 2, ok: true, step: 20 });
  assert.equal(acks.status("temperature_K").step, 20);
});

test("a lost connection settles what was pending", () => {
  const acks = new AckTracker();
  acks.sent(1, "friction_per_ps");
  const out = acks.abandon();
  assert.equal(out.length, 1);
  assert.equal(out[0].status.state, FAILED);
  assert.match(out[0].status.text, /connection lost/);
});
