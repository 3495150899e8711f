// The overlay: what the viewer streams and draws (scene, core, cell, triangles held, bytes,
// PVS latency, stalls), the status line (connecting, connected, a problem and the reconnect),
// and the choice of scene and core, which opens the same page for the new pair.

const $ = (id) => document.getElementById(id);

export class Overlay {
  constructor() {
    this.status = $("status");
    this.stats = $("stats");
    this.sceneSelect = $("scene");
    this.coreSelect = $("core");
    this.lastError = $("last-error");
    /** Every status line shown, oldest first (the tests read them). */
    this.history = [];
    for (const sel of [this.sceneSelect, this.coreSelect]) {
      sel.addEventListener("change", () => this.open());
    }
  }

  /** {text, level: "info" | "ok" | "error"}. */
  setStatus({ text, level }) {
    this.status.textContent = text;
    this.status.className = level;
    this.history.push({ text, level, at: performance.now() });
    if (this.history.length > 200) this.history.shift();
  }

  showError(text) { this.lastError.textContent = text; }

  setScenes(names, current) {
    this.fill(this.sceneSelect, names, current);
  }

  /** The cores the server offers for the scene (welcome.features.cores), "auto" first. */
  setCores(cores, current) {
    this.fill(this.coreSelect, ["auto", ...cores.filter((c) => c !== "auto")], current);
  }

  fill(select, values, current) {
    select.replaceChildren(...values.map((v) => new Option(v, v, false, v === current)));
    if (current && !values.includes(current)) select.prepend(new Option(current, current, true, true));
  }

  open() {
    const url = new URL(window.location.href);
    url.searchParams.set("scene", this.sceneSelect.value);
    url.searchParams.set("core", this.coreSelect.value);
    url.searchParams.delete("walk");
    window.location.assign(url.toString());
  }

  /** Rows of [label, value]. */
  setStats(rows) {
    this.stats.replaceChildren(...rows.map(([k, v]) => {
      const tr = document.createElement("tr");
      const a = document.createElement("th");
      const b = document.createElement("td");
      a.textContent = k;
      b.textContent = v;
      tr.append(a, b);
      return tr;
    }));
  }
}

/** Bytes as kB / MB. */
export function formatBytes(n) {
  if (n < 1e3) return `${n} B`;
  if (n < 1e6) return `${(n / 1e3).toFixed(1)} kB`;
  return `${(n / 1e6).toFixed(2)} MB`;
}
