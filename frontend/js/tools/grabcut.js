// GrabCut box: drag a box around an object; the server cuts it out of the photo (OpenCV
// GrabCut, no model download) and the object's pixels get the active class -- one command on
// the undo stack. The page provides `editor.smart.grabcut(rect) -> {ids, width, height, box}`.

import { PatchCommand } from "../paint/history.js";

export class GrabCutTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "grabcut";
    this.label = "GrabCut box";
    this.key = "g";
    this.cursor = "crosshair";
    this.start = null;
    this.at = null;
    this.busy = false;
  }
  down(p) {
    if (this.busy) return;
    this.start = p;
    this.at = p;
  }
  move(points) {
    this.at = points[points.length - 1];
    if (this.start) this.editor.view.request();
  }
  async up(p) {
    if (!this.start || this.busy) return;
    const ed = this.editor;
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
    this.busy = true;
    this.pending = rect;
    this.lastRect = rect;
    ed.view.request();
    ed.setStatus("GrabCut: cutting the object out of the box…");
    try {
      const r = await ed.smart.grabcut(rect);
      if (!r || this.editor !== ed || ed.readOnly) return;
      const [x0, y0, x1, y1] = r.box;
      const v = ed.state.classId;
      let n = 0;
      ed.history.execute(
        new PatchCommand("grabcut", ed.mask, (patch) => {
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
        }),
      );
      ed.setStatus(`GrabCut: ${n.toLocaleString()} pixels of the box given the class (Ctrl+Z undoes it).`);
    } catch (e) {
      ed.setStatus(`GrabCut failed: ${e.message}`);
    } finally {
      this.busy = false;
      this.pending = null;
      ed.view.request();
    }
  }
  cancel() {
    this.start = null;
  }
  leave() {}
  overlay(ctx, view) {
    const box = this.pending || (this.start && this.at ? [this.start[0], this.start[1], this.at[0], this.at[1]] : null);
    if (!box) return;
    const [a, b] = view.toScreen(box[0], box[1]);
    const [c, d] = view.toScreen(box[2], box[3]);
    ctx.lineWidth = 2;
    ctx.setLineDash(this.pending ? [2, 4] : [6, 4]);
    ctx.strokeStyle = "#ffbf47";
    ctx.strokeRect(a, b, c - a, d - b);
    ctx.setLineDash([]);
  }
}
