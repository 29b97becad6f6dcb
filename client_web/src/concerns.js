// The dashboard's behaviour by concern, each a class whose methods `compose` makes the
// dashboard's own: they read and change its one state (`this`) as the methods of one class do.

import { DashboardActions } from "./actions.js";
import { DashboardMessages } from "./messages.js";
import { DashboardPicking } from "./picking.js";
import { DashboardSessionPanel } from "./sessionpanel.js";
import { DashboardSteering } from "./steer.js";
import { DashboardView } from "./view.js";

export const CONCERNS = [
  DashboardMessages,
  DashboardSteering,
  DashboardView,
  DashboardPicking,
  DashboardSessionPanel,
  DashboardActions,
];

/** Put every concern's methods on `target`'s prototype; a name defined twice (by two concerns,
 * or by a concern and `target` itself) is refused rather than one silently replacing the other. */
export function compose(target, concerns = CONCERNS) {
  for (const concern of concerns) {
    for (const name of Object.getOwnPropertyNames(concern.prototype)) {
      if (name === "constructor") continue;
      if (Object.hasOwn(target.prototype, name)) throw new Error(`${concern.name}.${name} is defined twice`);
      Object.defineProperty(target.prototype, name, Object.getOwnPropertyDescriptor(concern.prototype, name));
    }
  }
  return target;
}
