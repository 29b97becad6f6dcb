// Keyboard shortcuts and their help overlay. Shortcuts never fire while typing in a field.

import { el } from "./dom.js";

/** Whether a key event comes from a place where keys mean text or control input. */
export function typingTarget(target) {
  if (!target || !target.tagName) return false;
  const tag = target.tagName.toLowerCase();
  if (tag === "textarea" || tag === "select" || target.isContentEditable) return true;
  if (tag === "input") return !["checkbox", "radio", "button", "submit", "color"].includes(target.type);
  return false;
}

export class Shortcuts {
  /** bindings: [{keys: ["r"], label: "R", description, run(event), when?(), hidden?}] */
  constructor({ dialog, table, bindings }) {
    Object.assign(this, { dialog, table, bindings });
    this.fill();
    document.addEventListener("keydown", (e) => this.handle(e));
  }

  fill() {
    const body = this.table.querySelector("tbody");
    body.replaceChildren(
      ...this.bindings
        .filter((b) => !b.hidden)
        .map((b) =>
          el("tr", {}, [
            el(
              "td",
              {},
              b.label.split(" / ").flatMap((k, i) => [...(i ? [" / "] : []), el("kbd", { text: k })]),
            ),
            el("td", { text: b.description }),
          ]),
        ),
    );
  }

  open() {
    if (!this.dialog.open) this.dialog.showModal();
  }

  close() {
    if (this.dialog.open) this.dialog.close();
  }

  toggle() {
    if (this.dialog.open) this.close();
    else this.open();
  }

  handle(e) {
    if (e.defaultPrevented || e.altKey || e.ctrlKey || e.metaKey) return;
    if (typingTarget(e.target)) return;
    if (this.dialog.open && e.key !== "?") return; // the dialog handles Escape itself
    const onControl = e.target?.closest?.("button, a, summary, input, select, label");
    for (const b of this.bindings) {
      if (!b.keys.includes(e.key)) continue;
      if (b.when && !b.when()) continue;
      // Space keeps its meaning on buttons, links, summaries and form controls
      if (b.keys.includes(" ") && onControl) continue;
      e.preventDefault();
      b.run(e);
      return;
    }
    // a space nobody took must not scroll the dashboard away (a viewer cannot pause)
    if (e.key === " " && !onControl) e.preventDefault();
  }
}
