// Render-parameter edits this page sent that the session has not answered yet. The session
// answers every `render_params` message with a `state` naming it (`ref` = its seq, `by` = this
// page's client_id), carrying the parameters it made or none when they were already in effect,
// or with an `error` naming it. States from before an answer (another steerer's change, or this
// page's own earlier edit coming back) do not include the edits still on their way, so the page
// shows those over the session's parameters: a scale typed right after adding a layer is not
// taken back by the echo of the layer.

import { mergeRender } from "./params.js";

export class Unconfirmed {
  constructor() {
    this.items = [];
  }

  /** The patch sent as message `seq` (null: not sent, nothing will answer it). */
  sent(seq, patch) {
    if (seq !== null && seq !== undefined) this.items.push({ seq, patch });
  }

  /** A state answered message `ref` of this page: it and every edit before it are in. */
  answered(ref) {
    this.items = this.items.filter((item) => item.seq > ref);
  }

  /** An error for message `ref`: whether it was one of these edits (it will not come in). */
  refused(ref) {
    const before = this.items.length;
    this.items = this.items.filter((item) => item.seq !== ref);
    return this.items.length !== before;
  }

  /** A new connection: nothing sent on the old one will be answered. */
  clear() {
    this.items = [];
  }

  get size() {
    return this.items.length;
  }

  /** The session's parameters with the edits on their way applied over them, in order. */
  over(session) {
    return this.items.reduce((render, item) => mergeRender(render, item.patch), session);
  }
}
