// Steering acknowledgements: every sim_params or control message shows "pending" until the
// server answers its seq with params_ack (the step it took effect at, or why it failed) or error.

export const PENDING = "pending";
export const APPLIED = "applied";
export const FAILED = "failed";

function describeAck(ack) {
  if (!ack.ok) return `failed: ${ack.detail || "the simulation refused it"}`;
  const parts = [];
  if (Number.isInteger(ack.step)) parts.push(`applied at step ${ack.step.toLocaleString("en-US")}`);
  else parts.push("applied");
  if (Number.isFinite(ack.time_ps)) parts.push(`(${formatPs(ack.time_ps)})`);
  if (ack.detail) parts.push(`: ${ack.detail}`);
  return parts.join(" ");
}

function formatPs(ps) {
  return Math.abs(ps) >= 1000 ? `${(ps / 1000).toFixed(3)} ns` : `${ps.toFixed(2)} ps`;
}

/** Tracks one status per control key (e.g. "temperature_K", "control"). */
export class AckTracker {
  constructor() {
    this.bySeq = new Map(); // seq -> {key, label}
    this.byKey = new Map(); // key -> {state, text, seq, label}
  }

  /** A message `seq` was sent for control `key`; returns the status to show. */
  sent(seq, key, label = "") {
    this.bySeq.set(seq, { key, label });
    const status = { state: PENDING, text: "pending…", seq, label };
    this.byKey.set(key, status);
    return status;
  }

  /** A params_ack arrived; returns {key, status} when it answers one of ours, else null. */
  ack(message) {
    return this.settle(message.ref, message.ok === false ? FAILED : APPLIED, describeAck(message), message);
  }

  /** An error arrived; returns {key, status} when it refers to one of ours, else null. */
  error(message) {
    return this.settle(message.ref, FAILED, `failed: ${message.code}: ${message.message}`, message);
  }

  settle(ref, state, text, message) {
    if (ref === undefined || ref === null) return null;
    const sent = this.bySeq.get(ref);
    if (!sent) return null;
    this.bySeq.delete(ref);
    const current = this.byKey.get(sent.key);
    const status = { state, text, seq: ref, label: sent.label, step: message.step ?? null };
    // a newer message for the same control keeps its own pending status
    if (!current || current.seq <= ref) this.byKey.set(sent.key, status);
    return { key: sent.key, status: this.byKey.get(sent.key) };
  }

  /** The connection dropped: whatever is still pending will never be answered. */
  abandon(reason = "connection lost before the acknowledgement") {
    const out = [];
    for (const [seq, { key, label }] of this.bySeq) {
      const status = { state: FAILED, text: `unknown: ${reason}`, seq, label };
      this.byKey.set(key, status);
      out.push({ key, status });
    }
    this.bySeq.clear();
    return out;
  }

  status(key) {
    return this.byKey.get(key) ?? null;
  }

  get pendingCount() {
    return this.bySeq.size;
  }
}
