// Flood fill: click a pixel to give the active class to the connected region of the *photo*
// whose colour is within the tolerance of the clicked pixel (max channel difference).

import { floodFill } from "../paint/mask.js";
import { PatchCommand } from "../paint/history.js";

export class FloodTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "flood";
    this.label = "Flood fill";
    this.key = "f";
    this.cursor = "cell";
    this.busy = false;
  }
  async down(p) {
    if (this.busy) return;
    this.busy = true;
    const ed = this.editor;
    try {
      ed.setStatus("Flood fill: reading image colours…");
      const rgba = await ed.photoRgba();
      const scratch = ed.scratch();
      const value = ed.state.classId;
      const tol = ed.state.tolerance;
      let count = 0;
      ed.history.execute(
        new PatchCommand("flood fill", ed.mask, (patch) => {
          const r = floodFill(ed.mask, patch, rgba, scratch, p[0], p[1], tol, value);
          count = r ? r.count : 0;
          return r ? r.rect : null;
        }),
      );
      ed.setStatus(`Flood fill: ${count.toLocaleString()} pixels`);
    } catch (e) {
      ed.setStatus(`Flood fill failed: ${e.message}`);
    } finally {
      this.busy = false;
    }
  }
  move() {}
  up() {}
  leave() {}
  overlay() {}
}
