// The painting workbench around an Editor: tool buttons, brush size / mask opacity / flood
// tolerance, undo / redo / fit, outline mode, zoom and minimap, the class palette with
// per-class hide, the preferences kept between frames, and the frame's server-side smart
// tools. One module for every page that paints a mask (the annotator's page and the
// reviewer's editor), so both offer the same tools with the same keys.

import { api } from "../core/api.js";
import { el } from "../core/ui.js";
import { decodeIdPng } from "../core/png.js";

/** The painting tools' keys (every page that paints lists them in its help, then its own). */
export const TOOL_KEYS = [
  ["B / E / P / F / R / G / I / H", "brush / eraser / polygon / flood fill / region fill (superpixels) / GrabCut box / intelligent scissors / pan"],
  ["1 … 9, 0  ·  ⇧1 … ⇧0", "classes 1 … 10 · 11 … 20 of the palette"],
  [", / .", "previous / next class (reaches every class)"],
  ["[ / ]", "brush size smaller / larger (kept between frames)"],
  ["+ / − / Home", "zoom in / out / fit; wheel zooms at the cursor"],
  ["arrows, Space+drag, middle drag", "pan"],
  ["O", "mask on / off"],
  ["L", "outline mode (class borders, faint insides)"],
  ["Ctrl+Z / Ctrl+Shift+Z", "undo / redo"],
  ["polygon: Enter, Backspace, Esc", "close and fill / remove last vertex / cancel"],
  ["GrabCut: drag a box, then scribble", "left drag: object, right drag (or X to switch): background; each scribble cuts again · Enter accept · Esc cancel (mask as before the box)"],
  ["scissors: click, Shift+click, Enter", "anchor (path snaps to edges, live preview) / straight segment / close and fill (or click the first anchor)"],
  ["scissors: Backspace, Esc", "remove the last anchor / cancel"],
];

/** The keyboard help table (#hotkeys) of rows [[keys, what], ...]. */
export function keysTable(rows) {
  return el("table", { class: "keys", id: "hotkeys" }, el("tbody", {}, rows.map(([k, v]) => el("tr", {}, el("th", { scope: "row" }, el("kbd", {}, k)), el("td", {}, v)))));
}

function loadPrefs(key) {
  try {
    return JSON.parse(localStorage.getItem(key) || "{}") || {};
  } catch {
    return {};
  }
}

/** Bind the server-side smart tools (GrabCut, intelligent scissors) of frame `frameId` to
 * editor `ed`; `alive()` is false once the page has moved on (the answer is then dropped). */
export function bindSmartTools(ed, frameId, alive) {
  ed.smart = {
    grabcut: async (rect, { strokes = [] } = {}) => {
      const res = await api.send("POST", `/frames/${frameId}/grabcut`, { json: { rect, strokes } });
      const box = (res.headers.get("X-Box") || rect.join(",")).split(",").map(Number);
      const d = await decodeIdPng(await res.blob());
      return alive() ? { ids: d.ids, width: d.width, height: d.height, box } : null;
    },
    scissors: async (start, end) => {
      const r = await api.post(`/frames/${frameId}/scissors`, { start, end });
      return alive() ? r.path : null;
    },
  };
}

export class Workbench {
  /**
   * toolsEl / paletteEl: the (empty) elements that receive the tool column and the palette;
   * prefsKey: localStorage key of the kept preferences (tool, brush size, opacity, outline,
   * hidden classes); readOnly(): whether the page's frame is read-only now; onHistory(): called
   * after every undo-stack change (after the undo / redo buttons are updated).
   */
  constructor({ toolsEl, paletteEl, prefsKey, readOnly = () => false, onHistory = null }) {
    this.toolsEl = toolsEl;
    this.paletteEl = paletteEl;
    this.prefsKey = prefsKey;
    this.readOnly = readOnly;
    this.onHistory = onHistory;
    this.prefs = loadPrefs(prefsKey);
    this.ed = null;
    this.outlineBox = null;
    this.minimap = null;
  }

  /** Build the tool column and the palette for editor `ed` (replacing the previous one's). */
  attach(ed) {
    this.ed = ed;
    this.buildTools();
    this.buildPalette(ed.classes);
  }

  savePrefs(patch) {
    Object.assign(this.prefs, patch);
    try {
      localStorage.setItem(this.prefsKey, JSON.stringify(this.prefs));
    } catch {
      /* private mode: keep them for this page only */
    }
  }

  /** Tool, brush size, opacity, outline mode and hidden classes carry over to the next frame. */
  applyPrefs() {
    const ed = this.ed;
    const p = this.prefs;
    if (p.size) ed.setSize(p.size);
    if (p.opacity != null) ed.setOpacity(p.opacity);
    if (p.tool && ed.tools[p.tool]) ed.setTool(p.tool);
    if (p.outline || (p.hidden && p.hidden.length)) {
      ed.mask.hidden = new Set(p.hidden || []);
      ed.mask.lut = ed.mask.baseLut.slice();
      for (const id of ed.mask.hidden) ed.mask.lut[id] = 0;
      ed.mask.setStyle(p.outline ? "outline" : "fill");
    }
    this.outlineBox.checked = !!p.outline;
    this.paletteEl.querySelectorAll(".eye").forEach((b) => b.setAttribute("aria-pressed", String(!ed.mask.hidden.has(Number(b.dataset.class)))));
  }

  /** Painting tools, undo / redo and the palette disabled while read-only (pan stays). */
  setReadOnly(on) {
    this.toolsEl.querySelectorAll("button.tool").forEach((b) => {
      if (b.dataset.tool !== "pan") b.disabled = on;
    });
    this.refreshUndo?.(); // undo/redo: enabled only with something to undo/redo
    this.paletteEl.querySelectorAll("button").forEach((b) => (b.disabled = on));
  }

  get outline() {
    return !!(this.outlineBox && this.outlineBox.checked);
  }

  setOutline(on) {
    this.ed.mask.setStyle(on ? "outline" : "fill");
    this.outlineBox.checked = on;
    this.savePrefs({ outline: on });
  }

  toggleClass(id) {
    const m = this.ed.mask;
    const hidden = new Set(m.hidden);
    if (hidden.has(id)) hidden.delete(id);
    else hidden.add(id);
    m.setHidden(hidden);
    this.savePrefs({ hidden: [...hidden] });
    this.paletteEl.querySelectorAll(".eye").forEach((b) => b.setAttribute("aria-pressed", String(!hidden.has(Number(b.dataset.class)))));
  }

  /** The workbench's own keys (L: outline mode), then the editor's; true when used. */
  handleKey(e) {
    if (!this.ed) return false;
    if (e.type === "keydown" && (e.key === "l" || e.key === "L") && !e.ctrlKey && !e.metaKey) {
      this.setOutline(!this.outline);
      return true;
    }
    return this.ed.handleKey(e);
  }

  buildTools() {
    const ed = this.ed;
    const btns = Object.values(ed.tools).map((t) =>
      el("button", { type: "button", class: "tool", "data-tool": t.name, "aria-pressed": String(t === ed.tool), title: `${t.label} (${t.key.toUpperCase()})`, onclick: () => ed.setTool(t.name) }, `${t.label}`, el("kbd", {}, t.key.toUpperCase())),
    );
    const size = el("input", { type: "range", id: "brush-size", min: 1, max: 400, value: ed.state.size });
    const sizeOut = el("output", { for: "brush-size" }, `${ed.state.size} px`);
    size.addEventListener("input", () => ed.setSize(Number(size.value)));
    const op = el("input", { type: "range", id: "opacity", min: 0, max: 100, value: Math.round(ed.state.opacity * 100) });
    const opOut = el("output", { for: "opacity" }, `${Math.round(ed.state.opacity * 100)} %`);
    op.addEventListener("input", () => ed.setOpacity(Number(op.value) / 100));
    const tol = el("input", { type: "range", id: "tolerance", min: 0, max: 128, value: ed.state.tolerance });
    const tolOut = el("output", { for: "tolerance" }, `${ed.state.tolerance}`);
    tol.addEventListener("input", () => {
      ed.state.tolerance = Number(tol.value);
      tolOut.textContent = tol.value;
    });
    const undo = el("button", { type: "button", id: "undo", title: "Undo (Ctrl+Z)", onclick: () => ed.undo() }, "Undo");
    const redo = el("button", { type: "button", id: "redo", title: "Redo (Ctrl+Shift+Z)", onclick: () => ed.redo() }, "Redo");
    const fit = el("button", { type: "button", title: "Fit to window (Home)", onclick: () => ed.view.fit() }, "Fit");
    const refreshUndo = () => {
      if (this.ed !== ed) return;
      undo.disabled = this.readOnly() || !ed.history.undos.length;
      redo.disabled = this.readOnly() || !ed.history.redos.length;
      this.onHistory?.();
    };
    this.refreshUndo = refreshUndo;
    ed.history.changed.add(refreshUndo);
    refreshUndo();
    ed.signals.toolChanged.add((name) => {
      btns.forEach((b) => b.setAttribute("aria-pressed", String(b.dataset.tool === name)));
      if (!this.readOnly()) this.savePrefs({ tool: name });
    });
    const zoom = el("output", { id: "zoom-level", title: "Zoom (+ / − / Home)" }, "");
    const showZoom = () => (zoom.textContent = `${Math.round(ed.view.scale * 100)} %`);
    ed.view.transformChanged.add(() => {
      showZoom();
      this.drawMinimap();
    });
    showZoom();
    this.outlineBox = el("input", { type: "checkbox", id: "outline" });
    this.outlineBox.addEventListener("change", () => this.setOutline(this.outlineBox.checked));
    this.minimap = el("canvas", { id: "minimap", class: "minimap", title: "Overview: click to move the view there", width: 150, height: 100 });
    this.minimap.addEventListener("click", (e) => {
      const r = this.minimap.getBoundingClientRect();
      const k = this.minimapScale;
      if (!k) return;
      const v = ed.view;
      const ix = (e.clientX - r.left) / k, iy = (e.clientY - r.top) / k;
      v.tx = v.cssW / 2 - ix * v.scale;
      v.ty = v.cssH / 2 - iy * v.scale;
      v.invalidate();
      v.transformChanged.dispatch();
    });
    ed.signals.sizeChanged.add((s) => {
      size.value = s;
      sizeOut.textContent = `${s} px`;
      this.savePrefs({ size: s });
    });
    ed.signals.opacityChanged.add((a) => {
      op.value = Math.round(a * 100);
      opOut.textContent = `${Math.round(a * 100)} %`;
      this.savePrefs({ opacity: a });
    });
    this.toolsEl.replaceChildren(
      ...btns,
      el("div", { class: "row" }, undo, redo, fit),
      el("label", { for: "brush-size" }, "Brush size ", sizeOut),
      size,
      el("label", { for: "opacity" }, "Mask opacity (O) ", opOut),
      op,
      el("label", { for: "tolerance" }, "Flood tolerance ", tolOut),
      tol,
      el("label", { for: "outline", class: "check" }, this.outlineBox, " Outline mode (L)"),
      el("div", { class: "row" }, el("span", { class: "muted" }, "Zoom"), zoom),
      this.minimap,
    );
    requestAnimationFrame(() => this.drawMinimap());
  }

  /** The photo scaled into the minimap with the visible part of the view as a rectangle. */
  drawMinimap() {
    const c = this.minimap;
    const ed = this.ed;
    if (!c || !ed) return;
    const v = ed.view;
    const k = Math.min(c.width / v.width, c.height / v.height);
    this.minimapScale = k;
    const g = c.getContext("2d");
    g.fillStyle = "#2b2f36";
    g.fillRect(0, 0, c.width, c.height);
    if (ed.photo) g.drawImage(ed.photo, 0, 0, v.width * k, v.height * k);
    g.globalAlpha = 0.6;
    g.drawImage(ed.mask.canvas, 0, 0, v.width * k, v.height * k);
    g.globalAlpha = 1;
    const [x0, y0] = [-v.tx / v.scale, -v.ty / v.scale];
    g.strokeStyle = "#ffbf47";
    g.lineWidth = 2;
    g.strokeRect(x0 * k, y0 * k, (v.cssW / v.scale) * k, (v.cssH / v.scale) * k);
  }

  buildPalette(classes) {
    const ed = this.ed;
    const keyOf = (i) => (i < 10 ? String((i + 1) % 10) : i < 20 ? `⇧${(i - 9) % 10}` : ", .");
    const items = classes.map((c, i) =>
      el(
        "button",
        { type: "button", role: "radio", class: "swatch-btn", "data-class": c.id, "aria-checked": String(c.id === ed.state.classId), title: `${c.name} (id ${c.id}, ${c.group})` },
        el("span", { class: "swatch", style: { background: ed.classCss(c.id) } }),
        el("kbd", {}, keyOf(i)),
        el("span", {}, c.name),
      ),
    );
    items.forEach((b) => b.addEventListener("click", () => ed.selectClass(Number(b.dataset.class))));
    // per-class hide / show (the colour layer only; the ids stay)
    const rows = items.map((b, i) =>
      el("div", { class: "palette-row" }, b, el("button", { type: "button", class: "eye", "data-class": classes[i].id, "aria-pressed": "true", title: `Show / hide ${classes[i].name}`, "aria-label": `Show ${classes[i].name}`, onclick: () => this.toggleClass(classes[i].id) }, "◉")),
    );
    ed.signals.classChanged.add((id) => items.forEach((b) => b.setAttribute("aria-checked", String(Number(b.dataset.class) === id))));
    this.paletteEl.replaceChildren(...rows);
  }
}
