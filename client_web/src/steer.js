// The dashboard's steering sent to the session: render-parameter patches (throttled, kept
// unconfirmed until the session answers), simulation parameters and run control (acknowledged
// by the engine), and the nudges the shortcuts make.

import { $ } from "./dom.js";
import { mergeRender } from "./params.js";
import { normalizePoints, presetPoints } from "./transfer.js";

export class DashboardSteering {
  steerRender(patch, final) {
    if (this.role !== "steerer") return;
    this.render = mergeRender(this.render, patch);
    Object.assign(this.pendingRender, patch);
    if (patch.transfer_function !== undefined || patch.tf_preset !== undefined) this.showTransferFunction();
    if (patch.color_by !== undefined) this.timePanel.update(this.render);
    this.writeHashSoon();
    if (final) {
      this.flushRenderSoon.cancel();
      this.flushRender();
    } else {
      this.flushRenderSoon();
    }
  }

  flushRender() {
    const params = this.pendingRender;
    this.pendingRender = {};
    if (!Object.keys(params).length) return;
    const seq = this.role === "steerer" ? this.connection.send({ type: "render_params", params }) : null;
    if (seq === null) {
      this.showRender(); // not sent: the page shows the session's values again
      return;
    }
    this.latency.sent(seq, "render_params", performance.now());
    this.unconfirmed.sent(seq, params);
  }

  /** The transfer function in effect: the session's points, or its preset's when it has none. */
  transferPoints() {
    const explicit = normalizePoints(this.render.transfer_function);
    return explicit.length ? explicit : presetPoints(this.render.tf_preset);
  }

  showTransferFunction() {
    this.tfEditor.setPoints(this.transferPoints());
    const preset = $("tf-preset");
    const edited = normalizePoints(this.render.transfer_function).length > 0;
    if (document.activeElement !== preset) preset.value = edited ? "custom" : this.render.tf_preset;
  }

  simParam(key, value) {
    const seq = this.connection.send({ type: "sim_params", [key]: value });
    if (seq === null) {
      this.simPanel.notSent(key, "not connected");
      return;
    }
    this.simPanel.showAck(key, this.acks.sent(seq, key, key));
  }

  control(action, extra, label) {
    const seq = this.connection.send({ type: "control", action, ...extra });
    if (seq === null) {
      this.simPanel.showAck("control", { state: "failed", text: "not connected" }, label);
      return;
    }
    this.simPanel.showAck("control", this.acks.sent(seq, "control", label), label);
  }
}
