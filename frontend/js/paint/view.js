// The painting viewport: three stacked canvases (photo, mask, overlay) showing a scaled,
// panned window onto image-resolution sources. The photo layer is redrawn only on pan/zoom;
// mask edits redraw only the screen rectangle they touched (clip + nearest-neighbour, image
// smoothing off), so a brush stroke on a 20-megapixel mask costs a few small blits per frame.

import { Signal } from "../core/bus.js";

export class View {
  constructor(container, width, height) {
    this.container = container;
    this.width = width;
    this.height = height;
    this.scale = 1;
    this.tx = 0;
    this.ty = 0;
    this.minScale = 0.01;
    this.maxScale = 32;
    container.classList.add("viewport");
    this.photoCanvas = this._layer("layer-photo");
    this.maskCanvas = this._layer("layer-mask");
    this.overlay = this._layer("layer-overlay");
    this.overlay.tabIndex = 0;
    this.overlay.setAttribute("role", "img");
    this.overlay.setAttribute("aria-label", "Image with mask; use the tools to paint");
    this.photo = null;
    this.mask = null;
    this._full = true;
    this._maskRect = null;
    this._pending = false;
    this.overlayPainters = [];
    this.rendered = new Signal(); // dispatch(ms) after each frame
    this.transformChanged = new Signal();
    this.frames = 0;
    this._ro = new ResizeObserver(() => this.resize());
    this._ro.observe(container);
    this.resize();
  }

  _layer(cls) {
    const c = document.createElement("canvas");
    c.className = `layer ${cls}`;
    this.container.appendChild(c);
    return c;
  }

  destroy() {
    this._ro.disconnect();
    this.container.replaceChildren();
  }

  setPhoto(source) {
    this.photo = source;
    this.pyramid = [];
    this.invalidate();
    // after the first paint, when the page is idle: do not compete with opening the frame
    const start = () => this.photo === source && this._buildPyramid(source);
    if (window.requestIdleCallback) requestIdleCallback(start, { timeout: 2000 });
    else setTimeout(start, 500);
  }

  /**
   * Half, quarter, eighth... resolution copies of the photo, made off the main thread after
   * the first paint; zoomed-out redraws sample the smallest level that still has at least one
   * source pixel per screen pixel, which keeps pan/zoom smooth on 20-megapixel images.
   */
  async _buildPyramid(source) {
    const levels = [];
    let w = source.width, h = source.height, src = source;
    try {
      while (w > 1024 && h > 1024) {
        w = Math.round(w / 2);
        h = Math.round(h / 2);
        src = await createImageBitmap(src, { resizeWidth: w, resizeHeight: h, resizeQuality: "medium" });
        if (this.photo !== source) return;
        levels.push({ factor: source.width / w, img: src });
      }
    } catch {
      return; // no resize support: draw the full image
    }
    this.pyramid = levels;
  }

  _photoLevel() {
    const px = this.scale * (this.dpr || 1); // screen pixels per image pixel
    let best = this.photo;
    for (const l of this.pyramid || []) if (px * l.factor <= 1) best = l.img;
    return best;
  }

  setMask(mask) {
    this.mask = mask;
    this._unsubMask?.();
    this._unsubMask = mask.changed.add((r) => this.invalidateMask(r));
    this.invalidate();
  }

  setOpacity(a) {
    this.maskCanvas.style.opacity = String(a);
  }

  resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, this.container.clientWidth);
    const h = Math.max(1, this.container.clientHeight);
    this.cssW = w;
    this.cssH = h;
    this.dpr = dpr;
    for (const c of [this.photoCanvas, this.maskCanvas, this.overlay]) {
      c.width = Math.round(w * dpr);
      c.height = Math.round(h * dpr);
      c.style.width = `${w}px`;
      c.style.height = `${h}px`;
    }
    // until the person zooms or pans, the image stays fitted: the page's layout settles after
    // the first resize (a 768 px tablet opened a frame at 307 % instead of fit, issue 40)
    if (!this._fitted || !this._moved) this.fit();
    this.invalidate();
  }

  fit() {
    const s = Math.min(this.cssW / this.width, this.cssH / this.height) * 0.98;
    this.scale = s;
    this.tx = (this.cssW - this.width * s) / 2;
    this.ty = (this.cssH - this.height * s) / 2;
    this._fitted = this.cssW > 1;
    this._moved = false;
    this.invalidate();
    this.transformChanged.dispatch();
  }

  /** Zoom by `factor` keeping the screen point (sx, sy) (CSS px) fixed. */
  zoomAt(factor, sx, sy) {
    const s = Math.min(this.maxScale, Math.max(this.minScale, this.scale * factor));
    const f = s / this.scale;
    this.tx = sx - (sx - this.tx) * f;
    this.ty = sy - (sy - this.ty) * f;
    this.scale = s;
    this._moved = true;
    this.invalidate();
    this.transformChanged.dispatch();
  }

  panBy(dx, dy) {
    this.tx += dx;
    this.ty += dy;
    this._moved = true;
    this.invalidate();
    this.transformChanged.dispatch();
  }

  /** Client (event) coordinates -> image pixel coordinates (floats). */
  toImage(clientX, clientY) {
    const r = this.overlay.getBoundingClientRect();
    return [(clientX - r.left - this.tx) / this.scale, (clientY - r.top - this.ty) / this.scale];
  }

  /** Image pixel coordinates -> CSS px in the viewport. */
  toScreen(x, y) {
    return [x * this.scale + this.tx, y * this.scale + this.ty];
  }

  invalidate() {
    this._full = true;
    this.request();
  }

  invalidateMask(r) {
    if (this._full) return;
    const m = this._maskRect;
    this._maskRect = m ? { x0: Math.min(m.x0, r.x0), y0: Math.min(m.y0, r.y0), x1: Math.max(m.x1, r.x1), y1: Math.max(m.y1, r.y1) } : { ...r };
    this.request();
  }

  request() {
    if (this._pending) return;
    this._pending = true;
    requestAnimationFrame(() => this.render());
  }

  _applyTransform(ctx) {
    const d = this.dpr;
    ctx.setTransform(this.scale * d, 0, 0, this.scale * d, this.tx * d, this.ty * d);
  }

  render() {
    const t0 = performance.now();
    this.beforeRender?.(); // may add dirty rects; request() is a no-op while pending
    this._pending = false;
    const full = this._full;
    if (full) {
      const pc = this.photoCanvas.getContext("2d");
      pc.setTransform(1, 0, 0, 1, 0, 0);
      pc.fillStyle = "#2b2f36";
      pc.fillRect(0, 0, this.photoCanvas.width, this.photoCanvas.height);
      if (this.photo) {
        this._applyTransform(pc);
        pc.imageSmoothingEnabled = this.scale < 2;
        pc.imageSmoothingQuality = "medium";
        pc.drawImage(this._photoLevel(), 0, 0, this.width, this.height);
      }
    }
    const mc = this.maskCanvas.getContext("2d");
    if (this.mask && (full || this._maskRect)) {
      mc.setTransform(1, 0, 0, 1, 0, 0);
      mc.imageSmoothingEnabled = false;
      if (full) {
        mc.clearRect(0, 0, this.maskCanvas.width, this.maskCanvas.height);
        this._applyTransform(mc);
        mc.drawImage(this.mask.canvas, 0, 0);
      } else {
        const r = this._maskRect;
        const d = this.dpr;
        const X0 = Math.floor((r.x0 * this.scale + this.tx) * d) - 1;
        const Y0 = Math.floor((r.y0 * this.scale + this.ty) * d) - 1;
        const X1 = Math.ceil((r.x1 * this.scale + this.tx) * d) + 1;
        const Y1 = Math.ceil((r.y1 * this.scale + this.ty) * d) + 1;
        mc.save();
        mc.beginPath();
        mc.rect(X0, Y0, X1 - X0, Y1 - Y0);
        mc.clip();
        mc.clearRect(X0, Y0, X1 - X0, Y1 - Y0);
        this._applyTransform(mc);
        mc.drawImage(this.mask.canvas, 0, 0);
        mc.restore();
      }
    }
    this._full = false;
    this._maskRect = null;
    const oc = this.overlay.getContext("2d");
    oc.setTransform(1, 0, 0, 1, 0, 0);
    oc.clearRect(0, 0, this.overlay.width, this.overlay.height);
    oc.setTransform(this.dpr, 0, 0, this.dpr, 0, 0);
    for (const p of this.overlayPainters) p(oc, this);
    this.frames++;
    this.rendered.dispatch(performance.now() - t0);
  }
}
