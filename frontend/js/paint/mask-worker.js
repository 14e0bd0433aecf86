// Module worker: decode a saved mask PNG and colour it, off the main thread, so opening a
// 20-megapixel frame leaves the page's thread free for the image and the first paint.
// In:  {id, png: ArrayBuffer, width, height, lut: Int32Array(256)}
// Out: {id, ids: Uint8Array, rgba: Uint8ClampedArray, painted} (buffers transferred) or {id, error}
import { decodeIdPng, resizeIds } from "../core/png.js";

self.onmessage = async (e) => {
  const { id, png, width, height, lut } = e.data;
  try {
    const d = await decodeIdPng(png);
    const ids = resizeIds(d.ids, d.width, d.height, width, height);
    const rgba = new Uint8ClampedArray(width * height * 4);
    const out = new Int32Array(rgba.buffer);
    let painted = 0;
    for (let i = 0; i < ids.length; i++) {
      const v = ids[i];
      out[i] = lut[v];
      painted += v !== 0 ? 1 : 0;
    }
    self.postMessage({ id, ids, rgba, painted }, [ids.buffer, rgba.buffer]);
  } catch (err) {
    self.postMessage({ id, error: String(err && err.message ? err.message : err) });
  }
};
