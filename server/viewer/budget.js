// The viewer's own triangle budget, enforced as a last resort (client/budget.py).
//
// The server keeps a client under the budget it declared in its hello with `drop` messages
// sent before new geometry. Should the store still hold more, the viewer evicts by itself before
// it draws: triangles outside the current cell's stream first, farthest from the eye first, and
// only then the farthest of the current cell's own.

/** The ids to evict so at most `budget` of `ids` remain: unprotected ones first (not in the
 * Set `protect`), each group farthest from `eye` first. `centroidOf(id, out)` fills a centroid. */
export function chooseEvictions(ids, centroidOf, protect, eye, budget) {
  const need = ids.length - budget;
  if (need <= 0) return [];
  const c = [0, 0, 0];
  const rows = Array.from(ids, (id) => {
    centroidOf(id, c);
    const d = Math.hypot(c[0] - eye[0], c[1] - eye[1], c[2] - eye[2]);
    return { id, d, p: protect.has(id) ? 1 : 0 };
  });
  rows.sort((a, b) => a.p - b.p || b.d - a.d);
  return rows.slice(0, need).map((r) => r.id);
}

/** Evict from `store` until it holds at most its budget; how many were evicted. `protect`: the
 * current cell's ids (a Set); `eye`: metres from the store's origin. */
export function enforceBudget(store, protect, eye) {
  if (!store.overBudget) return 0;
  const evict = chooseEvictions(store.heldIds(), (id, out) => store.centroid(id, out), protect,
    eye, store.budget);
  return store.drop(evict);
}
