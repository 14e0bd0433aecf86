// A tiny signal bus (three.js-editor style): named signals that views subscribe to.
// Models never call views directly; they dispatch signals and views redraw.

export class Signal {
  constructor() {
    this._listeners = new Set();
  }
  /** Subscribe; returns an unsubscribe function. */
  add(fn) {
    this._listeners.add(fn);
    return () => this._listeners.delete(fn);
  }
  dispatch(...args) {
    for (const fn of [...this._listeners]) fn(...args);
  }
  clear() {
    this._listeners.clear();
  }
}

/** Create an object of signals, e.g. createSignals(["maskChanged", "toolChanged"]). */
export function createSignals(names) {
  const out = {};
  for (const n of names) out[n] = new Signal();
  return out;
}
