// The mask model: raw class ids at image resolution plus an offscreen colour canvas that
// mirrors them (what the view scales onto the screen). All edits go through a TilePatch so
// undo/redo restore only the 256x256 tiles a command touched (dirty-rect patches, never a
// full copy of the 20-megapixel mask).

import { Signal } from "../core/bus.js";

export const TILE = 256;

/**
 * Packed RGBA per raw id (little-endian, as an Int32Array: signed values stay small integers
 * in V8, which makes the recolour loop ~4x faster than with Uint32); 0 (unpainted) is
 * transparent, ids outside the taxonomy are grey.
 */
export function buildLut(classes) {
  const lut = new Int32Array(256);
  for (let i = 1; i < 256; i++) lut[i] = 0xff808080 | 0;
  lut[0] = 0;
  for (const c of classes) {
    const [r, g, b] = c.rgb;
    lut[c.id] = (255 << 24) | (b << 16) | (g << 8) | r;
  }
  return lut;
}

export class MaskModel {
  /**
   * width, height: image size in pixels; classes: taxonomy rows [{id, name, rgb}].
   */
  constructor(width, height, classes) {
    this.width = width;
    this.height = height;
    this.ids = new Uint8Array(width * height);
    this.lut = buildLut(classes);
    this.baseLut = this.lut.slice(); // the taxonomy colours; `lut` also applies hidden classes
    this.style = "fill"; // or "outline": class borders opaque, insides faint (tell dark red from red)
    this.hidden = new Set();
    this.canvas = document.createElement("canvas");
    this.canvas.width = width;
    this.canvas.height = height;
    this.ctx = this.canvas.getContext("2d");
    this.painted = 0; // number of non-zero pixels, kept up to date incrementally
    this.changed = new Signal(); // dispatch({x0, y0, x1, y1}) in image pixels, exclusive ends
    this.tilesX = Math.ceil(width / TILE);
    this.tilesY = Math.ceil(height / TILE);
  }

  get paintedShare() {
    return this.painted / (this.width * this.height);
  }

  /** Replace every id (no undo); used when a saved version is loaded. */
  setAll(ids) {
    if (ids.length !== this.ids.length) throw new Error("mask size mismatch");
    this.ids.set(ids);
    this.painted = this.refresh(0, 0, this.width, this.height);
  }

  /**
   * Load a mask decoded and coloured elsewhere (see decodeMaskOffThread): ids (W*H raw ids),
   * rgba (their colours, W*H*4) and the painted count. No undo.
   */
  adopt(ids, rgba, painted) {
    if (ids.length !== this.ids.length || rgba.length !== 4 * this.ids.length) throw new Error("mask size mismatch");
    this.ids.set(ids);
    this.painted = painted;
    this.ctx.putImageData(new ImageData(rgba, this.width, this.height), 0, 0);
    this.changed.dispatch({ x0: 0, y0: 0, x1: this.width, y1: this.height });
  }

  /** Hide / show classes in the colour layer (the ids are untouched). */
  setHidden(ids) {
    this.hidden = new Set(ids);
    this.lut = this.baseLut.slice();
    for (const id of this.hidden) this.lut[id] = 0;
    this.refresh(0, 0, this.width, this.height);
  }

  /** "fill" (default) or "outline": borders between classes opaque, insides at ~20 %. */
  setStyle(style) {
    this.style = style === "outline" ? "outline" : "fill";
    this.refresh(0, 0, this.width, this.height);
  }

  /**
   * Recolour the canvas in a rectangle (exclusive ends) from the ids and notify views.
   * Returns the number of painted (non-zero) pixels in the rectangle.
   */
  refresh(x0, y0, x1, y1) {
    if (this.style === "outline") return this._refreshOutline(x0, y0, x1, y1);
    x0 = Math.max(0, Math.floor(x0));
    y0 = Math.max(0, Math.floor(y0));
    x1 = Math.min(this.width, Math.ceil(x1));
    y1 = Math.min(this.height, Math.ceil(y1));
    const rw = x1 - x0;
    const rh = y1 - y0;
    if (rw <= 0 || rh <= 0) return 0;
    const img = new ImageData(rw, rh);
    const out = new Int32Array(img.data.buffer);
    const { ids, lut, width } = this;
    let n = 0;
    for (let y = 0; y < rh; y++) {
      const s = (y0 + y) * width + x0;
      const d = y * rw;
      for (let x = 0; x < rw; x++) {
        const v = ids[s + x];
        out[d + x] = lut[v];
        n += v !== 0 ? 1 : 0;
      }
    }
    this.ctx.putImageData(img, x0, y0);
    this.changed.dispatch({ x0, y0, x1, y1 });
    return n;
  }

  _refreshOutline(x0, y0, x1, y1) {
    // a pixel's border state depends on its neighbours: widen the rectangle by one
    x0 = Math.max(0, Math.floor(x0) - 1);
    y0 = Math.max(0, Math.floor(y0) - 1);
    x1 = Math.min(this.width, Math.ceil(x1) + 1);
    y1 = Math.min(this.height, Math.ceil(y1) + 1);
    const rw = x1 - x0;
    const rh = y1 - y0;
    if (rw <= 0 || rh <= 0) return 0;
    const img = new ImageData(rw, rh);
    const out = new Int32Array(img.data.buffer);
    const { ids, lut, width, height } = this;
    const faint = 0x33 << 24;
    let n = 0;
    for (let y = 0; y < rh; y++) {
      const yy = y0 + y;
      const s = yy * width + x0;
      const d = y * rw;
      for (let x = 0; x < rw; x++) {
        const i = s + x;
        const v = ids[i];
        if (v === 0) continue;
        n++;
        const xx = x0 + x;
        const edge = (xx > 0 && ids[i - 1] !== v) || (xx < width - 1 && ids[i + 1] !== v) || (yy > 0 && ids[i - width] !== v) || (yy < height - 1 && ids[i + width] !== v);
        const c = lut[v];
        out[d + x] = edge || c === 0 ? c : (c & 0x00ffffff) | faint;
      }
    }
    this.ctx.putImageData(img, x0, y0);
    this.changed.dispatch({ x0, y0, x1, y1 });
    // the count covers the widened rectangle; callers that need the exact painted number of
    // the asked rectangle (setAll) recount below
    return n;
  }

  readTile(tx, ty) {
    const x0 = tx * TILE;
    const y0 = ty * TILE;
    const w = Math.min(TILE, this.width - x0);
    const h = Math.min(TILE, this.height - y0);
    const out = new Uint8Array(w * h);
    for (let y = 0; y < h; y++) out.set(this.ids.subarray((y0 + y) * this.width + x0, (y0 + y) * this.width + x0 + w), y * w);
    return out;
  }

  writeTile(tx, ty, data) {
    const x0 = tx * TILE;
    const y0 = ty * TILE;
    const w = Math.min(TILE, this.width - x0);
    const h = Math.min(TILE, this.height - y0);
    let delta = 0;
    for (let y = 0; y < h; y++) {
      const o = (y0 + y) * this.width + x0;
      for (let x = 0; x < w; x++) {
        const before = this.ids[o + x];
        const after = data[y * w + x];
        if ((before !== 0) !== (after !== 0)) delta += after !== 0 ? 1 : -1;
        this.ids[o + x] = after;
      }
    }
    this.painted += delta;
    return [x0, y0, x0 + w, y0 + h];
  }
}

/**
 * Records the tiles an edit touches. Call touch(rect) BEFORE changing ids in rect; call
 * finish() when the edit is complete. undo()/redo() swap the saved tiles back in.
 */
export class TilePatch {
  constructor(mask) {
    this.mask = mask;
    this.before = new Map(); // tile key -> Uint8Array
    this.after = null;
  }

  touch(x0, y0, x1, y1) {
    const m = this.mask;
    const tx0 = Math.max(0, Math.floor(x0 / TILE));
    const ty0 = Math.max(0, Math.floor(y0 / TILE));
    const tx1 = Math.min(m.tilesX - 1, Math.floor((x1 - 1) / TILE));
    const ty1 = Math.min(m.tilesY - 1, Math.floor((y1 - 1) / TILE));
    for (let ty = ty0; ty <= ty1; ty++) {
      for (let tx = tx0; tx <= tx1; tx++) {
        const key = ty * m.tilesX + tx;
        if (!this.before.has(key)) this.before.set(key, m.readTile(tx, ty));
      }
    }
  }

  finish() {
    const m = this.mask;
    this.after = new Map();
    for (const key of this.before.keys()) {
      this.after.set(key, m.readTile(key % m.tilesX, Math.floor(key / m.tilesX)));
    }
  }

  get bytes() {
    let n = 0;
    for (const v of this.before.values()) n += v.length;
    return this.after ? 2 * n : n;
  }

  get isEmpty() {
    if (!this.after) return this.before.size === 0;
    for (const [k, a] of this.before) {
      const b = this.after.get(k);
      for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
    }
    return true;
  }

  _apply(tiles) {
    const m = this.mask;
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (const [key, data] of tiles) {
      const r = m.writeTile(key % m.tilesX, Math.floor(key / m.tilesX), data);
      x0 = Math.min(x0, r[0]); y0 = Math.min(y0, r[1]); x1 = Math.max(x1, r[2]); y1 = Math.max(y1, r[3]);
    }
    if (x1 > x0) m.refresh(x0, y0, x1, y1);
  }

  undo() {
    this._apply(this.before);
  }

  redo() {
    this._apply(this.after);
  }
}

/**
 * Rasterise a round-capped segment (a "capsule") of radius r into ids with value v.
 * Pixel centres (x + 0.5, y + 0.5) within distance r of the segment are set, so fast pointer
 * samples far apart still give a gap-free stroke. Returns the dirty rect or null.
 */
export function stampSegment(mask, patch, ax, ay, bx, by, r, v) {
  const x0 = Math.max(0, Math.floor(Math.min(ax, bx) - r));
  const y0 = Math.max(0, Math.floor(Math.min(ay, by) - r));
  const x1 = Math.min(mask.width, Math.ceil(Math.max(ax, bx) + r) + 1);
  const y1 = Math.min(mask.height, Math.ceil(Math.max(ay, by) + r) + 1);
  if (x1 <= x0 || y1 <= y0) return null;
  patch.touch(x0, y0, x1, y1);
  const dx = bx - ax;
  const dy = by - ay;
  const L2 = dx * dx + dy * dy;
  const r2 = r * r;
  const { ids, width } = mask;
  let delta = 0;
  for (let y = y0; y < y1; y++) {
    const py = y + 0.5;
    const row = y * width;
    for (let x = x0; x < x1; x++) {
      const px = x + 0.5;
      let t = L2 > 0 ? ((px - ax) * dx + (py - ay) * dy) / L2 : 0;
      t = t < 0 ? 0 : t > 1 ? 1 : t;
      const qx = ax + t * dx - px;
      const qy = ay + t * dy - py;
      if (qx * qx + qy * qy <= r2) {
        const i = row + x;
        const old = ids[i];
        if (old !== v) {
          if (old === 0) delta++;
          else if (v === 0) delta--;
          ids[i] = v;
        }
      }
    }
  }
  mask.painted += delta;
  return [x0, y0, x1, y1];
}

/** Fill a polygon (image-pixel vertices [[x, y], ...], even-odd rule) with value v. */
export function fillPolygon(mask, patch, pts, v) {
  if (pts.length < 3) return null;
  let minY = Infinity, maxY = -Infinity, minX = Infinity, maxX = -Infinity;
  for (const [x, y] of pts) {
    minX = Math.min(minX, x); maxX = Math.max(maxX, x); minY = Math.min(minY, y); maxY = Math.max(maxY, y);
  }
  const y0 = Math.max(0, Math.floor(minY));
  const y1 = Math.min(mask.height, Math.ceil(maxY) + 1);
  const x0 = Math.max(0, Math.floor(minX));
  const x1 = Math.min(mask.width, Math.ceil(maxX) + 1);
  if (x1 <= x0 || y1 <= y0) return null;
  patch.touch(x0, y0, x1, y1);
  const { ids, width } = mask;
  const n = pts.length;
  const xs = [];
  let delta = 0;
  for (let y = y0; y < y1; y++) {
    const py = y + 0.5;
    xs.length = 0;
    for (let i = 0, j = n - 1; i < n; j = i++) {
      const [xi, yi] = pts[i];
      const [xj, yj] = pts[j];
      if ((yi > py) !== (yj > py)) xs.push(xi + ((py - yi) * (xj - xi)) / (yj - yi));
    }
    xs.sort((a, b) => a - b);
    for (let k = 0; k + 1 < xs.length; k += 2) {
      const a = Math.max(x0, Math.ceil(xs[k] - 0.5));
      const b = Math.min(x1 - 1, Math.ceil(xs[k + 1] - 0.5) - 1);
      const row = y * width;
      for (let x = a; x <= b; x++) {
        const old = ids[row + x];
        if (old !== v) {
          if (old === 0) delta++;
          else if (v === 0) delta--;
          ids[row + x] = v;
        }
      }
    }
  }
  mask.painted += delta;
  return [x0, y0, x1, y1];
}

/**
 * Flood fill the 4-connected region of pixels whose image colour is within `tol` (max channel
 * difference) of the seed pixel's colour. rgba: Uint8ClampedArray of the photo at mask size.
 * scratch: Uint8Array(width*height) reused between calls. Returns dirty rect and pixel count.
 */
export function floodFill(mask, patch, rgba, scratch, sx, sy, tol, v) {
  const { width, height, ids } = mask;
  sx = Math.floor(sx);
  sy = Math.floor(sy);
  if (sx < 0 || sy < 0 || sx >= width || sy >= height) return null;
  scratch.fill(0);
  const s = (sy * width + sx) * 4;
  const r0 = rgba[s], g0 = rgba[s + 1], b0 = rgba[s + 2];
  const similar = (i) => {
    const j = i * 4;
    return Math.abs(rgba[j] - r0) <= tol && Math.abs(rgba[j + 1] - g0) <= tol && Math.abs(rgba[j + 2] - b0) <= tol;
  };
  // Scanline fill with an explicit stack of seed indices.
  const stack = [sy * width + sx];
  let minX = sx, maxX = sx, minY = sy, maxY = sy, count = 0;
  while (stack.length) {
    const i = stack.pop();
    if (scratch[i]) continue;
    const y = (i / width) | 0;
    const row = y * width;
    let l = i - row;
    let r = l;
    while (l > 0 && !scratch[row + l - 1] && similar(row + l - 1)) l--;
    while (r < width - 1 && !scratch[row + r + 1] && similar(row + r + 1)) r++;
    for (let x = l; x <= r; x++) scratch[row + x] = 1;
    count += r - l + 1;
    if (l < minX) minX = l;
    if (r > maxX) maxX = r;
    if (y < minY) minY = y;
    if (y > maxY) maxY = y;
    for (const ny of [y - 1, y + 1]) {
      if (ny < 0 || ny >= height) continue;
      const nrow = ny * width;
      let inRun = false;
      for (let x = l; x <= r; x++) {
        const ok = !scratch[nrow + x] && similar(nrow + x);
        if (ok && !inRun) stack.push(nrow + x);
        inRun = ok;
      }
    }
  }
  patch.touch(minX, minY, maxX + 1, maxY + 1);
  let delta = 0;
  for (let y = minY; y <= maxY; y++) {
    const row = y * width;
    for (let x = minX; x <= maxX; x++) {
      const i = row + x;
      if (scratch[i] && ids[i] !== v) {
        if (ids[i] === 0) delta++;
        else if (v === 0) delta--;
        ids[i] = v;
      }
    }
  }
  mask.painted += delta;
  return { rect: [minX, minY, maxX + 1, maxY + 1], count };
}

let maskWorker = null;
let maskWorkerFailed = false;
let maskJob = 1;
const maskJobs = new Map();

/**
 * Decode a mask PNG (Blob) to raw ids at width x height and colour them with `lut` in a module
 * worker. Resolves {ids, rgba, painted}; falls back to the main thread without workers.
 */
export async function decodeMaskOffThread(blob, width, height, lut) {
  const png = await blob.arrayBuffer();
  if (!maskWorkerFailed && typeof Worker !== "undefined") {
    try {
      if (!maskWorker) {
        maskWorker = new Worker(new URL("./mask-worker.js", import.meta.url), { type: "module" });
        maskWorker.onmessage = (e) => {
          const p = maskJobs.get(e.data.id);
          maskJobs.delete(e.data.id);
          if (p) e.data.error ? p.reject(new Error(e.data.error)) : p.resolve(e.data);
        };
        maskWorker.onerror = (e) => {
          maskWorkerFailed = true;
          for (const p of maskJobs.values()) p.reject(new Error(`mask worker failed: ${e.message}`));
          maskJobs.clear();
          maskWorker = null;
        };
      }
      const id = maskJob++;
      const done = new Promise((resolve, reject) => maskJobs.set(id, { resolve, reject }));
      maskWorker.postMessage({ id, png, width, height, lut }, [png]);
      return await done;
    } catch (e) {
      if (!maskWorkerFailed) throw e;
    }
  }
  const { decodeIdPng, resizeIds } = await import("../core/png.js");
  const d = await decodeIdPng(blob);
  const ids = resizeIds(d.ids, d.width, d.height, width, height);
  const rgba = new Uint8ClampedArray(width * height * 4);
  const out = new Int32Array(rgba.buffer);
  let painted = 0;
  for (let i = 0; i < ids.length; i++) {
    out[i] = lut[ids[i]];
    painted += ids[i] !== 0 ? 1 : 0;
  }
  return { ids, rgba, painted };
}

