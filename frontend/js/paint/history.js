// Command history. Every edit is a command with execute()/undo(); a command that was already
// applied while the user worked (a brush stroke built sample by sample) is pushed with
// push(). Each command holds only the tiles it changed (see TilePatch).

import { Signal } from "../core/bus.js";
import { TilePatch } from "./mask.js";

/**
 * An edit recorded as a tile patch. `apply(patch)` runs the edit once (first execute);
 * later executes (redo) restore the recorded "after" tiles.
 */
export class PatchCommand {
  constructor(name, mask, apply) {
    this.name = name;
    this.mask = mask;
    this.patch = new TilePatch(mask);
    this._apply = apply;
    this._done = false;
  }
  execute() {
    if (this._done) {
      this.patch.redo();
      return;
    }
    const rect = this._apply(this.patch);
    this.patch.finish();
    this._done = true;
    if (rect) this.mask.refresh(...rect);
  }
  undo() {
    this.patch.undo();
  }
  /**
   * Replace what this (applied, newest) command did by another edit: the mask goes back to
   * the state before the command, then `apply(patch)` runs on the same patch, so undo still
   * restores the mask from before the first edit (GrabCut refined with scribbles).
   */
  amend(apply) {
    this.patch.undo();
    this.patch.after = null;
    const rect = apply(this.patch);
    this.patch.finish();
    if (rect) this.mask.refresh(...rect);
  }
}

/**
 * A brush/eraser stroke: consecutive pointer samples are merged into this one command
 * (addSample), applied live; end() seals it. value 0 = eraser.
 */
export class StrokeCommand {
  constructor(mask, value, radius, name = value === 0 ? "erase" : "brush") {
    this.name = name;
    this.mask = mask;
    this.value = value;
    this.radius = radius;
    this.patch = new TilePatch(mask);
    this.last = null;
    this.samples = 0;
    this._sealed = false;
    this.dirty = null; // pending dirty rect since last flush
  }
  /** Merge one pointer sample (image pixels); returns the dirty rect it changed. */
  addSample(x, y, stamp) {
    const a = this.last || [x, y];
    const rect = stamp(this.mask, this.patch, a[0], a[1], x, y, this.radius, this.value);
    this.last = [x, y];
    this.samples++;
    if (rect) {
      const d = this.dirty;
      this.dirty = d ? [Math.min(d[0], rect[0]), Math.min(d[1], rect[1]), Math.max(d[2], rect[2]), Math.max(d[3], rect[3])] : rect;
    }
    return rect;
  }
  /** Recolour what changed since the last flush (called once per animation frame). */
  flush() {
    if (this.dirty) {
      this.mask.refresh(...this.dirty);
      this.dirty = null;
    }
  }
  end() {
    this.flush();
    this.patch.finish();
    this._sealed = true;
  }
  execute() {
    if (this._sealed) this.patch.redo();
  }
  undo() {
    this.patch.undo();
  }
}

export class History {
  constructor(limitBytes = 512 * 1024 * 1024) {
    this.undos = [];
    this.redos = [];
    this.limitBytes = limitBytes;
    this.changed = new Signal();
  }
  execute(cmd) {
    cmd.execute();
    this.push(cmd);
  }
  /** Record a command that has already been applied. */
  push(cmd) {
    if (cmd.patch && cmd.patch.isEmpty) return;
    this.undos.push(cmd);
    this.redos = [];
    this._trim();
    this.changed.dispatch("push", cmd);
  }
  undo() {
    const c = this.undos.pop();
    if (!c) return null;
    c.undo();
    this.redos.push(c);
    this.changed.dispatch("undo", c);
    return c;
  }
  redo() {
    const c = this.redos.pop();
    if (!c) return null;
    c.execute();
    this.undos.push(c);
    this.changed.dispatch("redo", c);
    return c;
  }
  /** Whether `cmd` is the newest command (the one undo would revert next). */
  isTop(cmd) {
    return this.undos.length > 0 && this.undos[this.undos.length - 1] === cmd;
  }
  /** Amend the newest command in place (see PatchCommand.amend); false if it is not the newest. */
  amend(cmd, apply) {
    if (!this.isTop(cmd)) return false;
    cmd.amend(apply);
    this.redos = [];
    this._trim();
    this.changed.dispatch("amend", cmd);
    return true;
  }
  /** Revert the newest command and forget it (no redo): an edit the user cancelled. */
  discard(cmd) {
    if (!this.isTop(cmd)) return false;
    this.undos.pop();
    cmd.undo();
    this.changed.dispatch("discard", cmd);
    return true;
  }
  clear() {
    this.undos = [];
    this.redos = [];
    this.changed.dispatch("clear", null);
  }
  _trim() {
    let total = 0;
    for (let i = this.undos.length - 1; i >= 0; i--) {
      total += this.undos[i].patch ? this.undos[i].patch.bytes : 0;
      if (total > this.limitBytes) {
        this.undos.splice(0, i + 1);
        break;
      }
    }
  }
}
