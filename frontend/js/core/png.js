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
// For reading, the server stores and serves masks canonically (8-bit greyscale, no ancillary
// chunks); checkGreyPng refuses anything else before inflating a byte, then the browser's own
// decoder (createImageBitmap, colorSpaceConversion 'none') decodes it and the red channel is
// the id. There is no hand-written PNG decoder here (issue 24, finding 6: it read 16-bit and
// palette masks as empty, a short palette as 255, and inflated a 1 MB zlib bomb to 1 GB).

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

/** A mask PNG the page cannot read as stored (the message names what was found). */
export class MaskFormatError extends Error {
  constructor(msg) {
    super(msg);
    this.name = "MaskFormatError";
  }
}

export const MAX_MASK_PIXELS = 150e6; // a 150-megapixel mask: far above any survey photo

/**
 * Check the container of a mask PNG before anything is inflated (issue 24, finding 6): the
 * server stores masks canonically -- 8-bit greyscale, non-interlaced, no ancillary chunks --
 * so that is the one format read here; anything else (16-bit, palette, colour, truncated,
 * damaged, a zlib bomb) is refused with a MaskFormatError instead of being shown differently
 * from what the server lifts. Checks: signature, each chunk's CRC, IHDR first, IDAT present,
 * IEND last with nothing after it, the declared size within maxPixels (and equal to
 * expect {width, height} when given), and the compressed data no larger than deflate could
 * ever make the declared image (a 1 MB stream that inflates to 1 GB is refused unread).
 */
export function checkGreyPng(buf, { maxPixels = MAX_MASK_PIXELS, expect = null } = {}) {
  const b = buf instanceof Uint8Array ? buf : new Uint8Array(buf);
  const dv = new DataView(b.buffer, b.byteOffset, b.byteLength);
  const SIG = [137, 80, 78, 71, 13, 10, 26, 10];
  if (b.length < 8 || SIG.some((v, i) => b[i] !== v)) throw new MaskFormatError("mask is not a PNG file");
  let off = 8, width = 0, height = 0, idatBytes = 0, sawEnd = false;
  while (off < b.length) {
    if (off + 12 > b.length) throw new MaskFormatError(`mask PNG is truncated (chunk at byte ${off})`);
    const len = dv.getUint32(off);
    if (off + 12 + len > b.length) throw new MaskFormatError(`mask PNG is truncated (chunk at byte ${off} needs ${len} bytes)`);
    const type = String.fromCharCode(b[off + 4], b[off + 5], b[off + 6], b[off + 7]);
    const crc = (crc32(b.subarray(off + 4, off + 8 + len)) ^ 0xffffffff) >>> 0;
    if (crc !== dv.getUint32(off + 8 + len)) throw new MaskFormatError(`mask PNG is damaged (bad CRC of chunk ${type})`);
    if (off === 8 && type !== "IHDR") throw new MaskFormatError("mask PNG does not start with IHDR");
    if (type === "IHDR") {
      width = dv.getUint32(off + 8);
      height = dv.getUint32(off + 12);
      const depth = b[off + 16], ctype = b[off + 17], interlace = b[off + 20];
      if (depth !== 8 || ctype !== 0 || interlace !== 0) {
        const kind = { 0: "greyscale", 2: "RGB", 3: "palette", 4: "greyscale+alpha", 6: "RGBA" }[ctype] || `colour type ${ctype}`;
        throw new MaskFormatError(`mask PNG is ${depth}-bit ${kind}${interlace ? ", interlaced" : ""}; this page reads only the server's canonical 8-bit greyscale masks`);
      }
    } else if (type === "IDAT") idatBytes += len;
    else if (type === "IEND") {
      sawEnd = true;
      off += 12 + len;
      break;
    }
    off += 12 + len;
  }
  if (!sawEnd) throw new MaskFormatError("mask PNG is truncated (no IEND)");
  if (off !== b.length) throw new MaskFormatError(`mask PNG has ${b.length - off} bytes after IEND`);
  if (!width || !height || !idatBytes) throw new MaskFormatError("mask PNG has no image data");
  if (width * height > maxPixels) throw new MaskFormatError(`mask PNG declares ${width}x${height} pixels, more than ${maxPixels}`);
  if (expect && (expect.width !== width || expect.height !== height)) {
    throw new MaskFormatError(`mask PNG is ${width}x${height}, expected ${expect.width}x${expect.height}`);
  }
  const raw = (width + 1) * height; // filter byte + one byte per pixel and row
  if (idatBytes > raw + 5 * Math.ceil(raw / 16383) + 64) {
    throw new MaskFormatError(`mask PNG holds ${idatBytes} compressed bytes for a ${width}x${height} image (at most ${raw} could be needed): refused unread`);
  }
  return { width, height };
}

/**
 * Decode a canonical mask PNG (Blob or ArrayBuffer) to {width, height, ids: Uint8Array} with
 * the browser's own PNG decoder (createImageBitmap, no colour management, no premultiplied
 * alpha; the grey value is the red channel), after checkGreyPng. Throws MaskFormatError for
 * anything else, so a reviewer never accepts a mask the page shows differently.
 */
export async function decodeIdPng(src, opts = {}) {
  const buf = src instanceof Blob ? await src.arrayBuffer() : src;
  const { width, height } = checkGreyPng(buf, opts);
  let bmp;
  try {
    bmp = await createImageBitmap(new Blob([buf], { type: "image/png" }), { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  } catch (e) {
    throw new MaskFormatError(`mask PNG cannot be decoded (${e && e.message ? e.message : e})`);
  }
  try {
    if (bmp.width !== width || bmp.height !== height) throw new MaskFormatError(`mask PNG decoded as ${bmp.width}x${bmp.height}, header says ${width}x${height}`);
    const c = new OffscreenCanvas(width, height);
    const ctx = c.getContext("2d", { willReadFrequently: true });
    ctx.drawImage(bmp, 0, 0);
    const data = ctx.getImageData(0, 0, width, height).data;
    const ids = new Uint8Array(width * height);
    for (let i = 0, j = 0; i < ids.length; i++, j += 4) ids[i] = data[j];
    return { width, height, ids };
  } finally {
    bmp.close();
  }
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

