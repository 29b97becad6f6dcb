// Picking atoms (details, labels, the measurement of two to four atoms) and pulling one with a
// spring towards the pointer, within the engine's pull limits.

import { unprojectToPlane } from "./camera.js";
import { $, setText } from "./dom.js";
import { position, sig } from "./format.js";
import { atomLabel, measurement } from "./measure.js";
import { clamp } from "./params.js";

export class DashboardPicking {
  async pick(x, y, how = {}) {
    if (!this.connection.ready) return;
    let reply;
    try {
      ({ reply } = await this.connection.request({ type: "pick", x, y }));
    } catch (err) {
      this.notices.notify({ level: "warning", code: "pick", message: err.message });
      return;
    }
    if (reply.type !== "picked") return;
    if (how.add) this.picks.extend(reply);
    else this.picks.pick(reply);
    this.showPicks();
    this.sendView(false); // track the picked atoms: markers and measurements follow them
  }

  /** The picked atoms: details of the last, labels and the measurement on the view. */
  showPicks() {
    const atoms = this.picks.atoms;
    const last = atoms.at(-1) ?? { atom: null };
    this.showPicked(last);
    const m = measurement(atoms);
    const text = m ? `${m.kind} ${sig(m.value, 4)} ${m.unit}` : "";
    const details = $("pick-details");
    details.dataset.measure = m ? `${m.kind}:${m.value}` : "";
    setText(
      $("pick-measure"),
      m
        ? `${text} (atoms ${atoms.map((a) => a.atom).join(", ")})`
        : "Shift-click more atoms: two give a distance, three an angle, four a dihedral",
    );
    this.viewport.setMarker(null);
    this.viewport.setAnnotations(
      atoms.map((a) => ({ position: a.position, label: atomLabel(a) })),
      m ? { kind: m.kind, text } : null,
    );
  }

  showPicked(p) {
    const details = $("pick-details");
    details.dataset.atom = p.atom ?? "";
    if (p.atom === null || p.atom === undefined) {
      setText($("pick-atom"), "background (no atom here)");
      for (const id of ["pick-element", "pick-name", "pick-residue", "pick-chain", "pick-layer", "pick-position"])
        setText($(id), "–");
      this.viewport.setMarker(null);
      return;
    }
    setText($("pick-atom"), `index ${p.atom}`);
    setText($("pick-element"), p.element || "–");
    setText($("pick-name"), p.name || "–");
    setText($("pick-residue"), `${p.residue_name || "?"} ${p.residue_id ?? ""}`.trim());
    setText($("pick-chain"), p.chain || "–");
    setText($("pick-layer"), p.layer || "–");
    setText($("pick-position"), position(p.position));
  }

  clearSelection() {
    this.picks.clear();
    this.showPicks();
    setText($("pick-atom"), "click an atom");
    this.sendView(false);
  }

  /** The engine's pull limits beside the pull fields; pulling off where it takes no forces. */
  showPullLimits() {
    const e = this.engine;
    const k = $("pull-k");
    const max = $("pull-max");
    if (e?.pull) {
      k.max = String(e.pull.max_spring_k);
      max.max = String(e.pull.max_force);
      if (Number(k.value) > e.pull.max_spring_k) k.value = String(e.pull.max_spring_k);
      if (Number(max.value) > e.pull.max_force) max.value = String(e.pull.max_force);
      setText($("range-pull-k"), `≤ ${sig(e.pull.max_spring_k, 4)}`);
      setText($("range-pull-max"), `≤ ${sig(e.pull.max_force, 4)}`);
    } else if (e) {
      setText($("range-pull-k"), "not available");
      setText($("range-pull-max"), "not available");
    }
    const why =
      e && !e.pull ? `${e.name} cannot be pulled: ${e.unavailable?.pull || "it takes no external forces"}` : "";
    $("pull-reason").hidden = !why;
    setText($("pull-reason"), why);
  }

  async pullStart(x, y) {
    if (this.role !== "steerer") return;
    if (this.engine && !this.engine.pull) {
      this.notices.notify({ level: "info", code: "pull", message: $("pull-reason").textContent });
      return;
    }
    const pull = { state: "picking", pointer: [x, y], atom: null, position: null };
    this.pull = pull;
    this.viewport.setPending([x, y]);
    let reply;
    try {
      ({ reply } = await this.connection.request({ type: "pick", x, y }));
    } catch (err) {
      this.viewport.setPending(null);
      this.notices.notify({ level: "warning", code: "pull", message: err.message });
      if (this.pull === pull) this.pull = null;
      return;
    }
    this.viewport.setPending(null);
    if (this.pull !== pull || reply.type !== "picked") return; // released meanwhile, or refused
    if (reply.atom === null || reply.atom === undefined || !reply.position) {
      this.notices.notify({ level: "info", code: "pull", message: "no atom under the pointer to pull" });
      this.pull = null;
      return;
    }
    this.showPicked(reply);
    Object.assign(pull, { state: "active", atom: reply.atom, position: reply.position });
    setText($("pull-atom"), `${reply.atom} (${reply.element} ${reply.name})`);
    $("pull-hint").hidden = false;
    this.viewport.setPullLine({ from: pull.position, to: pull.pointer });
    this.sendPull();
    this.sendView(false); // track the pulled atom
  }

  pullMove(x, y) {
    if (!this.pull) return;
    this.pull.pointer = [x, y];
    if (this.pull.state !== "active") return;
    this.viewport.setPullLine({ from: this.pull.position, to: this.pull.pointer });
    this.sendPullSoon();
  }

  sendPull() {
    const pull = this.pull;
    if (!pull || pull.state !== "active" || !this.camera) return;
    const { viewW, viewH } = this.viewport.size;
    const target = unprojectToPlane(
      this.camera,
      pull.pointer[0] + 0.5,
      pull.pointer[1] + 0.5,
      viewW,
      viewH,
      pull.position,
    );
    if (!target) return;
    this.connection.send({
      type: "pull",
      atom: pull.atom,
      target,
      spring_k: clamp(Number($("pull-k").value) || 1, 0.01, this.engine?.pull?.max_spring_k ?? 10000),
      max_force: clamp(Number($("pull-max").value) || 50, 0.01, this.engine?.pull?.max_force ?? 100000),
    });
  }

  pullEnd(silent = false) {
    const pull = this.pull;
    this.pull = null;
    this.sendPullSoon.cancel();
    $("pull-hint").hidden = true;
    this.viewport.setPullLine(null);
    this.viewport.setPending(null);
    if (pull?.state === "active" && !silent) {
      this.connection.send({ type: "pull", atom: pull.atom, release: true });
      this.sendView(false); // no longer tracked
    }
  }

  releaseAll() {
    for (const p of this.pulling) this.connection.send({ type: "pull", atom: p.atom, release: true });
  }
}
