// Single-channel mask PNGs.
//
// How masks travel: the editor keeps the mask as raw class ids, one byte per pixel
// (Uint8Array, row-major, image resolution). The coloured canvas the annotator sees is only a
// view of those ids (colour = taxonomy.rgb[id]). For upload we do NOT read the coloured canvas
// back (anti-aliasing and colour management would corrupt ids); we encode the id bytes
// directly as an 8-bit greyscale PNG (colour type 0), grey value = raw class id, 0 = unpainted.
// canvas.toBlob('image/png') always writes RGB(A), which the backend rejects as
// "not single channel", so the PNG container is written here and the zlib stream comes from
// the browser's native CompressionStream('deflate'). Rows use PNG filter 2 ("Up"), which turns
// the large constant areas of a mask into zero runs that deflate very well.
//
// For reading, greyscale PNGs from the API (mask versions, prefill, render) are decoded with
// createImageBitmap(colorSpaceConversion: 'none') and the red channel is taken as the id; any
// RGB-coloured mask would instead need a colour -> id lookup (see idsFromRgba).

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

function crc32(bytes, crc = 0xffffffff) {
  for (let i = 0; i < bytes.length; i++) crc = CRC_TABLE[(crc ^ bytes[i]) & 0xff] ^ (crc >>> 8);
  return crc;
}

function chunk(type, data) {
  const out = new Uint8Array(12 + data.length);
  const dv = new DataView(out.buffer);
  dv.setUint32(0, data.length);
  for (let i = 0; i < 4; i++) out[4 + i] = type.charCodeAt(i);
  out.set(data, 8);
  const crc = crc32(out.subarray(4, 8 + data.length)) ^ 0xffffffff;
  dv.setUint32(8 + data.length, crc >>> 0);
  return out;
}

/** Encode ids: Uint8Array(width*height) as an 8-bit greyscale PNG Blob. */
export async function encodeGreyPng(ids, width, height) {
  if (ids.length !== width * height) throw new Error(`mask has ${ids.length} bytes, expected ${width}x${height}`);
  const stride = width + 1;
  const raw = new Uint8Array(stride * height);
  // Row 0 with filter None, the rest with filter Up (byte - byte above, mod 256).
  raw[0] = 0;
  raw.set(ids.subarray(0, width), 1);
  for (let y = 1; y < height; y++) {
    const o = y * stride;
    raw[o] = 2;
    const cur = y * width;
    const prev = cur - width;
    for (let x = 0; x < width; x++) raw[o + 1 + x] = (ids[cur + x] - ids[prev + x]) & 0xff;
  }
  const zipped = new Uint8Array(
    await new Response(new Blob([raw]).stream().pipeThrough(new CompressionStream("deflate"))).arrayBuffer(),
  );
  const ihdr = new Uint8Array(13);
  const dv = new DataView(ihdr.buffer);
  dv.setUint32(0, width);
  dv.setUint32(4, height);
  ihdr[8] = 8; // bit depth
  ihdr[9] = 0; // colour type: greyscale
  ihdr[10] = 0;
  ihdr[11] = 0;
  ihdr[12] = 0;
  const sig = new Uint8Array([137, 80, 78, 71, 13, 10, 26, 10]);
  return new Blob([sig, chunk("IHDR", ihdr), chunk("IDAT", zipped), chunk("IEND", new Uint8Array(0))], {
    type: "image/png",
  });
}

/** Decode an image Blob to RGBA pixels at its natural size. */
export async function decodeRgba(blob) {
  const bmp = await createImageBitmap(blob, { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  const c = new OffscreenCanvas(bmp.width, bmp.height);
  const ctx = c.getContext("2d", { willReadFrequently: true });
  ctx.drawImage(bmp, 0, 0);
  const data = ctx.getImageData(0, 0, bmp.width, bmp.height).data;
  const out = { width: bmp.width, height: bmp.height, data };
  bmp.close();
  return out;
}

/**
 * Decode an 8-bit greyscale, non-interlaced PNG directly (native inflate via
 * DecompressionStream + the five PNG row filters); returns null for any other PNG flavour.
 * Much cheaper than drawing to a canvas and reading back 4 bytes per pixel.
 */
export async function decodeGreyPngFast(buf) {
  const b = new Uint8Array(buf);
  const dv = new DataView(b.buffer, b.byteOffset, b.byteLength);
  if (b.length < 33 || dv.getUint32(0) !== 0x89504e47) return null;
  let off = 8;
  let width = 0, height = 0;
  const idat = [];
  while (off + 8 <= b.length) {
    const len = dv.getUint32(off);
    const type = String.fromCharCode(b[off + 4], b[off + 5], b[off + 6], b[off + 7]);
    const data = b.subarray(off + 8, off + 8 + len);
    if (type === "IHDR") {
      width = dv.getUint32(off + 8);
      height = dv.getUint32(off + 12);
      const depth = data[8], ctype = data[9], interlace = data[12];
      if (depth !== 8 || ctype !== 0 || interlace !== 0) return null;
    } else if (type === "IDAT") idat.push(data);
    else if (type === "IEND") break;
    off += 12 + len;
  }
  if (!width || !idat.length) return null;
  const raw = new Uint8Array(await new Response(new Blob(idat).stream().pipeThrough(new DecompressionStream("deflate"))).arrayBuffer());
  const stride = width + 1;
  if (raw.length < stride * height) throw new Error(`PNG data too short: ${raw.length} < ${stride * height}`);
  const ids = new Uint8Array(width * height);
  for (let y = 0; y < height; y++) {
    const f = raw[y * stride];
    const src = y * stride + 1;
    const o = y * width;
    const p = o - width; // previous output row
    switch (f) {
      case 0:
        ids.set(raw.subarray(src, src + width), o);
        break;
      case 1:
        for (let x = 0; x < width; x++) ids[o + x] = (raw[src + x] + (x ? ids[o + x - 1] : 0)) & 255;
        break;
      case 2:
        if (y === 0) ids.set(raw.subarray(src, src + width), o);
        else for (let x = 0; x < width; x++) ids[o + x] = (raw[src + x] + ids[p + x]) & 255;
        break;
      case 3:
        for (let x = 0; x < width; x++) ids[o + x] = (raw[src + x] + (((x ? ids[o + x - 1] : 0) + (y ? ids[p + x] : 0)) >> 1)) & 255;
        break;
      case 4:
        for (let x = 0; x < width; x++) {
          const a = x ? ids[o + x - 1] : 0, bb = y ? ids[p + x] : 0, c = x && y ? ids[p + x - 1] : 0;
          const pa = Math.abs(bb - c), pb = Math.abs(a - c), pc = Math.abs(a + bb - 2 * c);
          ids[o + x] = (raw[src + x] + (pa <= pb && pa <= pc ? a : pb <= pc ? bb : c)) & 255;
        }
        break;
      default:
        throw new Error(`PNG row ${y} has unknown filter type ${f}`);
    }
  }
  return { width, height, ids };
}

/** Decode a greyscale id PNG to {width, height, ids: Uint8Array}. */
export async function decodeIdPng(blob) {
  const fast = await decodeGreyPngFast(await blob.arrayBuffer());
  if (fast) return fast;
  const { width, height, data } = await decodeRgba(blob);
  const ids = new Uint8Array(width * height);
  for (let i = 0, j = 0; i < ids.length; i++, j += 4) ids[i] = data[j];
  return { width, height, ids };
}

/**
 * Convert an RGB-coloured mask (RGBA bytes) to ids by exact palette lookup; pixels with
 * alpha < 128 or a colour not in the palette become 0. classes: [{id, rgb:[r,g,b]}].
 */
export function idsFromRgba(data, classes) {
  const map = new Map();
  for (const c of classes) map.set((c.rgb[0] << 16) | (c.rgb[1] << 8) | c.rgb[2], c.id);
  const ids = new Uint8Array(data.length / 4);
  for (let i = 0, j = 0; i < ids.length; i++, j += 4) {
    if (data[j + 3] < 128) continue;
    ids[i] = map.get((data[j] << 16) | (data[j + 1] << 8) | data[j + 2]) || 0;
  }
  return ids;
}

/** Nearest-neighbour resample of ids to a new size (backend may send a downscaled render). */
export function resizeIds(ids, w, h, W, H) {
  if (w === W && h === H) return ids;
  const out = new Uint8Array(W * H);
  const xs = new Uint32Array(W);
  for (let x = 0; x < W; x++) xs[x] = Math.min(w - 1, Math.floor(((x + 0.5) * w) / W));
  for (let y = 0; y < H; y++) {
    const sy = Math.min(h - 1, Math.floor(((y + 0.5) * h) / H)) * w;
    const o = y * W;
    for (let x = 0; x < W; x++) out[o + x] = ids[sy + xs[x]];
  }
  return out;
}

let worker = null;
let workerFailed = false;
let nextId = 1;
const pending = new Map();

/**
 * encodeGreyPng in a module worker (a snapshot of `ids` is copied and transferred, so the
 * caller may keep editing). Falls back to the main thread where workers are unavailable.
 */
export async function encodeGreyPngOffThread(ids, width, height) {
  if (!workerFailed && typeof Worker !== "undefined") {
    try {
      if (!worker) {
        worker = new Worker(new URL("./png-worker.js", import.meta.url), { type: "module" });
        worker.onmessage = (e) => {
          const p = pending.get(e.data.id);
          pending.delete(e.data.id);
          if (p) e.data.error ? p.reject(new Error(e.data.error)) : p.resolve(e.data.blob);
        };
        worker.onerror = (e) => {
          workerFailed = true;
          for (const p of pending.values()) p.reject(new Error(`PNG worker failed: ${e.message}`));
          pending.clear();
          worker = null;
        };
      }
      const id = nextId++;
      const copy = ids.slice();
      const done = new Promise((resolve, reject) => pending.set(id, { resolve, reject }));
      worker.postMessage({ id, ids: copy, width, height }, [copy.buffer]);
      return await done;
    } catch (e) {
      if (!workerFailed) throw e;
    }
  }
  return encodeGreyPng(ids, width, height);
}

