// Readable notices: server errors (code + message), connection changes and local failures.
// Every notice is shown; repeats of the same notice are counted rather than stacked.

import { el } from "./dom.js";

const LIFETIME_MS = { info: 6000, warning: 12000, error: 30000 };
const MAX_SHOWN = 6;

export class Notices {
  constructor(root) {
    this.root = root;
    this.log = []; // every notice, for the session panel and automation
    this.shown = new Map(); // key -> {node, count, timer}
  }

  /** Show {level, code, message, path}; returns the notice's element. */
  notify({ level = "warning", code = "", message = "", path = "" }) {
    const entry = { level, code, message, path, time: Date.now() };
    this.log.push(entry);
    if (this.log.length > 500) this.log.shift();
    const key = `${level}|${code}|${message}|${path}`;
    const existing = this.shown.get(key);
    if (existing) {
      existing.count += 1;
      existing.counter.textContent = `×${existing.count}`;
      this.arm(key, level);
      return existing.node;
    }
    const text = path && !message.includes(path) ? `${message} (${path})` : message;
    const counter = el("span", { className: "count" });
    const close = el("button", { type: "button", "aria-label": "Dismiss notice", text: "×" });
    const node = el(
      "div",
      { className: "notice", role: level === "error" ? "alert" : "status", "data-level": level, "data-code": code },
      [
        ...(code ? [el("span", { className: "code", text: code })] : []),
        el("span", { className: "text", text }),
        counter,
        close,
      ],
    );
    close.addEventListener("click", () => this.dismiss(key));
    this.root.append(node);
    this.shown.set(key, { node, count: 1, counter, timer: null });
    this.arm(key, level);
    while (this.shown.size > MAX_SHOWN) this.dismiss(this.shown.keys().next().value);
    return node;
  }

  arm(key, level) {
    const item = this.shown.get(key);
    if (!item) return;
    clearTimeout(item.timer);
    item.timer = setTimeout(() => this.dismiss(key), LIFETIME_MS[level] ?? LIFETIME_MS.warning);
  }

  dismiss(key) {
    const item = this.shown.get(key);
    if (!item) return;
    clearTimeout(item.timer);
    item.node.remove();
    this.shown.delete(key);
  }

  /** A protocol `error` message from the server. */
  serverError(message) {
    return this.notify({ level: "error", code: message.code, message: message.message, path: message.path ?? "" });
  }
}
