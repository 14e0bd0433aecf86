// Intelligent scissors: an edge-snapping polygon. Click anchor points along an object's
// outline; between consecutive anchors the server finds the path that follows the photo's
// edges (OpenCV IntelligentScissorsMB on a crop around the two anchors), and a live preview
// shows that path from the last anchor to the cursor (throttled, the newest request wins).
// Shift+click adds a straight segment. Click the first anchor, double-click or press Enter to
// close: the polygon is filled with the active class as one command on the undo stack.
// Backspace removes the last anchor, Escape cancels. The page provides
// `editor.smart.scissors(start, end) -> [[x, y], ...]` (image pixels, start and end included).

import { fillPolygon } from "../paint/mask.js";
import { PatchCommand } from "../paint/history.js";

const PREVIEW_MS = 120; // at most one preview request per this many ms (one in flight)
const CLOSE_PX = 9; // a click this close (screen px) to the first anchor closes the polygon

/** Give value v to every pixel on the closed ring of pixel vertices (8-connected lines). */
export function strokeRing(mask, patch, ring, v) {
  if (!ring.length) return null;
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (const [x, y] of ring) {
    x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x + 1); y1 = Math.max(y1, y + 1);
  }
  patch.touch(x0, y0, x1, y1);
  const { ids, width } = mask;
  let delta = 0;
  const set = (x, y) => {
    const i = y * width + x;
    if (ids[i] === v) return;
    if (ids[i] === 0) delta++;
    else if (v === 0) delta--;
    ids[i] = v;
  };
  for (let k = 0; k < ring.length; k++) {
    const [ax, ay] = ring[k], [bx, by] = ring[(k + 1) % ring.length];
    const n = Math.max(Math.abs(bx - ax), Math.abs(by - ay));
    for (let t = 0; t <= n; t++) set(Math.round(ax + ((bx - ax) * t) / Math.max(1, n)), Math.round(ay + ((by - ay) * t) / Math.max(1, n)));
  }
  mask.painted += delta;
  return [x0, y0, x1, y1];
}

export class ScissorsTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "scissors";
    this.label = "Scissors";
    this.key = "i";
    this.cursor = "crosshair";
    this.anchors = []; // {p: [x, y], seg: {path: [[x, y]...] from the previous anchor, pending} | null}
    this.at = null;
    this.preview = null; // {from: anchor, to: [x, y], path}
    this._previewBusy = false;
    this._previewWant = null;
    this._previewLast = 0;
    this._timer = null;
    this.closing = false;
  }

  _px(p) {
    const m = this.editor.mask;
    return [Math.max(0, Math.min(m.width - 1, Math.floor(p[0]))), Math.max(0, Math.min(m.height - 1, Math.floor(p[1])))];
  }

  _nearFirst(p) {
    if (this.anchors.length < 2) return false;
    const v = this.editor.view;
    const [fx, fy] = v.toScreen(this.anchors[0].p[0] + 0.5, this.anchors[0].p[1] + 0.5);
    const [px, py] = v.toScreen(p[0], p[1]);
    return Math.hypot(fx - px, fy - py) < CLOSE_PX;
  }

  /** The path between two pixels: snapped by the server, straight if asked or unavailable. */
  _segment(a, b, straight) {
    const ed = this.editor;
    const seg = { path: null, pending: null };
    if (straight || !ed.smart || !ed.smart.scissors) {
      seg.path = [a, b];
      return seg;
    }
    const pv = this.preview;
    if (pv && pv.from[0] === a[0] && pv.from[1] === a[1] && pv.to[0] === b[0] && pv.to[1] === b[1]) {
      seg.path = pv.path; // the preview the user saw is the segment they clicked
      return seg;
    }
    seg.pending = ed.smart
      .scissors(a, b)
      .then((path) => {
        seg.path = path && path.length ? path : [a, b];
      })
      .catch((e) => {
        seg.path = [a, b];
        ed.setStatus(`Scissors: could not snap the segment (${e.message}); it is a straight line.`);
      })
      .finally(() => {
        seg.pending = null;
        ed.view.request();
      });
    return seg;
  }

  down(p, e) {
    if (this.closing) return;
    if (this._nearFirst(p) || (e?.detail >= 2 && this.anchors.length >= 2)) {
      this.close(e?.shiftKey);
      return;
    }
    const q = this._px(p);
    const last = this.anchors[this.anchors.length - 1];
    if (last && last.p[0] === q[0] && last.p[1] === q[1]) return;
    this.anchors.push({ p: q, seg: last ? this._segment(last.p, q, e?.shiftKey) : null });
    this.preview = null;
    if (this.anchors.length === 1) this.editor.setStatus("Scissors: click along the outline; the path snaps to edges (Shift+click: straight). Click the first point or press Enter to fill, Backspace removes the last point, Esc cancels.");
    this.editor.view.request();
  }

  move(points, e) {
    this.at = points[points.length - 1];
    this.editor.view.request();
    if (!this.anchors.length || this.closing || e?.shiftKey) return;
    this._previewWant = this._px(this.at);
    this._schedulePreview();
  }

  _schedulePreview() {
    if (this._previewBusy || this._timer) return;
    const wait = Math.max(0, PREVIEW_MS - (performance.now() - this._previewLast));
    this._timer = setTimeout(() => {
      this._timer = null;
      this._runPreview();
    }, wait);
  }

  async _runPreview() {
    const ed = this.editor;
    const want = this._previewWant;
    const from = this.anchors[this.anchors.length - 1];
    if (!want || !from || !ed.smart || !ed.smart.scissors) return;
    const pv = this.preview;
    if (pv && pv.from === from.p && pv.to[0] === want[0] && pv.to[1] === want[1]) return;
    this._previewBusy = true;
    this._previewLast = performance.now();
    try {
      const path = await ed.smart.scissors(from.p, want);
      // still the same last anchor: show it (an older anchor's answer is dropped)
      if (path && this.anchors[this.anchors.length - 1] === from) {
        this.preview = { from: from.p, to: want, path };
        ed.view.request();
      }
    } catch {
      // a failed preview is not an error: the click will ask again (and say so if it fails)
    } finally {
      this._previewBusy = false;
      const w = this._previewWant;
      if (w && this.anchors.length && (w[0] !== want[0] || w[1] !== want[1])) this._schedulePreview();
    }
  }

  up() {}

  onKey(e) {
    if (this.closing) return ["Enter", "Escape", "Backspace"].includes(e.key); // wait for the fill
    if (e.key === "Enter" && this.anchors.length >= 2) {
      this.close(e.shiftKey);
      return true;
    }
    if (e.key === "Escape" && this.anchors.length) {
      this.reset();
      this.editor.setStatus("Scissors: cancelled.");
      return true;
    }
    if (e.key === "Backspace" && this.anchors.length) {
      this.anchors.pop();
      this.preview = null;
      this.editor.view.request();
      return true;
    }
    return false;
  }

  reset() {
    this.anchors = [];
    this.preview = null;
    this._previewWant = null;
    clearTimeout(this._timer);
    this._timer = null;
    this.editor.view.request();
  }

  /** The outline so far as polygon vertices (pixel centres), each joint once. */
  outline(anchors = this.anchors, closing = null) {
    const pts = [];
    const push = (q) => {
      const l = pts[pts.length - 1];
      if (!l || l[0] !== q[0] || l[1] !== q[1]) pts.push(q);
    };
    anchors.forEach((a, i) => {
      if (i === 0) push(a.p);
      else for (const q of a.seg.path || [anchors[i - 1].p, a.p]) push(q);
    });
    if (closing) for (const q of closing.path || []) push(q);
    if (pts.length > 1 && pts[0][0] === pts[pts.length - 1][0] && pts[0][1] === pts[pts.length - 1][1]) pts.pop();
    return pts;
  }

  /** Close the polygon (snapped last -> first segment) and fill it: one undoable command. */
  async close(straight = false) {
    const ed = this.editor;
    const anchors = this.anchors;
    if (anchors.length < 2 || this.closing) return;
    this.closing = true;
    ed.setStatus("Scissors: closing the outline…");
    ed.view.request();
    try {
      const closing = this._segment(anchors[anchors.length - 1].p, anchors[0].p, straight);
      this._closingSeg = closing;
      await Promise.all([...anchors.slice(1).map((a) => a.seg.pending), closing.pending].filter(Boolean));
      if (this.editor !== ed || this.anchors !== anchors || ed.readOnly) return;
      const pts = this.outline(anchors, closing).map(([x, y]) => [x + 0.5, y + 0.5]);
      this.anchors = [];
      this.preview = null;
      if (pts.length < 3) {
        ed.setStatus("Scissors: the outline encloses nothing; click at least three points around the object.");
        return;
      }
      const v = ed.state.classId;
      const mask = ed.mask;
      const ring = this.outline(anchors, closing);
      ed.history.execute(new PatchCommand("scissors", mask, (patch) => {
        const r = fillPolygon(mask, patch, pts, v);
        const e = strokeRing(mask, patch, ring, v); // the outline's own pixels belong to the region
        return r && e ? [Math.min(r[0], e[0]), Math.min(r[1], e[1]), Math.max(r[2], e[2]), Math.max(r[3], e[3])] : r || e;
      }));
      ed.setStatus(`Scissors: the outline (${pts.length} vertices) filled with the class (Ctrl+Z undoes it).`);
    } finally {
      this.closing = false;
      this._closingSeg = null;
      ed.view.request();
    }
  }

  cancel() {
    if (!this.closing) this.reset();
  }

  leave() {}

  overlay(ctx, view) {
    if (!this.anchors.length) return;
    const last = this.anchors[this.anchors.length - 1];
    const pv = this.preview && this.preview.from === last.p && !this.closing && this.at ? this.preview : null;
    // the region the outline encloses so far (with the preview), lightly in the class colour
    const ring = this.outline();
    if (pv) for (const q of pv.path) ring.push(q);
    if (ring.length >= 3) {
      ctx.globalAlpha = 0.25;
      ctx.fillStyle = this.editor.classCss(this.editor.state.classId);
      ctx.beginPath();
      ring.forEach((q, i) => {
        const [x, y] = view.toScreen(q[0] + 0.5, q[1] + 0.5);
        if (i === 0) ctx.moveTo(x, y);
        else ctx.lineTo(x, y);
      });
      ctx.closePath();
      ctx.fill();
      ctx.globalAlpha = 1;
    }
    const line = (path, dash) => {
      ctx.setLineDash(dash);
      ctx.beginPath();
      path.forEach((q, i) => {
        const [x, y] = view.toScreen(q[0] + 0.5, q[1] + 0.5);
        if (i === 0) ctx.moveTo(x, y);
        else ctx.lineTo(x, y);
      });
      ctx.stroke();
    };
    ctx.lineJoin = "round";
    // a bright line on a dark halo: visible on any photo and any class colour
    for (const [w, c] of [[5, "rgba(0,0,0,0.65)"], [2, "#ffd54a"]]) {
      ctx.lineWidth = w;
      ctx.strokeStyle = c;
      this.anchors.forEach((a, i) => {
        if (i > 0) line(a.seg.path || [this.anchors[i - 1].p, a.p], a.seg.path ? [] : [4, 4]);
      });
      if (this._closingSeg) line(this._closingSeg.path || [last.p, this.anchors[0].p], [4, 4]);
      if (pv) line(pv.path, [6, 3]);
      else if (!this.closing && this.at) line([last.p, this._px(this.at)], [2, 4]);
    }
    ctx.setLineDash([]);
    const near = this.at && this._nearFirst(this.at);
    this.anchors.forEach((a, i) => {
      const [x, y] = view.toScreen(a.p[0] + 0.5, a.p[1] + 0.5);
      const r = i === 0 && near ? 6 : 4;
      ctx.fillStyle = i === 0 && near ? "#ff9f1c" : "#ffffff";
      ctx.strokeStyle = "rgba(0,0,0,0.8)";
      ctx.lineWidth = 1.5;
      ctx.fillRect(x - r, y - r, 2 * r, 2 * r);
      ctx.strokeRect(x - r, y - r, 2 * r, 2 * r);
    });
  }
}
