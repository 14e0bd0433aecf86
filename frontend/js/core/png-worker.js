// Module worker: encodes a mask snapshot to a greyscale PNG off the main thread, so an
// autosave of a 20-megapixel mask never stalls the brush.
import { encodeGreyPng } from "./png.js";

self.onmessage = async (e) => {
  const { id, ids, width, height } = e.data;
  try {
    const blob = await encodeGreyPng(ids, width, height);
    self.postMessage({ id, blob });
  } catch (err) {
    self.postMessage({ id, error: String(err && err.message ? err.message : err) });
  }
};
