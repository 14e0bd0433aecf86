// Pan/zoom: drag to pan. Zoom is on the mouse wheel / trackpad pinch (exponential in the wheel
// delta, anchored at the cursor) and on the keyboard (+ / -, Home to fit) for every tool.
// Holding Space or the middle button pans temporarily from any tool.

export class PanTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "pan";
    this.label = "Pan";
    this.key = "h";
    this.cursor = "grab";
    this.last = null;
  }
  down(p, e) {
    this.last = [e.clientX, e.clientY];
  }
  move(points, e) {
    if (!this.last || !e) return;
    this.editor.view.panBy(e.clientX - this.last[0], e.clientY - this.last[1]);
    this.last = [e.clientX, e.clientY];
  }
  up() {
    this.last = null;
  }
  leave() {}
  overlay() {}
}

/** Install wheel zoom on the view's overlay canvas. */
export function installWheelZoom(view) {
  view.overlay.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      const r = view.overlay.getBoundingClientRect();
      const dy = e.deltaMode === 1 ? e.deltaY * 16 : e.deltaY;
      view.zoomAt(Math.exp(-dy * 0.0015), e.clientX - r.left, e.clientY - r.top);
    },
    { passive: false },
  );
}
