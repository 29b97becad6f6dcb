import assert from "node:assert/strict";
import { test } from "node:test";
import { DEFAULT_CAMERA } from "../src/camera.js";
import { RENDER_DEFAULTS, renderProblems } from "../src/params.js";
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

test("a damaged view is refused whole, naming every problem", () => {
  const bad = {
    scalesteer_view: 1,
    camera: { target: [0, 0, 0], distance: -5, orientation: [1, 0, 0, 0] },
    render_params: { sigma_A: "x", mode: "hologram", lighting: { ambient: 3, glow: 1 }, colour: "red" },
  };
  assert.throws(
    () => readViewFile(JSON.stringify(bad)),
    (err) => {
      for (const part of [
        "camera.distance -5 is outside",
        'render_params.sigma_A "x" is not a number',
        'render_params.mode "hologram" is not one of iso, volume',
        "render_params.lighting.ambient 3 is outside [0, 1]",
        "render_params.lighting.glow is not a lighting parameter",
        "render_params.colour is not a render parameter",
      ]) {
        assert.ok(err.message.includes(part), `${part} missing from: ${err.message}`);
      }
      return /not applied/.test(err.message);
    },
  );
  assert.throws(
    () =>
      readViewFile(JSON.stringify({ scalesteer_view: 1, camera: { target: [0, "a", 0], orientation: [0, 0, 0, 0] } })),
    /camera\.target must be 3 numbers; camera\.orientation is zero/,
  );
});

test("a view saved with every render parameter at its default reads back", () => {
  const render = JSON.parse(JSON.stringify(RENDER_DEFAULTS));
  const text = JSON.stringify(viewFile({ session: "s", camera: DEFAULT_CAMERA, render }));
  assert.deepEqual(readViewFile(text).render, render);
  assert.deepEqual(renderProblems({ sigma_A: 0.01, time_window: 8, show_cell: "yes" }), [
    "sigma_A 0.01 is outside [0.05, 50]",
    'show_cell "yes" is not true or false',
  ]);
});
