// Picked atoms for labels and measurements: one atom is a selection, two a distance, three an
// angle, four a dihedral. Positions are updated from the server's `tracked` messages, so the
// markers and the values follow the atoms as the simulation moves them.

export const MAX_MEASURED = 4;

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.sqrt(dot(a, a));

/** Distance between two points (angstrom). */
export function distance(a, b) {
  return norm(sub(a, b));
}

/** Angle a-b-c at b, in degrees. */
export function angle(a, b, c) {
  const u = sub(a, b);
  const v = sub(c, b);
  const cos = dot(u, v) / (norm(u) * norm(v));
  return (Math.acos(Math.min(1, Math.max(-1, cos))) * 180) / Math.PI;
}

/** Dihedral a-b-c-d in degrees, in (-180, 180] (IUPAC sign: clockwise looking from b to c). */
export function dihedral(a, b, c, d) {
  const b1 = sub(b, a);
  const b2 = sub(c, b);
  const b3 = sub(d, c);
  const y = norm(b2) * dot(b1, cross(b2, b3));
  const x = dot(cross(b1, b2), cross(b2, b3));
  return (Math.atan2(y, x) * 180) / Math.PI;
}

/** A short label for a picked atom: element, name and residue. */
export function atomLabel(p) {
  if (!p) return "";
  const residue = p.residue_name ? `${p.residue_name}${p.residue_id ?? ""}` : "";
  return [p.name || p.element || `#${p.atom}`, residue].filter(Boolean).join(" ");
}

/** The measurement the picked atoms make, with the atoms it joins, or null. */
export function measurement(atoms) {
  const pts = atoms.map((a) => a.position);
  if (pts.length < 2 || pts.some((p) => !p)) return null;
  if (pts.length === 2) return { kind: "distance", value: distance(pts[0], pts[1]), unit: "Å" };
  if (pts.length === 3) return { kind: "angle", value: angle(pts[0], pts[1], pts[2]), unit: "°" };
  return { kind: "dihedral", value: dihedral(pts[0], pts[1], pts[2], pts[3]), unit: "°" };
}

/** The atoms a view asks the server to track: the picked ones and an atom being pulled (its
 * arrow starts where the atom is now, not where it was picked). */
export function trackedAtoms(picked, pulled = null) {
  return pulled === null || pulled === undefined || picked.includes(pulled) ? [...picked] : [...picked, pulled];
}

/** Where a `tracked` message puts `atom` (null when it does not name it). */
export function trackedPosition(message, atom) {
  const i = (message.atoms ?? []).indexOf(atom);
  return i < 0 ? null : (message.positions?.[i] ?? null);
}

/** The picked atoms: `pick` replaces them, `extend` adds one (the oldest goes past four). */
export class Picks {
  constructor() {
    this.atoms = [];
  }

  pick(p) {
    this.atoms = p && p.atom !== null && p.atom !== undefined ? [p] : [];
  }

  extend(p) {
    if (!p || p.atom === null || p.atom === undefined) return;
    this.atoms = this.atoms.filter((a) => a.atom !== p.atom);
    this.atoms.push(p);
    if (this.atoms.length > MAX_MEASURED) this.atoms.shift();
  }

  clear() {
    this.atoms = [];
  }

  get indices() {
    return this.atoms.map((a) => a.atom);
  }

  /** Take the positions of a `tracked` message; true when any of ours moved. */
  track(message) {
    let moved = false;
    (message.atoms ?? []).forEach((atom, i) => {
      const mine = this.atoms.find((a) => a.atom === atom);
      const pos = message.positions?.[i];
      if (mine && pos) {
        moved = moved || !mine.position || distance(mine.position, pos) > 0;
        mine.position = pos;
      }
    });
    return moved;
  }
}
