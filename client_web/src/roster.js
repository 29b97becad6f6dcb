// Who is in the session: the whole list arrives when we join, then as joined/left deltas.

/**
 * The roster after one `state` message: `clients` replaces it, then `left` removes and
 * `joined` adds (a client id never appears twice).
 * @param {Array<{client_id: string}>} current
 * @param {{clients?: Array, joined?: Array, left?: string[]}} m
 */
export function applyRoster(current, m) {
  let next = m.clients ? [...m.clients] : [...current];
  if (m.left?.length) {
    const gone = new Set(m.left);
    next = next.filter((c) => !gone.has(c.client_id));
  }
  for (const c of m.joined ?? []) {
    const at = next.findIndex((x) => x.client_id === c.client_id);
    if (at >= 0) next[at] = c;
    else if (c.role === "simulation") next.unshift(c);
    else next.push(c);
  }
  return next;
}
