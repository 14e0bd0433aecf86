// GrabCut box + scribbles: drag a box around an object; the server cuts it out of the photo
// (OpenCV GrabCut, no model download) and the object's pixels get the active class -- one
// command on the undo stack. Then refine: paint foreground scribbles (left drag) on parts the
// cut missed and background scribbles (right drag, or X to switch the left button) on parts
// it took wrongly; each scribble re-runs the cut with all scribbles so far and the new cut
// replaces the previous one in that same command (undo restores the mask from before the
// GrabCut). Enter accepts, Escape cancels (the mask as before the box). The page provides
// `editor.smart.grabcut(rect, {strokes}) -> {ids, width, height, box}`.

import { PatchCommand } from "../paint/history.js";

const MAX_POINTS = 20_000; // all strokes together, the API's limit
const FG = "#3ddc84";
const BG = "#ff5a5a";

export class GrabCutTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "grabcut";
    this.label = "GrabCut box";
    this.key = "g";
    this.cursor = "crosshair";
    this.rightButton = true; // right drag = background scribble while refining
    this.start = null;
    this.at = null;
    this.busy = false;
    this.session = null; // {rect, cmd, strokes: [{kind, pts}], sent}
    this.stroke = null;
    this.mark = "fg"; // what a left-button scribble marks (X switches)
  }

  get refining() {
    return !!this.session;
  }

  down(p, e) {
    if (this.session) {
      const kind = e?.button === 2 ? "bg" : e?.shiftKey ? (this.mark === "fg" ? "bg" : "fg") : this.mark;
      this.stroke = { kind, pts: [p] };
      this.editor.view.request();
      return;
    }
    if (this.busy || e?.button === 2) return; // boxes are dragged with the left button
    this.start = p;
    this.at = p;
  }

  move(points) {
    this.at = points[points.length - 1];
    if (this.stroke) {
      for (const q of points) this.stroke.pts.push(q);
      this.editor.view.request();
    } else if (this.start) this.editor.view.request();
  }

  async up(p) {
    const ed = this.editor;
    if (this.stroke) {
      const s = this.stroke;
      this.stroke = null;
      if (p) s.pts.push(p);
      if (this.session) {
        this.session.strokes.push(s);
        this.recut();
      }
      return;
    }
    if (!this.start || this.busy) return;
    const a = this.start;
    this.start = null;
    const W = ed.mask.width, H = ed.mask.height;
    const rect = [Math.floor(Math.min(a[0], p[0])), Math.floor(Math.min(a[1], p[1])), Math.ceil(Math.max(a[0], p[0])), Math.ceil(Math.max(a[1], p[1]))].map((v, i) => Math.max(0, Math.min(i % 2 ? H : W, v)));
    if (rect[2] - rect[0] < 3 || rect[3] - rect[1] < 3) {
      ed.setStatus("GrabCut: drag a box around the object.");
      ed.view.request();
      return;
    }
    if (!ed.smart || !ed.smart.grabcut) {
      ed.setStatus("GrabCut is not available here.");
      return;
    }
    this.lastRect = rect;
    this.session = { rect, cmd: null, strokes: [], sent: -1, classId: ed.state.classId };
    await this.recut();
  }

  /** The scribbles as the API's strokes: integer pixels, in painting order (a later wins). */
  scribbles() {
    const W = this.editor.mask.width, H = this.editor.mask.height;
    const out = this.session.strokes.map((st) => {
      const pts = [];
      for (const [x, y] of st.pts) {
        const q = [Math.max(0, Math.min(W - 1, Math.floor(x))), Math.max(0, Math.min(H - 1, Math.floor(y)))];
        const l = pts[pts.length - 1];
        if (!l || l[0] !== q[0] || l[1] !== q[1]) pts.push(q);
      }
      return { kind: st.kind, points: pts };
    });
    const total = out.reduce((n, st) => n + st.points.length, 0);
    if (total > MAX_POINTS) {
      const f = Math.ceil(total / MAX_POINTS); // keep every f-th point (and each stroke's ends)
      for (const st of out) st.points = st.points.filter((_, i) => i % f === 0 || i === st.points.length - 1);
    }
    return out;
  }

  /** Run the cut for the box and every scribble so far; the newest request wins. */
  async recut() {
    const ed = this.editor;
    const s = this.session;
    if (!s || this.busy) return;
    this.busy = true;
    ed.view.request();
    try {
      while (this.session === s && s.sent < s.strokes.length) {
        const n = s.strokes.length;
        s.sent = n;
        const strokes = this.scribbles();
        ed.setStatus(n ? `GrabCut: cutting again with ${n} scribble${n > 1 ? "s" : ""}…` : "GrabCut: cutting the object out of the box…");
        const r = await ed.smart.grabcut(s.rect, { strokes });
        if (!r || this.editor !== ed || ed.readOnly || this.session !== s) return;
        if (s.sent !== s.strokes.length) continue; // scribbled meanwhile: cut again with all of them
        const n1 = this.apply(s, r);
        const hint = "left drag: foreground, right drag (or X to switch): background · Enter accept · Esc cancel";
        ed.setStatus(`GrabCut: ${n1.toLocaleString()} pixels of the box given the class${n ? ` (${n} scribble${n > 1 ? "s" : ""})` : ""}. Refine — ${hint}.`);
      }
    } catch (e) {
      ed.setStatus(`GrabCut failed: ${e.message}`);
      if (this.session === s && !s.cmd) this.session = null;
    } finally {
      this.busy = false;
      ed.view.request();
    }
  }

  /** Put the cut into the mask: the first one as a new command, later ones amend it. */
  apply(s, r) {
    const ed = this.editor;
    const W = ed.mask.width;
    const [x0, y0, x1, y1] = r.box;
    const v = s.classId;
    let n = 0;
    const paint = (patch) => {
      patch.touch(x0, y0, x1, y1);
      const ids = ed.mask.ids;
      let delta = 0;
      for (let y = y0; y < y1; y++)
        for (let x = x0; x < x1; x++) {
          if (!r.ids[(y - y0) * r.width + (x - x0)]) continue;
          const i = y * W + x;
          if (ids[i] === v) continue;
          if (ids[i] === 0) delta++;
          ids[i] = v;
          n++;
        }
      ed.mask.painted += delta;
      return [x0, y0, x1, y1];
    };
    if (s.cmd && ed.history.amend(s.cmd, paint)) return n;
    s.cmd = new PatchCommand("grabcut", ed.mask, paint);
    ed.history.execute(s.cmd);
    return n;
  }

  /** Enter: keep the cut (it stays one command on the undo stack). */
  accept() {
    if (!this.session) return;
    this.session = null;
    this.stroke = null;
    this.editor.setStatus("GrabCut accepted (Ctrl+Z undoes it). Drag a new box for the next object.");
    this.editor.view.request();
  }

  /** Escape: the mask as before the box. */
  abort() {
    const s = this.session;
    if (!s) return;
    this.session = null;
    this.stroke = null;
    if (s.cmd) this.editor.history.discard(s.cmd);
    this.editor.setStatus("GrabCut cancelled: the mask is as before the box.");
    this.editor.view.request();
  }

  onKey(e) {
    if (!this.session) return false;
    if (e.key === "Enter") {
      this.accept();
      return true;
    }
    if (e.key === "Escape") {
      this.abort();
      return true;
    }
    if (e.key === "x" || e.key === "X") {
      this.mark = this.mark === "fg" ? "bg" : "fg";
      this.editor.setStatus(`GrabCut: the left button now marks ${this.mark === "fg" ? "foreground (object)" : "background (not the object)"}.`);
      this.editor.view.request();
      return true;
    }
    return false;
  }

  // another tool, undo / redo, a new frame: the cut so far is kept (Ctrl+Z still undoes it)
  cancel() {
    this.start = null;
    this.stroke = null;
    this.session = null;
    this.editor.view.request();
  }

  leave() {}

  overlay(ctx, view) {
    const s = this.session;
    const box = s ? s.rect : this.start && this.at ? [this.start[0], this.start[1], this.at[0], this.at[1]] : null;
    if (!box) return;
    const [a, b] = view.toScreen(box[0], box[1]);
    const [c, d] = view.toScreen(box[2], box[3]);
    ctx.lineWidth = 2;
    ctx.setLineDash(this.busy ? [2, 4] : [6, 4]);
    ctx.strokeStyle = "#ffbf47";
    ctx.strokeRect(a, b, c - a, d - b);
    ctx.setLineDash([]);
    if (!s) return;
    const strokes = this.stroke ? [...s.strokes, this.stroke] : s.strokes;
    ctx.lineCap = "round";
    ctx.lineJoin = "round";
    for (const st of strokes) {
      ctx.strokeStyle = st.kind === "fg" ? FG : BG;
      ctx.lineWidth = 4;
      ctx.beginPath();
      st.pts.forEach((p, i) => {
        const [x, y] = view.toScreen(p[0], p[1]);
        if (i === 0) ctx.moveTo(x, y);
        else ctx.lineTo(x, y);
      });
      if (st.pts.length === 1) ctx.lineTo(...view.toScreen(st.pts[0][0] + 0.01, st.pts[0][1]));
      ctx.stroke();
    }
    // which kind the left button marks
    ctx.font = "12px sans-serif";
    ctx.fillStyle = this.mark === "fg" ? FG : BG;
    ctx.fillText(this.mark === "fg" ? "+ object (X: switch)" : "− background (X: switch)", a + 4, Math.max(12, b - 6));
  }
}
