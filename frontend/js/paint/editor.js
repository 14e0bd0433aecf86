// The mask editor: model (MaskModel + History), view (View) and tools (one file each),
// wired by a small signal bus. Pages build their toolbars around `editor.signals`.

import { createSignals } from "../core/bus.js";
import { MaskModel } from "./mask.js";
import { History, PatchCommand } from "./history.js";
import { View } from "./view.js";
import { BrushTool } from "../tools/brush.js";
import { EraserTool } from "../tools/eraser.js";
import { PolygonTool } from "../tools/polygon.js";
import { FloodTool } from "../tools/flood.js";
import { PanTool, installWheelZoom } from "../tools/panzoom.js";
import { SuperpixelTool } from "../tools/superpixel.js";
import { GrabCutTool } from "../tools/grabcut.js";
import { ScissorsTool } from "../tools/scissors.js";

export class Editor {
  /**
   * container: element that receives the stacked canvases; width/height: image pixels;
   * classes: taxonomy rows [{id, name, rgb:[r,g,b], group}].
   */
  constructor(container, { width, height, classes }) {
    this.classes = classes;
    this.state = { classId: classes.length ? classes[0].id : 1, size: 24, tolerance: 24, opacity: 0.6 };
    this.signals = createSignals(["classChanged", "toolChanged", "sizeChanged", "opacityChanged", "edited", "status"]);
    this.mask = new MaskModel(width, height, classes);
    this.history = new History();
    this.history.changed.add((kind) => this.signals.edited.dispatch(kind));
    this.view = new View(container, width, height);
    this.view.setMask(this.mask);
    this.view.setOpacity(this.state.opacity);
    this.tools = {};
    for (const T of [BrushTool, EraserTool, PolygonTool, FloodTool, SuperpixelTool, GrabCutTool, ScissorsTool, PanTool]) {
      const t = new T(this);
      this.tools[t.name] = t;
    }
    this.tool = this.tools.brush;
    this.readOnly = false; // frames the user may look at but not change (submitted, accepted)
    this.view.beforeRender = () => this.tool.beforeRender?.();
    this.view.overlayPainters.push((ctx, v) => this.tool.overlay(ctx, v));
    this._css = new Map(classes.map((c) => [c.id, `rgb(${c.rgb[0]},${c.rgb[1]},${c.rgb[2]})`]));
    this._photoRgba = null;
    this._scratch = null;
    this._spaceDown = false;
    this._panning = null;
    installWheelZoom(this.view);
    this._bindPointer();
    this._setCursor();
  }

  destroy() {
    this.view.destroy();
    this.history.clear();
    // free the decoded 20-megapixel bitmaps now rather than at the next GC
    for (const l of this.view.pyramid || []) l.img.close?.();
    this.photo?.close?.();
  }

  classCss(id) {
    return this._css.get(id) || "rgb(128,128,128)";
  }

  setStatus(msg) {
    this.signals.status.dispatch(msg);
  }

  setPhoto(source) {
    this.photo = source;
    this._photoRgba = null;
    this.view.setPhoto(source);
  }

  /** The photo's RGBA bytes at mask resolution (read once, lazily, for flood fill). */
  async photoRgba() {
    if (this._photoRgba) return this._photoRgba;
    if (!this.photo) throw new Error("the image is not loaded yet");
    const c = new OffscreenCanvas(this.mask.width, this.mask.height);
    const ctx = c.getContext("2d", { willReadFrequently: true });
    ctx.drawImage(this.photo, 0, 0, this.mask.width, this.mask.height);
    this._photoRgba = ctx.getImageData(0, 0, this.mask.width, this.mask.height).data;
    return this._photoRgba;
  }

  scratch() {
    if (!this._scratch) this._scratch = new Uint8Array(this.mask.width * this.mask.height);
    return this._scratch;
  }

  selectClass(id) {
    if (!this._css.has(id)) return;
    this.state.classId = id;
    if (this.tool.name === "eraser" || this.tool.name === "pan") this.setTool("brush");
    this.signals.classChanged.dispatch(id);
    this.view.request();
  }

  setTool(name) {
    const t = this.tools[name];
    if (!t || t === this.tool) return;
    this.tool.cancel?.();
    this.tool = t;
    this._setCursor();
    this.signals.toolChanged.dispatch(name);
    this.view.request();
  }

  setSize(px) {
    this.state.size = Math.max(1, Math.min(1000, Math.round(px)));
    this.signals.sizeChanged.dispatch(this.state.size);
    this.view.request();
  }

  setOpacity(a) {
    this.state.opacity = Math.max(0, Math.min(1, a));
    this.view.setOpacity(this.state.opacity);
    this.signals.opacityChanged.dispatch(this.state.opacity);
  }

  /** Read-only: painting tools, undo/redo and replaceIds do nothing (pan and zoom still work). */
  setReadOnly(on) {
    this.readOnly = !!on;
    if (this.readOnly && this.tool.name !== "pan") this.tool.cancel?.();
    this.view.request();
  }

  /** Replace the whole mask as one undoable command (prefill, load a version). */
  replaceIds(name, ids, { onlyUnpainted = false } = {}) {
    if (this.readOnly) return;
    const m = this.mask;
    this.history.execute(
      new PatchCommand(name, m, (patch) => {
        patch.touch(0, 0, m.width, m.height);
        let n = 0;
        const cur = m.ids;
        for (let i = 0; i < cur.length; i++) {
          if (onlyUnpainted && cur[i] !== 0) {
            if (cur[i]) n++;
            continue;
          }
          cur[i] = ids[i];
          if (ids[i]) n++;
        }
        m.painted = n;
        return [0, 0, m.width, m.height];
      }),
    );
  }

  undo() {
    this.tool.cancel?.();
    if (this.readOnly) return false;
    return this.history.undo();
  }

  redo() {
    this.tool.cancel?.();
    if (this.readOnly) return false;
    return this.history.redo();
  }

  _setCursor() {
    this.view.overlay.style.cursor = this._spaceDown ? "grab" : this.tool.cursor;
  }

  _bindPointer() {
    const ov = this.view.overlay;
    const toImg = (e) => this.view.toImage(e.clientX, e.clientY);
    ov.addEventListener("pointerdown", (e) => {
      ov.focus({ preventScroll: true });
      if (e.button === 1 || (e.button === 0 && this._spaceDown)) {
        this._panning = [e.clientX, e.clientY];
        ov.setPointerCapture(e.pointerId);
        e.preventDefault();
        return;
      }
      if (e.button !== 0 && !(e.button === 2 && this.tool.rightButton)) return;
      if (this.readOnly && this.tool.name !== "pan") {
        this.setStatus("This frame is read-only: nothing you paint here would be saved.");
        return;
      }
      ov.setPointerCapture(e.pointerId);
      e.preventDefault();
      this._down = true;
      this.tool.down(toImg(e), e);
    });
    ov.addEventListener("pointermove", (e) => {
      if (this._panning) {
        this.view.panBy(e.clientX - this._panning[0], e.clientY - this._panning[1]);
        this._panning = [e.clientX, e.clientY];
        return;
      }
      if (this.readOnly && this.tool.name !== "pan" && !this._down) {
        this.tool.move([toImg(e)], e); // cursor preview only: tools paint between down and up
        return;
      }
      const evs = e.getCoalescedEvents ? e.getCoalescedEvents() : [];
      const pts = (evs.length ? evs : [e]).map(toImg);
      this.tool.move(pts, e);
    });
    const end = (e) => {
      if (this._panning) {
        this._panning = null;
        return;
      }
      if (ov.hasPointerCapture(e.pointerId)) ov.releasePointerCapture(e.pointerId);
      if (this.readOnly && !this._down) return;
      this._down = false;
      this.tool.up(toImg(e), e);
    };
    ov.addEventListener("pointerup", end);
    ov.addEventListener("pointercancel", end);
    ov.addEventListener("pointerleave", () => this.tool.leave());
    ov.addEventListener("contextmenu", (e) => e.preventDefault());
  }

  /** Keyboard shortcuts; returns true when the key was used. */
  handleKey(e) {
    if (e.type === "keyup") {
      if (e.code === "Space") {
        this._spaceDown = false;
        this._setCursor();
        return true;
      }
      return false;
    }
    const k = e.key;
    const mod = e.ctrlKey || e.metaKey;
    if (mod && (k === "z" || k === "Z")) {
      if (e.shiftKey) this.redo();
      else this.undo();
      return true;
    }
    if (mod && (k === "y" || k === "Y")) {
      this.redo();
      return true;
    }
    if (mod) return false;
    if (this.tool.onKey && this.tool.onKey(e)) return true;
    if (e.code === "Space") {
      this._spaceDown = true;
      this._setCursor();
      return true;
    }
    // Number keys: 1..9, 0 -> classes 1..10 of the palette; with Shift -> classes 11..20.
    if (/^Digit[0-9]$/.test(e.code)) {
      const d = Number(e.code.slice(5));
      const idx = (d === 0 ? 9 : d - 1) + (e.shiftKey ? 10 : 0);
      if (idx < this.classes.length) this.selectClass(this.classes[idx].id);
      return true;
    }
    // , and . step through the palette (reaches every class, also past the 20 number keys)
    if ((k === "," || k === ".") && this.classes.length) {
      const i = this.classes.findIndex((c) => c.id === this.state.classId);
      const n = this.classes.length;
      const j = i < 0 ? 0 : (i + (k === "." ? 1 : n - 1)) % n;
      this.selectClass(this.classes[j].id);
      return true;
    }
    const lower = k.toLowerCase();
    for (const t of Object.values(this.tools)) {
      if (t.key === lower && typeof t.key === "string") {
        this.setTool(t.name);
        return true;
      }
    }
    const r = this.view.overlay.getBoundingClientRect();
    switch (k) {
      case "[":
        this.setSize(this.state.size / 1.25);
        return true;
      case "]":
        this.setSize(this.state.size * 1.25);
        return true;
      case "+":
      case "=":
        this.view.zoomAt(1.25, r.width / 2, r.height / 2);
        return true;
      case "-":
        this.view.zoomAt(0.8, r.width / 2, r.height / 2);
        return true;
      case "Home":
        this.view.fit();
        return true;
      case "ArrowLeft":
        this.view.panBy(60, 0);
        return true;
      case "ArrowRight":
        this.view.panBy(-60, 0);
        return true;
      case "ArrowUp":
        this.view.panBy(0, 60);
        return true;
      case "ArrowDown":
        this.view.panBy(0, -60);
        return true;
      case "o":
      case "O":
        this.setOpacity(this.state.opacity > 0.05 ? 0 : 0.6);
        return true;
      default:
        return false;
    }
  }
}
