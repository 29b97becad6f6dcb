import { test } from "node:test";
import assert from "node:assert/strict";

import { cellEdges } from "../src/cell.js";

test("a cell has twelve edges, each one of its vectors long, between its eight corners", () => {
  const cell = { origin: [1, 2, 3], vectors: [[10, 0, 0], [2, 8, 0], [1, 1, 7]] };
  const edges = cellEdges(cell);
  assert.equal(edges.length, 12);
  const corners = new Set(edges.flat().map((p) => p.join(",")));
  assert.equal(corners.size, 8);
  assert.ok(corners.has("1,2,3") && corners.has("14,11,10"));
  const lengths = edges.map(([a, b]) => Math.hypot(b[0] - a[0], b[1] - a[1], b[2] - a[2]));
  const expected = cell.vectors.map((v) => Math.hypot(...v));
  for (const len of expected) assert.equal(lengths.filter((l) => Math.abs(l - len) < 1e-9).length, 4);
});

test("no cell, no edges", () => {
  assert.deepEqual(cellEdges(null), []);
  assert.deepEqual(cellEdges({ origin: [0, 0, 0], vectors: [] }), []);
});
