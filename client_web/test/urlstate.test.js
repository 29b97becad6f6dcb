import assert from "node:assert/strict";
import { test } from "node:test";

import { orbit, DEFAULT_CAMERA } from "../src/camera.js";
import { RENDER_DEFAULTS, mergeRender } from "../src/params.js";
import { decodeHash, encodeHash, readQuery } from "../src/urlstate.js";

const close = (a, b, eps) => assert.ok(Math.abs(a - b) <= eps, `${a} != ${b}`);

test("default render params encode to an almost empty hash and back", () => {
  const hash = encodeHash({ render: mergeRender(RENDER_DEFAULTS, {}) });
  assert.equal(hash, "v=1");
  assert.deepEqual(decodeHash(`#${hash}`).render, mergeRender(RENDER_DEFAULTS, {}));
});

test("render params and camera survive the round trip", () => {
  const render = mergeRender(RENDER_DEFAULTS, {
    mode: "volume",
    sigma_A: 2.75,
    iso_level: 0.35,
    color_by: "chain",
    background: [1, 1, 1],
    uniform_color: [0.2, 0.4, 0.6],
    tf_preset: "shells",
    transfer_function: [
      { x: 0, color: [0, 0, 1], alpha: 0 },
      { x: 1.25, color: [1, 0.5, 0], alpha: 0.625 },
    ],
    lighting: { ambient: 0.5, key_light: false, ambient_occlusion: true },
    quality: 0.5,
    jpeg_quality: 70,
  });
  const camera = {
    ...orbit({ ...DEFAULT_CAMERA, target: [1.5, -2.25, 30] }, 80, 30, 480),
    projection: "orthographic",
    ortho_height: 33,
  };
  const hash = encodeHash({ render, camera });
  const back = decodeHash(`#${hash}`);
  assert.deepEqual(back.invalid, []);
  assert.equal(back.render.mode, "volume");
  assert.equal(back.render.sigma_A, 2.75);
  assert.equal(back.render.lighting.key_light, false);
  assert.equal(back.render.lighting.ambient_occlusion, true);
  assert.equal(back.render.lighting.diffuse, RENDER_DEFAULTS.lighting.diffuse);
  assert.deepEqual(back.render.transfer_function[1].color, [1, 0.502, 0]);
  assert.deepEqual(back.render.uniform_color, [0.2, 0.4, 0.6]);
  assert.equal(back.camera.projection, "orthographic");
  back.camera.orientation.forEach((v, i) => close(v, camera.orientation[i], 1e-4));
  back.camera.target.forEach((v, i) => close(v, camera.target[i], 1e-4));
  close(back.camera.ortho_height, 33, 1e-9);
  // encoding what was decoded gives the same hash: the form is stable
  assert.equal(encodeHash({ render: back.render, camera: back.camera }), hash);
});

test("a link carries the centre and fit selections with the periodic options", () => {
  const render = mergeRender(RENDER_DEFAULTS, {
    periodic: "wrap",
    center: "selection",
    center_selection: "name CA and resid 10-20",
    fit: "rotation",
    fit_selection: "name CA & resname 'ALA'",
  });
  const hash = encodeHash({ render });
  const back = decodeHash(`#${hash}`);
  assert.deepEqual(back.invalid, []);
  assert.equal(back.render.center_selection, "name CA and resid 10-20");
  assert.equal(back.render.fit_selection, "name CA & resname 'ALA'");
  assert.equal(encodeHash({ render: back.render }), hash);
  assert.deepEqual(decodeHash(`#v=1&csel=${"x".repeat(2001)}&fsel=%20`).invalid, ["csel", "fsel"]);
});

test("a hash without state, or with junk, is handled", () => {
  assert.deepEqual(decodeHash(""), { render: null, camera: null, invalid: [], hasLayers: false });
  const junk = decodeHash("#v=1&sigma=abc&mode=cubes&bg=zz&cam=1,2&tf=1:xyz:1");
  assert.deepEqual(junk.invalid.sort(), ["bg", "cam", "mode", "sigma", "tf"]);
  assert.equal(junk.render.sigma_A, RENDER_DEFAULTS.sigma_A);
  assert.equal(decodeHash("#v=1&sigma=1e9").render.sigma_A, 50, "clamped to the protocol range");
});

test("the query names token, role and session", () => {
  assert.deepEqual(readQuery("?token=abc"), { token: "abc", role: "steerer", session: "default", transport: "auto" });
  assert.deepEqual(readQuery("?role=viewer&token=v&session=run-2"), {
    token: "v",
    role: "viewer",
    session: "run-2",
    transport: "auto",
  });
  assert.equal(readQuery("?session=../x").session, "default");
  assert.equal(readQuery("?transport=jpeg").transport, "jpeg");
  assert.equal(readQuery("?transport=h264").transport, "auto"); // only JPEG may be asked for
});
