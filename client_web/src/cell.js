// The periodic box as an outline: the twelve edges of the cell the server reports in
// `state.cell` (a corner and three edge vectors, in the displayed frame).

/** The 12 edges [[a, b], ...] of a cell {origin, vectors}; [] without one. */
export function cellEdges(cell) {
  if (!cell || !Array.isArray(cell.vectors) || cell.vectors.length !== 3) return [];
  const [a, b, c] = cell.vectors;
  const o = cell.origin ?? [0, 0, 0];
  const corner = (i, j, k) => [0, 1, 2].map((d) => o[d] + i * a[d] + j * b[d] + k * c[d]);
  const edges = [];
  for (const i of [0, 1]) {
    for (const j of [0, 1]) {
      for (const k of [0, 1]) {
        const from = corner(i, j, k);
        if (i === 0) edges.push([from, corner(1, j, k)]);
        if (j === 0) edges.push([from, corner(i, 1, k)]);
        if (k === 0) edges.push([from, corner(i, j, 1)]);
      }
    }
  }
  return edges;
}
