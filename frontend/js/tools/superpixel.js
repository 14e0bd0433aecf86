// Region fill on superpixels ("fill this region"): the photo is cut once into SLIC superpixels
// (k-means in CIELAB + position, at most ~0.5 MP working resolution, no model download); a
// click gives the active class to the superpixel under the cursor, a drag to every superpixel
// it crosses. One click or drag = one command on the undo stack.

import { PatchCommand } from "../paint/history.js";

const WORK_PIXELS = 500_000; // working resolution of the segmentation
const STEP = 14; // superpixel spacing at working resolution (px)
const COMPACTNESS = 12;
const ITERATIONS = 8;

function srgbToLab(r, g, b) {
  const lin = (c) => ((c /= 255) <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4);
  const R = lin(r), G = lin(g), B = lin(b);
  const f = (t) => (t > 0.008856 ? Math.cbrt(t) : 7.787 * t + 16 / 116);
  const X = f((0.4124 * R + 0.3576 * G + 0.1805 * B) / 0.95047);
  const Y = f(0.2126 * R + 0.7152 * G + 0.0722 * B);
  const Z = f((0.0193 * R + 0.1192 * G + 0.9505 * B) / 1.08883);
  return [116 * Y - 16, 500 * (X - Y), 200 * (Y - Z)];
}

/**
 * SLIC superpixels of an RGBA image (w x h): Int32Array of labels 0..k-1 (every label one
 * connected region after the final relabelling pass).
 */
export function slic(rgba, w, h, step = STEP, m = COMPACTNESS, iters = ITERATIONS) {
  const n = w * h;
  const L = new Float32Array(n), A = new Float32Array(n), B = new Float32Array(n);
  for (let i = 0; i < n; i++) {
    const [l, a, b] = srgbToLab(rgba[4 * i], rgba[4 * i + 1], rgba[4 * i + 2]);
    L[i] = l;
    A[i] = a;
    B[i] = b;
  }
  const cx = [], cy = [], cl = [], ca = [], cb = [];
  for (let y = step / 2; y < h; y += step)
    for (let x = step / 2; x < w; x += step) {
      const i = Math.floor(y) * w + Math.floor(x);
      cx.push(x); cy.push(y); cl.push(L[i]); ca.push(A[i]); cb.push(B[i]);
    }
  const k = cx.length;
  const label = new Int32Array(n).fill(-1);
  const dist = new Float32Array(n);
  const wS = (m / step) ** 2;
  for (let it = 0; it < iters; it++) {
    dist.fill(Infinity);
    for (let c = 0; c < k; c++) {
      const x0 = Math.max(0, Math.floor(cx[c] - step)), x1 = Math.min(w, Math.ceil(cx[c] + step));
      const y0 = Math.max(0, Math.floor(cy[c] - step)), y1 = Math.min(h, Math.ceil(cy[c] + step));
      for (let y = y0; y < y1; y++) {
        const dy = y - cy[c];
        for (let x = x0; x < x1; x++) {
          const i = y * w + x;
          const dl = L[i] - cl[c], da = A[i] - ca[c], db = B[i] - cb[c], dx = x - cx[c];
          const d = dl * dl + da * da + db * db + wS * (dx * dx + dy * dy);
          if (d < dist[i]) {
            dist[i] = d;
            label[i] = c;
          }
        }
      }
    }
    const sx = new Float64Array(k), sy = new Float64Array(k), sl = new Float64Array(k), sa = new Float64Array(k), sb = new Float64Array(k), cnt = new Float64Array(k);
    for (let y = 0, i = 0; y < h; y++)
      for (let x = 0; x < w; x++, i++) {
        const c = label[i];
        if (c < 0) continue;
        sx[c] += x; sy[c] += y; sl[c] += L[i]; sa[c] += A[i]; sb[c] += B[i]; cnt[c]++;
      }
    for (let c = 0; c < k; c++)
      if (cnt[c]) {
        cx[c] = sx[c] / cnt[c]; cy[c] = sy[c] / cnt[c]; cl[c] = sl[c] / cnt[c]; ca[c] = sa[c] / cnt[c]; cb[c] = sb[c] / cnt[c];
      }
  }
  // connected components of equal labels -> final ids (a k-means cluster may be split), and
  // SLIC's connectivity step: a fragment smaller than a quarter of a superpixel joins the
  // segment next to it (scanned in raster order, the one left of / above its first pixel).
  // Without it a click on a thin structure (a cable, a kerb) or a split cluster filled a
  // fragment of a few pixels (issue 40: 12 px where a superpixel is ~200).
  const out = new Int32Array(n).fill(-1);
  const stack = new Int32Array(n);
  const members = new Int32Array(n); // the pixels of the component being grown
  const minSize = Math.max(1, Math.floor((step * step) / 4));
  let next = 0;
  for (let s = 0; s < n; s++) {
    if (out[s] >= 0) continue;
    const lab = label[s];
    const sx0 = s % w;
    // the final id of an already labelled neighbour (left, else above)
    const adj = sx0 > 0 ? out[s - 1] : s >= w ? out[s - w] : -1;
    let top = 0;
    let size = 0;
    stack[top++] = s;
    out[s] = next;
    while (top) {
      const i = stack[--top];
      members[size++] = i;
      const x = i % w;
      const nb = [x > 0 ? i - 1 : -1, x < w - 1 ? i + 1 : -1, i - w, i + w];
      for (const j of nb) {
        if (j < 0 || j >= n || out[j] >= 0 || label[j] !== lab) continue;
        out[j] = next;
        stack[top++] = j;
      }
    }
    if (size < minSize && adj >= 0) {
      for (let t = 0; t < size; t++) out[members[t]] = adj;
    } else next++;
  }
  return { labels: out, count: next };
}

export class SuperpixelTool {
  constructor(editor) {
    this.editor = editor;
    this.name = "superpixel";
    this.label = "Region fill";
    this.key = "r";
    this.cursor = "copy";
    this.seg = null; // {labels, count, w, h}
    this.picked = null; // Set of superpixel ids of the current click / drag
    this.busy = false;
  }

  /** The segmentation of the current photo (computed on first use, then cached). */
  async segmentation() {
    const ed = this.editor;
    if (this.seg && this.seg.photo === ed.photo) return this.seg;
    ed.setStatus("Region fill: cutting the photo into superpixels…");
    await new Promise((r) => setTimeout(r, 0));
    const W = ed.mask.width, H = ed.mask.height;
    const f = Math.min(1, Math.sqrt(WORK_PIXELS / (W * H)));
    const w = Math.max(1, Math.round(W * f)), h = Math.max(1, Math.round(H * f));
    const c = new OffscreenCanvas(w, h);
    const g = c.getContext("2d", { willReadFrequently: true });
    g.drawImage(ed.photo, 0, 0, w, h);
    const t0 = performance.now();
    const { labels, count } = slic(g.getImageData(0, 0, w, h).data, w, h);
    this.seg = { labels, count, w, h, photo: ed.photo, ms: performance.now() - t0 };
    return this.seg;
  }

  /** Superpixel id under image point p (mask pixels). */
  at(p) {
    const { w, h, labels } = this.seg;
    const ed = this.editor;
    const x = Math.min(w - 1, Math.max(0, Math.floor((p[0] * w) / ed.mask.width)));
    const y = Math.min(h - 1, Math.max(0, Math.floor((p[1] * h) / ed.mask.height)));
    return labels[y * w + x];
  }

  async down(p) {
    if (this.busy || !this.editor.photo) return;
    this.busy = true;
    this.trail = [p];
    this.released = false;
    try {
      await this.segmentation();
      this.picked = new Set(this.trail.map((q) => this.at(q)));
      this.editor.view.request();
    } finally {
      this.busy = false;
    }
    if (this.released) this.up(); // the first click: released while the photo was being cut
  }

  move(points) {
    if (this.busy && this.trail) this.trail.push(...points);
    if (!this.picked || !this.seg) return;
    for (const p of points) this.picked.add(this.at(p));
    this.editor.view.request();
  }

  up() {
    if (this.busy) {
      this.released = true;
      return;
    }
    if (!this.picked || !this.seg) return;
    const picked = this.picked;
    this.picked = null;
    const ed = this.editor;
    const m = ed.mask;
    const { w, h, labels } = this.seg;
    const v = ed.state.classId;
    const W = m.width, H = m.height;
    // full-resolution lookup: which working pixel each mask column / row falls in
    const colOf = new Int32Array(W);
    for (let x = 0; x < W; x++) colOf[x] = Math.min(w - 1, Math.floor((x * w) / W));
    let n = 0;
    ed.history.execute(
      new PatchCommand(picked.size > 1 ? `region fill (${picked.size})` : "region fill", m, (patch) => {
        let x0 = W, y0 = H, x1 = 0, y1 = 0;
        for (let y = 0; y < H; y++) {
          const row = Math.min(h - 1, Math.floor((y * h) / H)) * w;
          for (let x = 0; x < W; x++) if (picked.has(labels[row + colOf[x]])) {
            if (x < x0) x0 = x;
            if (x >= x1) x1 = x + 1;
            if (y < y0) y0 = y;
            if (y >= y1) y1 = y + 1;
          }
        }
        if (x1 <= x0) return null;
        patch.touch(x0, y0, x1, y1);
        const ids = m.ids;
        let delta = 0;
        for (let y = y0; y < y1; y++) {
          const row = Math.min(h - 1, Math.floor((y * h) / H)) * w;
          for (let x = x0; x < x1; x++) {
            if (!picked.has(labels[row + colOf[x]])) continue;
            const i = y * W + x;
            const old = ids[i];
            if (old === v) continue;
            if (old === 0) delta++;
            else if (v === 0) delta--;
            ids[i] = v;
            n++;
          }
        }
        m.painted += delta;
        return [x0, y0, x1, y1];
      }),
    );
    ed.setStatus(`Region fill: ${n.toLocaleString()} pixels in ${picked.size} superpixel${picked.size > 1 ? "s" : ""} (${this.seg.count.toLocaleString()} in the photo, cut in ${Math.round(this.seg.ms)} ms)`);
  }

  cancel() {
    this.picked = null;
  }

  leave() {}

  overlay(ctx, view) {
    if (!this.picked || !this.seg) return;
    // outline the picked superpixels' working-resolution cells (cheap: bounding boxes)
    ctx.strokeStyle = this.editor.classCss(this.editor.state.classId);
    ctx.lineWidth = 2;
    ctx.setLineDash([4, 3]);
    const { w, h, labels } = this.seg;
    const sx = this.editor.mask.width / w, sy = this.editor.mask.height / h;
    const boxes = new Map();
    for (let y = 0, i = 0; y < h; y++)
      for (let x = 0; x < w; x++, i++) {
        const c = labels[i];
        if (!this.picked.has(c)) continue;
        const b = boxes.get(c) || [x, y, x, y];
        b[0] = Math.min(b[0], x); b[1] = Math.min(b[1], y); b[2] = Math.max(b[2], x); b[3] = Math.max(b[3], y);
        boxes.set(c, b);
      }
    for (const [x0, y0, x1, y1] of boxes.values()) {
      const [a, b] = view.toScreen(x0 * sx, y0 * sy);
      const [c, d] = view.toScreen((x1 + 1) * sx, (y1 + 1) * sy);
      ctx.strokeRect(a, b, c - a, d - b);
    }
    ctx.setLineDash([]);
  }
}
