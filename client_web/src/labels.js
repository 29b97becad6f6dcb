// Where the overlay's labels go: beside their anchor (an atom, a measurement's middle), never
// over one another nor off the view. Plain geometry, so it is tested without a canvas.

const GAP = 10;
const RINGS = 6;

function overlaps(a, b) {
  return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
}

/** Candidate top-left corners for a w x h label at anchor [x, y], nearest first: the four
 * corners around it, then the same pushed further out ring by ring. */
function candidates([x, y], w, h, gap) {
  const out = [];
  for (let ring = 0; ring < RINGS; ring += 1) {
    const d = gap + ring * (h + 2);
    out.push([x + d, y - d - h], [x - d - w, y - d - h], [x + d, y + d], [x - d - w, y + d]);
    out.push([x - w / 2, y - d - h], [x - w / 2, y + d], [x + d, y - h / 2], [x - d - w, y - h / 2]);
  }
  return out;
}

/**
 * Place labels in order (earlier ones keep the better spots): `items` are {anchor: [x, y], w,
 * h}; `bounds` {w, h} is the view; `obstacles` are rects no label may cover (the atoms'
 * markers). Returns {x, y, w, h, moved} per item: its top-left corner, and whether it had to
 * leave the first spot (then a leader line helps). A label with no free spot takes the first
 * that stays in view.
 */
export function placeLabels(items, bounds, { gap = GAP, obstacles = [] } = {}) {
  const placed = [];
  const taken = [...obstacles];
  for (const { anchor, w, h } of items) {
    const spots = candidates(anchor, w, h, gap).map(([x, y]) => ({
      x: Math.min(Math.max(0, x), Math.max(0, bounds.w - w)),
      y: Math.min(Math.max(0, y), Math.max(0, bounds.h - h)),
      w,
      h,
    }));
    const free = spots.find((r) => !taken.some((p) => overlaps(r, p)));
    const rect = free ?? spots[0];
    placed.push({ ...rect, moved: rect !== spots[0] });
    taken.push(rect);
  }
  return placed;
}

export { overlaps };
