import assert from "node:assert/strict";
import { test } from "node:test";
import { readViewFile, viewFile, viewFileName } from "../src/viewfile.js";

test("a saved view reads back the same", () => {
  const camera = { target: [1, 2, 3], distance: 40, orientation: [1, 0, 0, 0], fov_deg: 35 };
  const render = { sigma_A: 2.5, mode: "volume" };
  const text = JSON.stringify(viewFile({ session: "s", camera, render, atoms: [3, 9] }));
  assert.deepEqual(readViewFile(text), { session: "s", camera, render, atoms: [3, 9] });
  assert.match(viewFileName("s", new Date("2026-01-02T03:04:05.678Z")), /^scalesteer-view-s-2026-01-02T030405Z\.json$/);
});

test("files that are not views say why", () => {
  assert.throws(() => readViewFile("{oops"), /not a view file/);
  assert.throws(() => readViewFile('{"camera": {}}'), /no scalesteer_view/);
  assert.throws(() => readViewFile('{"scalesteer_view": 9, "camera": {}}'), /newer than this dashboard/);
  assert.throws(() => readViewFile('{"scalesteer_view": 1}'), /neither a camera nor render/);
  const odd = readViewFile('{"scalesteer_view": 1, "camera": {"distance": 5}, "atoms": [1, -2, "x", 4.5, 7]}');
  assert.deepEqual(odd.atoms, [1, 7]);
});
