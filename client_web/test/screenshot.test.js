import assert from "node:assert/strict";
import { test } from "node:test";

import { requestScreenshot, screenshotName } from "../src/screenshot.js";

test("a screenshot posts the session, size, params and camera with the bearer token", async () => {
  let seen;
  const fetchImpl = async (url, init) => {
    seen = { url, init };
    return new Response(new Uint8Array([0x89, 0x50, 0x4e, 0x47]), {
      status: 200,
      headers: { "content-type": "image/png" },
    });
  };
  const camera = { target: [0, 0, 0], distance: 40 };
  const blob = await requestScreenshot({
    token: "tok",
    session: "demo",
    width: 800.4,
    height: 600,
    params: { sigma_A: 2 },
    camera,
    fetchImpl,
  });
  assert.equal(seen.url, "/api/render");
  assert.equal(seen.init.method, "POST");
  assert.equal(seen.init.headers.Authorization, "Bearer tok");
  const form = seen.init.body;
  assert.equal(form.get("session"), "demo");
  assert.equal(form.get("width"), "800");
  assert.equal(form.get("format"), "png");
  assert.deepEqual(JSON.parse(form.get("params")), { sigma_A: 2 });
  assert.deepEqual(JSON.parse(form.get("camera")), camera);
  assert.equal(blob.size, 4);
});

test("a refused screenshot names the server's reason", async () => {
  const fetchImpl = async () =>
    new Response(JSON.stringify({ detail: "session 'x' has no frame yet" }), { status: 409 });
  await assert.rejects(
    requestScreenshot({ token: null, session: "x", width: 10, height: 10, fetchImpl }),
    /HTTP 409: session 'x' has no frame yet/,
  );
});

test("file names carry session, step and time", () => {
  assert.equal(
    screenshotName("demo", 1200, new Date("2025-01-02T03:04:05.678Z")),
    "scalesteer-demo-step1200-2025-01-02T030405Z.png",
  );
});
