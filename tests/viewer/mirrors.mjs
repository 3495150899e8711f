// Runs the viewer's pure functions on inputs from stdin (JSON) and prints their results, for
// tests/viewer/test_mirrors_js.py to compare with the Python functions they mirror.
import { readFileSync } from "node:fs";
import { chooseEvictions } from "../../server/viewer/budget.js";
import { lookRotation, shadeInto, unitIcosphere } from "../../server/viewer/shading.js";
import { isToken } from "../../server/viewer/token.js";
import { parseWalkthrough, poseAt } from "../../server/viewer/walk.js";

const input = JSON.parse(readFileSync(0, "utf8"));
const out = {};
out.shade = input.shade.tris.map((c, i) => {
  const o = new Uint8Array(3);
  shadeInto(c, ...input.shade.colors[i], o, 0);
  return Array.from(o);
});
out.look = input.look.map((f) => { const r = lookRotation(f); return [r.right, r.up, r.back]; });
out.icosphere = Array.from(unitIcosphere(2));
const e = input.evict;
const cents = new Map(e.ids.map((id, i) => [id, e.centroids[i]]));
out.evict = chooseEvictions(e.ids, (id, o) => { o.splice(0, 3, ...cents.get(id)); return o; },
  new Set(e.protect), e.eye, e.budget);
const walk = parseWalkthrough(input.walk.data);
out.poses = input.walk.times.map((t) => { const p = poseAt(walk, t); return [p.position, p.forward]; });
out.isToken = input.tokens.map(isToken);
process.stdout.write(JSON.stringify(out));
