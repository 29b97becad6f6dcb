import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";

import { CONCERNS, compose } from "../src/concerns.js";

const SOURCES = ["app.js", "messages.js", "steer.js", "view.js", "picking.js", "sessionpanel.js", "actions.js"].map(
  (name) => readFileSync(new URL(`../src/${name}`, import.meta.url), "utf8"),
);

test("the concerns compose into one class, each method once", () => {
  class Target {}
  compose(Target);
  const names = CONCERNS.flatMap((c) => Object.getOwnPropertyNames(c.prototype).filter((n) => n !== "constructor"));
  assert.equal(new Set(names).size, names.length);
  for (const name of names) assert.equal(typeof Target.prototype[name], "function", name);
});

test("a method two concerns define is refused, naming it", () => {
  class A {
    show() {}
  }
  class B {
    show() {}
  }
  assert.throws(() => compose(class {}, [A, B]), /B\.show is defined twice/);
});

test("every method the dashboard calls on itself is defined by a concern or set by the constructor", () => {
  class Target {}
  compose(Target);
  const fields = new Set([...SOURCES[0].matchAll(/this\.(\w+) = /g)].map((m) => m[1]));
  const called = new Set(SOURCES.flatMap((s) => [...s.matchAll(/this\.(\w+)\(/g)].map((m) => m[1])));
  const missing = [...called].filter((name) => !(name in Target.prototype) && !fields.has(name));
  assert.deepEqual(missing, []);
});
