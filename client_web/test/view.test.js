import assert from "node:assert/strict";
import { test } from "node:test";
import { imageSizeText } from "../src/view.js";

test("the HUD names the size an image was drawn at when it is smaller than the view", () => {
  assert.equal(imageSizeText({ width: 1040, height: 627 }, [1040, 627]), "1040×627");
  assert.equal(imageSizeText({ width: 520, height: 313 }, [1040, 627]), "520×313 of 1040×627");
  assert.equal(imageSizeText({ width: 320, height: 240 }, undefined), "320×240");
});
