import assert from "node:assert/strict";
import { test } from "node:test";
import { Picks, angle, atomLabel, dihedral, distance, measurement } from "../src/measure.js";

const close = (a, b, eps = 1e-9) => assert.ok(Math.abs(a - b) < eps, `${a} != ${b}`);

test("distance, angle and dihedral of known geometry", () => {
  close(distance([0, 0, 0], [3, 4, 0]), 5);
  close(angle([1, 0, 0], [0, 0, 0], [0, 1, 0]), 90);
  close(angle([1, 0, 0], [0, 0, 0], [-1, 0, 0]), 180);
  close(dihedral([1, 0, 0], [0, 0, 0], [0, 1, 0], [0, 1, 1]), -90);
  close(dihedral([1, 0, 0], [0, 0, 0], [0, 1, 0], [1, 1, 0]), 0);
  close(Math.abs(dihedral([1, 0, 0], [0, 0, 0], [0, 1, 0], [-1, 1, 0])), 180);
});

test("picks grow into measurements and follow tracked positions", () => {
  const picks = new Picks();
  picks.pick({ atom: 3, name: "CA", residue_name: "LEU", residue_id: 7, position: [0, 0, 0] });
  assert.equal(measurement(picks.atoms), null);
  assert.equal(atomLabel(picks.atoms[0]), "CA LEU7");
  picks.extend({ atom: 9, name: "N", position: [3, 4, 0] });
  assert.deepEqual(measurement(picks.atoms), { kind: "distance", value: 5, unit: "Å" });
  assert.ok(picks.track({ atoms: [9, 3], positions: [[6, 8, 0], [0, 0, 0]] }));
  close(measurement(picks.atoms).value, 10);
  picks.extend({ atom: 11, position: [6, 0, 0] });
  assert.equal(measurement(picks.atoms).kind, "angle");
  picks.extend({ atom: 12, position: [6, 0, 5] });
  picks.extend({ atom: 13, position: [0, 0, 5] });
  assert.deepEqual(picks.indices, [9, 11, 12, 13], "four at most: the oldest goes");
  picks.extend({ atom: 12, position: [6, 0, 5] });
  assert.deepEqual(picks.indices, [9, 11, 13, 12], "picking again moves it to the end");
  picks.clear();
  assert.deepEqual(picks.indices, []);
});

test("a pulled atom is tracked with the picked ones, and its tracked position is found", async () => {
  const { trackedAtoms, trackedPosition } = await import("../src/measure.js");
  assert.deepEqual(trackedAtoms([3, 7]), [3, 7]);
  assert.deepEqual(trackedAtoms([3, 7], 12), [3, 7, 12]);
  assert.deepEqual(trackedAtoms([3, 7], 7), [3, 7]);
  assert.deepEqual(trackedAtoms([], 0), [0]); // atom 0 is an atom
  const message = { type: "tracked", atoms: [3, 12], positions: [[0, 0, 0], [1, 2, 3]] };
  assert.deepEqual(trackedPosition(message, 12), [1, 2, 3]);
  assert.equal(trackedPosition(message, 5), null);
});
