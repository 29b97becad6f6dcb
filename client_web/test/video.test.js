import { test } from "node:test";
import assert from "node:assert/strict";

import { CODECS, DeliveryMeter, decodableCodecs, describeStream } from "../src/video.js";

class FakeDecoder {
  static asked = [];
  static async isConfigSupported(config) {
    FakeDecoder.asked.push(config);
    if (config.codec.startsWith("av01")) throw new TypeError("unknown codec");
    return { supported: config.codec.startsWith("avc1.64") || config.codec.startsWith("vp09") };
  }
}

test("codecs the decoder accepts, in preference order, asked at the even coded size", async () => {
  FakeDecoder.asked = [];
  const got = await decodableCodecs(641, 480, FakeDecoder, new Map());
  assert.deepEqual(got, ["h264", "vp9"]);
  assert.equal(FakeDecoder.asked.length, CODECS.length);
  assert.ok(FakeDecoder.asked.every((c) => c.codedWidth === 642 && c.codedHeight === 480 && c.optimizeForLatency));
});

test("no WebCodecs: no video, and answers are cached per size", async () => {
  assert.deepEqual(await decodableCodecs(640, 480, undefined), []);
  const cache = new Map();
  FakeDecoder.asked = [];
  await decodableCodecs(640, 480, FakeDecoder, cache);
  await decodableCodecs(640, 480, FakeDecoder, cache);
  assert.equal(FakeDecoder.asked.length, CODECS.length);
});

test("the meter reports bit rate and frame rate over its window", () => {
  const m = new DeliveryMeter(1000);
  for (let i = 0; i < 60; i++) m.add(i * (1000 / 60), 20_000);
  const r = m.rate(1000);
  assert.ok(Math.abs(r.fps - 59) <= 1, r.fps);
  assert.ok(Math.abs(r.kbps - 9600) < 200, r.kbps);
  assert.deepEqual(m.rate(5000), { kbps: 0, fps: 0 });
});

test("the overlay line names codec, encoder, rates", () => {
  const line = describeStream({ format: "h264", encoder: "libx264", bitrate_kbps: 9300 }, { kbps: 4200, fps: 59.4 });
  assert.equal(line, "H.264 (libx264) · 4.2 Mbit/s of 9.3 Mbit/s · 59 fps");
  assert.equal(describeStream({ format: "jpeg" }, { kbps: 800, fps: 12 }), "JPEG · 800 kbit/s · 12 fps");
});
