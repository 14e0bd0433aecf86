// Polygon fill: click to add vertices; click the first vertex, double-click or press Enter to
// fill the polygon with the active class; Backspace removes the last vertex, Escape cancels.

import { fillPolygon } from "../paint/mask.js";
import { PatchCommand } from "../paint/history.js";

export class PolygonTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "polygon";
    this.label = "Polygon";
    this.key = "p";
    this.cursor = "crosshair";
    this.points = [];
    this.at = null;
  }
  down(p, e) {
    const v = this.editor.view;
    if (this.points.length >= 3) {
      const [fx, fy] = v.toScreen(...this.points[0]);
      const [px, py] = v.toScreen(...p);
      if (Math.hypot(fx - px, fy - py) < 8 || e?.detail >= 2) {
        this.close();
        return;
      }
    }
    this.points.push(p);
    v.request();
  }
  move(points) {
    this.at = points[points.length - 1];
    this.editor.view.request();
  }
  up() {}
  onKey(e) {
    if (e.key === "Enter" && this.points.length >= 3) {
      this.close();
      return true;
    }
    if (e.key === "Escape" && this.points.length) {
      this.points = [];
      this.editor.view.request();
      return true;
    }
    if (e.key === "Backspace" && this.points.length) {
      this.points.pop();
      this.editor.view.request();
      return true;
    }
    return false;
  }
  close() {
    const pts = this.points;
    this.points = [];
    if (pts.length < 3) return;
    const value = this.editor.state.classId;
    const mask = this.editor.mask;
    this.editor.history.execute(new PatchCommand("polygon", mask, (patch) => fillPolygon(mask, patch, pts, value)));
    this.editor.view.request();
  }
  cancel() {
    this.points = [];
  }
  leave() {}
  overlay(ctx, view) {
    if (!this.points.length) return;
    ctx.lineWidth = 2;
    ctx.strokeStyle = this.editor.classCss(this.editor.state.classId);
    ctx.fillStyle = "rgba(255,255,255,0.9)";
    ctx.beginPath();
    this.points.forEach((p, i) => {
      const [x, y] = view.toScreen(...p);
      if (i === 0) ctx.moveTo(x, y);
      else ctx.lineTo(x, y);
    });
    if (this.at) ctx.lineTo(...view.toScreen(...this.at));
    ctx.stroke();
    for (const p of this.points) {
      const [x, y] = view.toScreen(...p);
      ctx.fillRect(x - 3, y - 3, 6, 6);
    }
  }
}
