// Brush: paints the active class with a round, hard-edged brush (no anti-aliasing: every
// pixel gets exactly one class id). Consecutive pointer samples (including the browser's
// coalesced events) are merged into one StrokeCommand; each sample is joined to the previous
// one by a capsule, so fast strokes have no gaps.

import { stampSegment } from "../paint/mask.js";
import { StrokeCommand } from "../paint/history.js";

export class BrushTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "brush";
    this.label = "Brush";
    this.key = "b";
    this.cursor = "none";
    this.stroke = null;
    this.at = null; // cursor position in image px
  }
  get value() {
    return this.editor.state.classId;
  }
  get radius() {
    return Math.max(0.5, this.editor.state.size / 2);
  }
  down(p) {
    this.stroke = new StrokeCommand(this.editor.mask, this.value, this.radius);
    this.stroke.addSample(p[0], p[1], stampSegment);
    this.at = p;
    this.editor.view.request();
  }
  move(points) {
    this.at = points[points.length - 1];
    if (this.stroke) for (const p of points) this.stroke.addSample(p[0], p[1], stampSegment);
    this.editor.view.request();
  }
  up() {
    if (!this.stroke) return;
    const s = this.stroke;
    this.stroke = null;
    s.end();
    this.editor.history.push(s);
  }
  cancel() {
    if (this.stroke) this.up();
  }
  leave() {
    this.at = null;
    this.editor.view.request();
  }
  beforeRender() {
    this.stroke?.flush();
  }
  overlay(ctx, view) {
    if (!this.at) return;
    const [x, y] = view.toScreen(this.at[0], this.at[1]);
    const r = Math.max(1.5, this.radius * view.scale);
    ctx.lineWidth = 1.5;
    ctx.strokeStyle = "rgba(0,0,0,0.8)";
    ctx.beginPath();
    ctx.arc(x, y, r + 1, 0, Math.PI * 2);
    ctx.stroke();
    ctx.strokeStyle = this.value === 0 ? "rgba(255,255,255,0.95)" : this.editor.classCss(this.value);
    ctx.beginPath();
    ctx.arc(x, y, r, 0, Math.PI * 2);
    ctx.stroke();
  }
}
