// Annotator page: take the next frame from the queue, paint its mask at full resolution,
// autosave drafts (idle + leaving) with If-Match, submit, resolve 409 conflicts without
// losing either version, prefill from the lifted 3D labels.

import { api, ApiError } from "../core/api.js";
import { el, showError, toast, dialog, downloadBlob, fmtDate } from "../core/ui.js";
import { encodeGreyPngOffThread, decodeIdPng, resizeIds } from "../core/png.js";
import { Editor } from "../paint/editor.js";
import { buildLut, decodeMaskOffThread } from "../paint/mask.js";
import { Workbench, bindSmartTools, TOOL_KEYS, keysTable } from "../paint/workbench.js";
import { attachCorrections } from "./corrections.js";

const IDLE_SAVE_MS = 2500;
const PREFS_KEY = "occufly.annotator.prefs";
const FEW_MASKS = 3; // a prefill lifted from fewer submitted masks than this gets a warning
const LOW_CONFIDENCE = 0.6; // prefill pixels whose lifted label is less sure than this are marked
const LAG_SHOW_S = 2; // the lifting lag is shown from this many seconds (the target p95)
const LAG_POLL_MS = 5000;
// the keys of the painting tools (shared with the reviewer's editor), then this page's own
const KEYS = [
  ...TOOL_KEYS,
  ["Ctrl+S / Ctrl+Enter", "save draft / submit"],
  ["T", "take a reviewer's proposed mask change (a new draft: current mask + proposal)"],
  ["?", "this help"],
];

export async function mount(root, ctx) {
  const page = new AnnotatorPage(root, ctx);
  await page.start();
  return page;
}

class AnnotatorPage {
  constructor(root, ctx) {
    this.root = root;
    this.ctx = ctx;
    this.editor = null;
    this.frame = null;
    this.scene = null;
    this.version = null; // mask version the editor content is based on ("none" = no mask yet)
    this.versionNumber = null; // its per-frame number (what the user sees: "version 3")
    this.readOnly = false;
    this.editSeq = 0;
    this.savedSeq = 0;
    this.saving = null;
    this.idleTimer = null;
    this.stats = { openMs: null, saves: [] };
    this.skipped = [];
    this._listeners = [];
    window.__occufly = { page: this }; // used by the e2e tests and bench/bench_browser.py
  }

  get unsaved() {
    return this.editSeq !== this.savedSeq;
  }

  listen(target, type, fn, opts) {
    target.addEventListener(type, fn, opts);
    this._listeners.push(() => target.removeEventListener(type, fn, opts));
  }

  async start() {
    const scenes = await api.get("/scenes");
    this.scenes = scenes || [];
    this.sceneSel = el(
      "select",
      { id: "scene-select", "aria-label": "Scene" },
      this.scenes.map((s) => el("option", { value: s.id }, `${s.name} (${s.n_selected ?? "?"} selected)`)),
    );
    const want = this.ctx.params.scene;
    if (want) this.sceneSel.value = want;
    this.sceneSel.addEventListener("change", () => this.ctx.setParams({ scene: this.sceneSel.value, frame: null }));
    this.nextBtn = el("button", { type: "button", class: "primary", id: "next-frame", onclick: () => this.next() }, "Next frame");
    this.skipBtn = el("button", { type: "button", id: "skip", disabled: true, onclick: () => this.skip(), title: "Give this frame back to the queue (saved work stays) and take the next one" }, "Skip");
    this.queueEl = el("span", { class: "queue-pos", id: "queue-pos" }, "");
    this.helpBtn = el("button", { type: "button", id: "help", title: "Keyboard shortcuts (?)", onclick: () => this.showHelp() }, "?");
    this.frameInfo = el("span", { class: "frame-info", id: "frame-info" }, "No frame open");
    this.saveState = el("span", { class: "save-state", id: "save-state", role: "status" }, "");
    // how far the lifted 3D labels (the prefill's source) trail the submitted masks
    this.lagEl = el("span", { class: "lift-lag", id: "lift-lag", role: "status", hidden: true, title: "Submitted masks the lifting worker has not applied to the 3D labels yet; a prefill does not show them" }, "");
    this.paintedEl = el("span", { class: "painted", id: "painted" }, "");
    this.prefillBtn = el("button", { type: "button", id: "prefill", disabled: true, onclick: () => this.prefill(), title: "Start from the lifted 3D labels rendered into this frame" }, "Prefill from 3D");
    this.draftBtn = el("button", { type: "button", id: "save-draft", disabled: true, onclick: () => this.save("draft"), title: "Save a draft (Ctrl+S)" }, "Save draft");
    this.submitBtn = el("button", { type: "button", id: "submit", class: "primary", disabled: true, onclick: () => this.submit(), title: "Submit for review (Ctrl+Enter)" }, "Submit");
    this.host = el("div", { class: "canvas-host", id: "canvas-host" }, el("p", { class: "empty-hint" }, 'Press "Next frame" to get a frame from the annotation queue.'));
    this.toolsEl = el("div", { class: "tools", role: "toolbar", "aria-label": "Painting tools" });
    this.paletteEl = el("div", { class: "palette", role: "radiogroup", "aria-label": "Class palette" });
    // tools, palette, kept preferences (tool, brush size, opacity, outline, hidden classes):
    // the workbench the reviewer's editor shares
    this.bench = new Workbench({
      toolsEl: this.toolsEl,
      paletteEl: this.paletteEl,
      prefsKey: PREFS_KEY,
      readOnly: () => this.readOnly,
      onHistory: () => {
        // the prefill's warning and marks go when it is undone, come back on redo
        const live = this.prefillLive();
        if (live !== this._prefillShown) {
          this._prefillShown = live;
          if (this.frame && this.editor) this.buildSide();
        }
      },
    });
    this.sideEl = el("div", { class: "side-info" });
    this.versionsEl = el("div", { class: "side-versions" });
    this.progressEl = el("details", { class: "progress-box", id: "scene-progress" }, el("summary", {}, "Scene progress"));
    this.progressEl.addEventListener("toggle", () => this.progressEl.open && this.loadProgress());
    this.statusEl = el("div", { class: "statusline", id: "status" }, "");
    this.root.append(
      el(
        "section",
        { class: "annotator", "aria-label": "Annotator" },
        el("div", { class: "toolbar" }, el("label", { for: "scene-select", class: "sr-only" }, "Scene"), this.sceneSel, this.nextBtn, this.skipBtn, el("div", { class: "frame-head" }, this.frameInfo, this.queueEl), el("span", { class: "spacer" }), this.paintedEl, this.saveState, this.lagEl, this.prefillBtn, this.draftBtn, this.submitBtn, this.helpBtn),
        el("div", { class: "workspace" }, el("aside", { class: "left" }, this.toolsEl), this.host, el("aside", { class: "right", "aria-label": "Classes and review comments" }, this.sideEl, el("h2", {}, "Classes"), this.paletteEl, this.versionsEl, this.progressEl)),
        this.statusEl,
      ),
    );
    this.listen(document, "keydown", (e) => this.onKey(e));
    this.listen(document, "keyup", (e) => this.onKey(e));
    this.listen(window, "beforeunload", (e) => {
      if (this.unsaved) {
        this.saveOnLeave();
        e.preventDefault();
        e.returnValue = "";
      }
    });
    this.listen(document, "visibilitychange", () => {
      if (document.visibilityState === "hidden" && this.unsaved) this.saveOnLeave();
    });
    this.listen(window, "pagehide", () => {
      if (this.unsaved) this.saveOnLeave();
    });
    if (!this.scenes.length) {
      this.host.replaceChildren(el("p", { class: "empty-hint" }, "There is no scene yet. An admin has to import one first."));
      this.nextBtn.disabled = true;
      return;
    }
    if (this.ctx.params.frame) await this.openOrExplain(Number(this.ctx.params.frame));
  }

  /** Open a frame; on failure explain it and keep the page usable ("Next frame" still works). */
  async openOrExplain(fid) {
    try {
      await this.open(fid);
    } catch (e) {
      showError(e);
      this.status("");
      this.opening = null;
      this.editor?.destroy();
      this.editor = null;
      this.frame = null;
      this.host.replaceChildren(el("p", { class: "empty-hint" }, `Frame ${fid} could not be opened: ${e.message} Press "Next frame" to get one from the queue.`));
      this.ctx.setParams({ frame: null });
    }
  }

  async unmount() {
    clearTimeout(this.idleTimer);
    clearInterval(this.lagTimer);
    if (this.unsaved && this.frame) {
      try {
        await this.save("draft");
      } catch (e) {
        showError(e);
      }
    }
    for (const off of this._listeners) off();
    this.editor?.destroy();
    if (window.__occufly?.page === this) delete window.__occufly;
  }

  status(msg) {
    this.statusEl.textContent = msg;
  }

  /** "3D labels N s behind": the scene's lifting lag (labels/status lag_s), polled every
   * LAG_POLL_MS while a frame of the scene is open; hidden below LAG_SHOW_S. */
  async refreshLag() {
    const sid = this.frame?.scene_id ?? this.scene?.id;
    if (sid == null || document.visibilityState === "hidden") return;
    const st = await api.get(`/scenes/${sid}/labels/status`).catch(() => null);
    if (!st || (this.frame?.scene_id ?? this.scene?.id) !== sid) return;
    const lag = Number(st.lag_s) || 0;
    this.lagEl.hidden = lag < LAG_SHOW_S;
    this.lagEl.dataset.lag = String(lag);
    this.lagEl.dataset.pending = String(st.pending_frames ?? 0);
    this.lagEl.textContent = lag < LAG_SHOW_S ? "" : `3D labels ${Math.round(lag)} s behind`;
  }

  watchLag() {
    clearInterval(this.lagTimer);
    this.lagTimer = setInterval(() => this.refreshLag(), LAG_POLL_MS);
    this.refreshLag();
  }

  async sceneDetail(sid) {
    if (this.scene && String(this.scene.id) === String(sid)) return this.scene;
    this.scene = await api.get(`/scenes/${sid}`);
    return this.scene;
  }

  async next() {
    if (this.frame && this.unsaved) await this.save("draft");
    this.nextBtn.disabled = true;
    try {
      const q = this.skipped.length ? "?" + this.skipped.map((id) => `skip=${id}`).join("&") : "";
      const f = await api.post(`/scenes/${this.sceneSel.value}/next${q}`);
      if (!f) {
        toast("The queue is empty: every selected frame is taken or done.");
        this.host.replaceChildren(el("p", { class: "empty-hint" }, "The annotation queue is empty. Thank you!"));
        return;
      }
      if (this.frame && this.editor && f.id === this.frame.id) {
        // the queue hands back the frame that is open (it is still leased to this annotator
        // and not submitted): keep it, its painting and its undo history, and say why
        this.nextNotice = `${this.frame.name} is still yours and not submitted: Submit it when it is done, or Skip to give it back and take another frame.`;
        this.buildSide();
        toast("This frame is not submitted yet: Submit it, or Skip to take another.");
        return;
      }
      this.ctx.setParams({ scene: this.sceneSel.value, frame: f.id });
      await this.openOrExplain(f.id);
    } catch (e) {
      showError(e);
    } finally {
      this.nextBtn.disabled = false;
    }
  }

  /**
   * Mark the prefilled pixels whose lifted label has low confidence (hatched overlay, toggle in
   * the side panel): where to look first.
   */
  async loadConfidence(frame, ed, prefillIds) {
    const r = await api.blob(`/frames/${frame.id}/prefill/confidence`).catch(() => null);
    if (!r || this.editor !== ed) return;
    const d = await decodeIdPng(r.blob);
    const conf = resizeIds(d.ids, d.width, d.height, ed.mask.width, ed.mask.height);
    const W = ed.mask.width, H = ed.mask.height;
    const img = new ImageData(W, H);
    const px = new Uint32Array(img.data.buffer);
    const cut = 1 + Math.round(254 * LOW_CONFIDENCE);
    let low = 0, lab = 0;
    for (let i = 0; i < conf.length; i++) {
      if (!prefillIds[i] || !conf[i]) continue;
      lab++;
      if (conf[i] < cut) {
        low++;
        const x = i % W, y = (i / W) | 0;
        px[i] = ((x + y) & 3) < 2 ? 0xe0ff00ff : 0x60000000; // magenta / dark hatch (ABGR)
      }
    }
    const c = new OffscreenCanvas(W, H);
    c.getContext("2d").putImageData(img, 0, 0);
    this.lowConf = { canvas: c, low, share: lab ? low / lab : 0, show: true };
    if (!this._confPainter) {
      this._confPainter = (g, v) => {
        const lc = this.lowConf;
        if (!lc || !lc.show || this.editor !== ed) return;
        // the marks belong to the prefill: not shown once it is undone
        if (this.prefillCmd && !ed.history.undos.includes(this.prefillCmd)) return;
        g.save();
        g.imageSmoothingEnabled = false;
        g.translate(v.tx, v.ty);
        g.scale(v.scale, v.scale);
        g.drawImage(lc.canvas, 0, 0);
        g.restore();
      };
      ed.view.overlayPainters.unshift(this._confPainter);
    }
    ed.view.request();
  }

  /** Skip: save, release the lease, take the next frame (this one is not offered again now). */
  async skip() {
    if (!this.frame) return;
    const f = this.frame;
    try {
      if (this.unsaved) await this.save("draft");
      if (!this.readOnly) await api.post(`/frames/${f.id}/release`);
      if (!this.skipped.includes(f.id)) this.skipped.push(f.id);
      toast(`Skipped ${f.name}; it stays in the queue for later.`);
      await this.next();
    } catch (e) {
      showError(e);
    }
  }

  showHelp() {
    return dialog({
      title: "Keyboard shortcuts",
      body: keysTable(KEYS),
      buttons: [{ label: "Close", value: null, primary: true }],
    });
  }

  /** Per-scene progress (selected frames by state) and per annotator; "frame 7 of 23". */
  async loadProgress() {
    const sid = this.sceneSel.value;
    let frames;
    try {
      frames = ((await api.get(`/scenes/${sid}/frames`)) || []).filter((f) => f.selected);
    } catch (e) {
      this.queueEl.textContent = "";
      return;
    }
    this.queueFrames = frames;
    const order = ["unassigned", "in_progress", "submitted", "accepted", "rejected"];
    const label = { unassigned: "to do", in_progress: "in progress", submitted: "submitted", accepted: "accepted", rejected: "rejected" };
    const count = (rows) => Object.fromEntries(order.map((s) => [s, rows.filter((f) => f.state === s).length]));
    const all = count(frames);
    const me = this.ctx.session?.user?.username;
    const who = (f) => f.assignee || f.last_annotator || null;
    const people = [...new Set(frames.map(who).filter(Boolean))].sort();
    const left = all.unassigned + all.in_progress + all.rejected;
    if (this.frame) {
      // the position counts frames handed out (done + this one), not the frame's place in the
      // scene's list: the first frame anyone gets is "frame 1 of N"
      const mine = frames.find((f) => f.id === this.frame.id);
      const done = all.submitted + all.accepted;
      if (!mine) this.queueEl.textContent = `not a selected frame · ${left} of ${frames.length} left`;
      else if (mine.state === "submitted" || mine.state === "accepted") this.queueEl.textContent = `${done} of ${frames.length} done · ${left} left to do`;
      else this.queueEl.textContent = `frame ${done + 1} of ${frames.length} · ${left} left to do`;
    } else this.queueEl.textContent = `${left} of ${frames.length} frames left`;
    this.queueEl.dataset.left = String(left);
    this.queueEl.dataset.total = String(frames.length);
    if (!this.progressEl.open) return;
    const bar = el("div", { class: "state-bar", role: "img", "aria-label": order.map((s) => `${all[s]} ${label[s]}`).join(", ") }, order.filter((s) => all[s]).map((s) => el("span", { class: `seg st-${s}`, style: { flexGrow: String(all[s]) }, title: `${all[s]} ${label[s]}` })));
    const cols = [{ name: "all", ...all }, ...people.map((p) => ({ name: p === me ? `${p} (you)` : p, ...count(frames.filter((f) => who(f) === p)) }))];
    // one column per person (the side panel is narrow; states are the rows)
    this.progressEl.replaceChildren(
      el("summary", {}, "Scene progress"),
      bar,
      el(
        "table",
        { class: "progress-table", id: "progress-table" },
        el("thead", {}, el("tr", {}, el("th", {}, ""), cols.map((c) => el("th", { scope: "col", "data-who": c.name }, c.name)))),
        el("tbody", {}, order.map((s) => el("tr", { "data-state": s }, el("th", { scope: "row" }, el("span", { class: `dot st-${s}` }), ` ${label[s]}`), cols.map((c) => el("td", { "data-who": c.name }, String(c[s])))))),
      ),
    );
  }

  async open(fid) {
    const t0 = performance.now();
    this.stats.openMs = null;
    this.status("Opening frame…");
    // nothing may act on the previous frame while this one loads (prefill, save, submit)
    for (const b of [this.prefillBtn, this.draftBtn, this.submitBtn]) b.disabled = true;
    this.opening = fid;
    this.prefillWarning = this.prefillInfo = this.nextNotice = null;
    this.prefillCmd = this.prefillId = null; // a prefill belongs to the frame it was asked for
    this._prefillShown = false;
    this.lowConf = null;
    this._confPainter = null;
    const frame = await api.get(`/frames/${fid}`);
    const sid = frame.scene_id ?? this.sceneSel.value;
    if (frame.scene_id !== undefined) this.sceneSel.value = String(frame.scene_id);
    const ph = { detail: performance.now() - t0 };
    const mark = (k) => (x) => ((ph[k] = performance.now() - t0), x);
    // image and mask are fetched and decoded concurrently (image decoding runs off-thread)
    const W = frame.width;
    const H = frame.height;
    const scenePromise = this.sceneDetail(sid).then(mark("scene"));
    const [scene, bitmap, maskRes, items] = await Promise.all([
      scenePromise,
      api.send("GET", `/frames/${fid}/image`).then((r) => r.blob()).then(mark("imageFetched")).then((b) => createImageBitmap(b)).then(mark("imageDecoded")),
      // the saved mask is decoded and coloured in a worker while the image decodes
      // a fresh frame has no mask: do not ask for one (the API would answer 404)
      Promise.all([frame.current_version == null ? null : api.blob(`/frames/${fid}/mask`).then(mark("maskFetched")), scenePromise]).then(async ([r, sc]) =>
        r ? { etag: r.etag, number: r.number, decoded: await decodeMaskOffThread(r.blob, W, H, buildLut((sc.taxonomy && sc.taxonomy.classes) || [])) } : null,
      ).then(mark("maskDecoded")),
      api.get(`/scenes/${sid}/review-items`).catch(() => []),
    ]);
    const decoded = maskRes ? maskRes.decoded : null;
    const classes = (scene.taxonomy && scene.taxonomy.classes) || [];
    if (!classes.length) throw new Error(`Scene ${scene.name} has no taxonomy classes; cannot paint.`);
    this.editor?.destroy();
    this.host.replaceChildren();
    this.frame = frame;
    const ed = new Editor(this.host, { width: W, height: H, classes });
    this.editor = ed;
    this.watchLag();
    ed.setPhoto(bitmap);
    ph.editor = performance.now() - t0;
    if (decoded) ed.mask.adopt(decoded.ids, decoded.rgba, decoded.painted);
    ph.maskColoured = performance.now() - t0;
    this.version = maskRes ? maskRes.etag || "none" : "none";
    this.versionNumber = maskRes ? maskRes.number : null;
    this.editSeq = this.savedSeq = 0;
    ed.signals.edited.add(() => this.onEdited());
    bindSmartTools(ed, frame.id, () => this.editor === ed); // server-side smart tools, bound to this frame
    ed.signals.status.add((m) => this.status(m));
    ed.mask.changed.add(() => this.schedulePainted());
    this.bench.attach(ed);
    this.items = (items || []).filter((it) => String(it.frame_id) === String(fid));
    this.buildSide();
    ed.view.overlayPainters.push((c, v) => this.drawPins(c, v));
    attachCorrections(this, ed, frame).catch(() => {}); // reviewers' proposals, 3D items (issue 25)
    ed.view.overlay.focus({ preventScroll: true });
    this.frameInfo.replaceChildren(el("span", { class: "frame-name" }, frame.name), ` · ${frame.state.replace("_", " ")}`);
    this.frameInfo.title = `${frame.name}: ${W}×${H} px, ${frame.state.replace("_", " ")}`;
    this.opening = null;
    this.bench.applyPrefs();
    this.setReadOnly(this.readOnlyReason(frame));
    this.skipBtn.disabled = false;
    this.loadProgress();
    this.updatePainted();
    this.updateSaveState();
    await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
    this.stats.openMs = performance.now() - t0;
    ph.painted = this.stats.openMs;
    this.stats.openPhases = Object.fromEntries(Object.entries(ph).map(([k, v]) => [k, Math.round(v)]));
    this.status(`Opened ${frame.name} in ${(this.stats.openMs / 1000).toFixed(2)} s. B brush, E eraser, P polygon, F flood fill, R region fill, G GrabCut box (then scribble), I scissors, H pan, [ ] size, 1–0 / ⇧1–0 classes, , . previous / next class, Ctrl+Z undo.`);
  }

  /** Why an annotator may not edit this frame (null: editable). Reviewers/admins always may. */
  readOnlyReason(frame) {
    const me = this.ctx.session && this.ctx.session.user;
    if (!me || me.role !== "annotator") return null;
    if (frame.state === "accepted") return "accepted";
    if (frame.state === "submitted") return "submitted";
    if (frame.assignee && frame.assignee !== me.username) return "other";
    if (!frame.assignee && frame.state !== "rejected") return "free";
    return null;
  }

  setReadOnly(reason) {
    this.readOnly = !!reason;
    this.readOnlyWhy = reason;
    this.editor?.setReadOnly(this.readOnly);
    for (const b of [this.prefillBtn, this.draftBtn, this.submitBtn]) b.disabled = this.readOnly;
    this.bench.setReadOnly(this.readOnly);
    if (this.readOnly && this.editor) this.editor.setTool("pan");
    if (this.frame) this.buildSide();
  }

  readOnlyBanner() {
    const why = this.readOnlyWhy;
    if (!why) return null;
    const text = {
      accepted: "This frame was accepted by a reviewer. It is read-only.",
      submitted: "You submitted this frame; it is waiting for review and is read-only. Reopen it to change it (only while no reviewer has decided).",
      other: `This frame is leased to ${this.frame.assignee}. It is read-only for you.`,
      free: 'This frame is not leased to you, so it is read-only. Press "Next frame" to get one from the queue.',
    }[why];
    return el(
      "div",
      { class: "notice readonly", id: "readonly-banner", role: "status", "data-reason": why },
      el("strong", {}, "Read-only. "),
      text,
      why === "submitted" ? el("div", {}, el("button", { type: "button", id: "reopen", onclick: () => this.reopen() }, "Reopen for editing")) : null,
    );
  }

  /** Take a submitted, not yet reviewed frame back (the API renews the lease). */
  async reopen() {
    const fid = this.frame.id;
    try {
      await api.post(`/frames/${fid}/reopen`);
      toast("Reopened: the frame is yours again. Submit it when you are done.");
      await this.openOrExplain(fid);
    } catch (e) {
      showError(e);
    }
  }

  /** A prefill was applied to this frame and is not undone (its warning and marks apply). */
  prefillLive() {
    return !!(this.prefillCmd && this.editor && this.editor.history.undos.includes(this.prefillCmd));
  }

  buildSide() {
    const f = this.frame;
    const parts = [];
    const banner = this.readOnlyBanner();
    if (banner) parts.push(banner);
    if (this.nextNotice) parts.push(el("p", { class: "notice", id: "next-notice", role: "status" }, this.nextNotice));
    this._prefillShown = this.prefillLive(); // what the panel shows; refreshUndo follows it
    if (this._prefillShown) {
      if (this.prefillWarning) parts.push(el("p", { class: "notice", id: "prefill-warning", role: "status" }, this.prefillWarning));
      else if (this.prefillInfo) parts.push(el("p", { class: "muted", id: "prefill-info" }, this.prefillInfo));
    }
    if (this.lowConf) {
      const box = el("input", { type: "checkbox", id: "show-low-confidence" });
      box.checked = this.lowConf.show;
      box.addEventListener("change", () => {
        this.lowConf.show = box.checked;
        this.editor?.view.request();
      });
      parts.push(el("label", { class: "check low-conf", for: "show-low-confidence", "data-low": this.lowConf.low }, box, ` Mark low-confidence prefill (${(100 * this.lowConf.share).toFixed(1)} % of it, confidence < ${LOW_CONFIDENCE})`));
    }
    if (f.state === "rejected") parts.push(el("p", { class: "notice" }, "A reviewer sent this frame back. See the comments below and on the image."));
    if (this.items.length) {
      parts.push(el("h2", {}, "Review comments"));
      parts.push(
        el(
          "ul",
          { class: "comments", id: "review-comments" },
          this.items.map((it) =>
            el(
              "li",
              {},
              el("strong", {}, it.pixel ? `at (${Math.round(it.pixel[0])}, ${Math.round(it.pixel[1])}) ` : ""),
              it.comment ?? it.text ?? "",
              ...(it.comments || []).map((c) => el("div", { class: "reply" }, `${c.author ?? ""}: ${c.text ?? c.comment ?? ""}`)),
              it.pixel ? el("button", { type: "button", class: "link", onclick: () => this.jumpTo(it.pixel) }, "show") : null,
            ),
          ),
        ),
      );
    }
    if (!this.versionsBox || this.versionsBox.dataset.frame !== String(f.id)) {
      const versions = el("details", { class: "versions", "data-frame": f.id }, el("summary", {}, "Version history"));
      versions.addEventListener("toggle", () => versions.open && this.loadVersions(versions));
      this.versionsBox = versions;
      this.versionsEl.replaceChildren(versions);
    }
    this.sideEl.replaceChildren(...parts);
  }

  async loadVersions(box) {
    try {
      const vs = await api.get(`/frames/${this.frame.id}/mask/versions`);
      box.replaceChildren(
        el("summary", {}, "Version history"),
        vs && vs.length
          ? el(
              "ul",
              { class: "version-list" },
              [...vs].reverse().map((v) =>
                el(
                  "li",
                  { "data-version": v.version, "data-number": v.number ?? "" },
                  // an imported version: its source and the admin who uploaded it (issue 40)
                  typeof v.source === "string" && v.source.startsWith("imported")
                    ? `v${v.number ?? v.version} ${v.kind}, ${v.source}, uploaded by ${v.author ?? "?"} ${fmtDate(v.created_at)} `
                    : `v${v.number ?? v.version} ${v.kind} by ${v.author ?? "?"} ${fmtDate(v.created_at)} `,
                  el("button", { type: "button", class: "link", onclick: () => this.restore(v.version) }, "restore"),
                  el("a", { href: `/api/frames/${this.frame.id}/mask/versions/${v.version}`, download: `${this.frame.name}_v${v.version}.png` }, "download"),
                ),
              ),
            )
          : el("p", {}, "No saved versions yet."),
      );
    } catch (e) {
      showError(e);
    }
  }

  refreshVersions() {
    if (this.versionsBox && this.versionsBox.open) this.loadVersions(this.versionsBox);
  }

  /** Make an old version current again (as a new version; If-Match guards against races). */
  async restore(vid) {
    try {
      if (this.unsaved) await this.save("draft");
      const res = await api.send("POST", `/frames/${this.frame.id}/mask/versions/${vid}/restore`, {
        headers: { "If-Match": String(this.version ?? "none") },
      });
      const r = await res.json();
      toast(`Restored version ${vid} as version ${r?.version ?? "?"}.`);
      await this.openOrExplain(this.frame.id);
    } catch (e) {
      showError(e);
    }
  }

  jumpTo(px) {
    if (!px || !this.editor) return;
    const v = this.editor.view;
    v.scale = Math.max(v.scale, 0.5);
    v.tx = v.cssW / 2 - px[0] * v.scale;
    v.ty = v.cssH / 2 - px[1] * v.scale;
    v.invalidate();
  }

  drawPins(c, v) {
    for (const it of this.items || []) {
      if (!it.pixel) continue;
      const [x, y] = v.toScreen(it.pixel[0], it.pixel[1]);
      c.fillStyle = it.status === "resolved" ? "#6c6" : "#ff3b30";
      c.strokeStyle = "#fff";
      c.lineWidth = 2;
      c.beginPath();
      c.arc(x, y, 7, 0, Math.PI * 2);
      c.fill();
      c.stroke();
    }
  }

  onKey(e) {
    if (!this.editor) return;
    const t = e.target;
    if (t && (t.tagName === "INPUT" || t.tagName === "TEXTAREA" || t.tagName === "SELECT") && t.type !== "range") return;
    if (document.querySelector("dialog[open]")) return;
    if (this.opening != null && e.type === "keydown" && (e.ctrlKey || e.metaKey) && (e.key === "s" || e.key === "Enter")) {
      // a frame is loading: the editor on screen is the previous frame's (issue 40)
      e.preventDefault();
      this.status("Wait until the frame has opened: nothing was saved or submitted.");
      return;
    }
    if (e.type === "keydown" && (e.ctrlKey || e.metaKey) && e.key === "s") {
      e.preventDefault();
      this.save("draft").catch(showError);
      return;
    }
    if (e.type === "keydown" && (e.ctrlKey || e.metaKey) && e.key === "Enter") {
      e.preventDefault();
      this.submit();
      return;
    }
    if (t && t.tagName === "BUTTON" && (e.key === " " || e.key === "Enter")) return;
    if (e.type === "keydown" && e.key === "?") {
      e.preventDefault();
      this.showHelp();
      return;
    }
    if (this.corrections && this.corrections.ed === this.editor && this.corrections.onKey(e)) {
      e.preventDefault(); // T takes a reviewer's proposed mask change
      return;
    }
    if (this.bench.handleKey(e)) e.preventDefault(); // L outline, then the editor's keys
  }

  onEdited() {
    this.editSeq++;
    this.updateSaveState();
    this.updatePainted();
    clearTimeout(this.idleTimer);
    this.idleTimer = setTimeout(() => this.save("draft").catch(showError), IDLE_SAVE_MS);
  }

  schedulePainted() {
    if (this._paintedPending) return;
    this._paintedPending = true;
    setTimeout(() => {
      this._paintedPending = false;
      this.updatePainted();
      this.bench.drawMinimap();
    }, 200);
  }

  updatePainted() {
    if (!this.editor) return;
    const s = this.editor.mask.paintedShare;
    this.paintedEl.textContent = `Painted ${(100 * s).toFixed(1)} %`;
    this.paintedEl.dataset.share = String(s);
  }

  updateSaveState(text) {
    const el_ = this.saveState;
    if (text) el_.textContent = text;
    else if (this.saving) el_.textContent = "Saving…";
    else if (this.unsaved) el_.textContent = "Unsaved changes";
    else el_.textContent = this.version && this.version !== "none" ? `Saved (version ${this.versionNumber ?? "?"})` : "Nothing saved yet";
    el_.dataset.state = this.saving ? "saving" : this.unsaved ? "unsaved" : "saved";
  }

  /** Encode the mask and PUT it; one save at a time. Returns the server's answer. */
  async save(kind = "draft", { force = false, keepalive = false } = {}) {
    if (!this.editor || !this.frame) return null;
    clearTimeout(this.idleTimer);
    if (this.readOnly) return null;
    while (this.saving) await this.saving.catch(() => {});
    if (kind === "draft" && !this.unsaved && !force) return null;
    const run = this._save(kind, { keepalive });
    this.saving = run;
    this.updateSaveState();
    try {
      return await run;
    } finally {
      this.saving = null;
      this.updateSaveState();
    }
  }

  async _save(kind, { keepalive = false } = {}) {
    const ed = this.editor;
    const seq = this.editSeq;
    const frame = this.frame;
    const t0 = performance.now();
    const blob = await encodeGreyPngOffThread(ed.mask.ids, ed.mask.width, ed.mask.height);
    const tEnc = performance.now();
    try {
      const res = await api.send("PUT", `/frames/${frame.id}/mask?kind=${kind}`, {
        body: blob,
        headers: {
          "Content-Type": "image/png",
          "If-Match": String(this.version ?? "none"),
          // the effort figures count a prefill only while the mask is still painted over it
          ...(kind === "submitted" && this.prefillId && this.prefillCmd && ed.history.undos.includes(this.prefillCmd) ? { "X-Prefill-Id": String(this.prefillId) } : {}),
        },
        keepalive: keepalive && blob.size < 60000, // browsers cap keepalive bodies at 64 KiB
      });
      const body = await res.json();
      if (this.frame !== frame) return body; // saved for a frame that is no longer open
      this.version = String(body.version);
      this.versionNumber = body.number ?? null;
      if (this.editSeq === seq) this.savedSeq = seq;
      else this.savedSeq = Math.min(this.savedSeq, seq);
      this.stats.saves.push({ kind, bytes: blob.size, rawBytes: ed.mask.ids.length, encodeMs: tEnc - t0, totalMs: performance.now() - t0, version: this.version });
      if (kind === "submitted") this.frame.state = body.frame_state ?? "submitted";
      if (kind === "submitted") setTimeout(() => this.refreshLag(), 1000);
      this.refreshVersions();
      return body;
    } catch (e) {
      if (e instanceof ApiError && e.status === 409) return this.conflict(kind, blob, e);
      if (e instanceof ApiError && e.status === 401) {
        throw new ApiError(401, "Your session has expired, so the mask was not saved. Your painting is still here: log in again in another tab (this address with #/login), then press Save draft.");
      }
      throw e;
    }
  }

  /** 409: another session saved first. Keep both versions; let the user choose. */
  async conflict(kind, mine, err) {
    if (err.body && err.body.reason === "lease") return this.leaseLost(kind, mine, err);
    const theirs = err.body && err.body.current_version != null ? String(err.body.current_version) : null;
    const theirsNo = err.body && err.body.current_number != null ? err.body.current_number : theirs;
    const kept = err.body && err.body.conflict_version != null ? ` as conflict version ${err.body.conflict_version}` : "";
    for (;;) {
      const choice = await dialog({
        title: "This mask was changed by someone else",
        body: el(
          "div",
          {},
          el("p", {}, `While you were painting, version ${theirsNo ?? "?"} of ${this.frame.name} was saved from another session.`),
          el("p", {}, `Nothing is lost: your painting is still in this editor (the server also kept your upload${kept || " as a conflict version"}), and theirs is stored on the server. Choose what to do:`),
          el("p", { class: "muted" }, err.message),
          el("ul", {}, el("li", {}, "Keep mine: save your mask as a new version on top of theirs."), el("li", {}, "Load theirs: show their version here; Undo (Ctrl+Z) brings yours back."), el("li", {}, "Download mine: save your mask as a PNG file, then choose again.")),
        ),
        buttons: [
          { label: "Keep mine as new version", value: "mine", primary: true },
          { label: "Load theirs", value: "theirs" },
          { label: "Download mine", value: "download" },
        ],
        cancelValue: "later",
      });
      if (choice === "download") {
        downloadBlob(mine, `${this.frame.name.replace(/\.[^.]+$/, "")}_mine.png`);
        continue;
      }
      if (choice === "mine") {
        this.version = theirs ?? "none";
        return this._save(kind);
      }
      if (choice === "theirs") {
        const r = await api.blob(theirs ? `/frames/${this.frame.id}/mask/versions/${theirs}` : `/frames/${this.frame.id}/mask`);
        if (r) {
          const d = await decodeIdPng(r.blob);
          this.editor.replaceIds("load their version", resizeIds(d.ids, d.width, d.height, this.editor.mask.width, this.editor.mask.height));
        }
        this.version = theirs ?? (r && r.etag) ?? "none";
        this.savedSeq = this.editSeq;
        clearTimeout(this.idleTimer);
        toast("Loaded their version. Undo brings yours back.");
        return null;
      }
      toast("Not saved yet: your changes stay in the editor.");
      return null;
    }
  }

  /**
   * 409 because the frame is no longer leased to this annotator (submitted, accepted, lease
   * expired and taken by someone else). Say so, and offer what can actually work.
   */
  async leaseLost(kind, mine, err) {
    const state = err.body.frame_state || "not yours";
    const canReopen = state === "submitted";
    const why = {
      submitted: "You already submitted this frame, so it is waiting for review and no longer leased to you.",
      accepted: "A reviewer accepted this frame; it can no longer be changed.",
    }[state] || `The frame is ${state.replace("_", " ")} and no longer leased to you (the lease may have expired and someone else took it).`;
    clearTimeout(this.idleTimer);
    for (;;) {
      const choice = await dialog({
        title: "This frame is no longer leased to you",
        body: el(
          "div",
          {},
          el("p", {}, `Your change to ${this.frame.name} was not saved. ${why}`),
          el("p", {}, "Your painting is still in this editor, and the server kept your upload as a conflict version."),
          el("p", { class: "muted" }, err.message),
        ),
        buttons: [
          canReopen ? { label: "Reopen and save mine", value: "reopen", primary: true } : null,
          { label: "Download mine", value: "download", primary: !canReopen },
          { label: "Close", value: "close" },
        ].filter(Boolean),
        cancelValue: "close",
      });
      if (choice === "download") {
        downloadBlob(mine, `${this.frame.name.replace(/\.[^.]+$/, "")}_mine.png`);
        continue;
      }
      if (choice === "reopen") {
        const f = await api.post(`/frames/${this.frame.id}/reopen`);
        if (f) Object.assign(this.frame, f);
        this.version = f && f.current_version != null ? String(f.current_version) : this.version;
        this.setReadOnly(null);
        return this._save(kind === "submitted" ? "submitted" : "draft");
      }
      this.frame.state = state;
      this.setReadOnly(this.readOnlyReason(this.frame) || "other");
      this.savedSeq = this.editSeq; // nothing more to autosave: it would fail the same way
      this.updateSaveState(`Not saved: the frame is ${state.replace("_", " ")}`);
      return null;
    }
  }

  /**
   * Leaving: when the tab is hidden the page keeps running, so a normal draft save completes;
   * when it is being closed, the PUT is sent with keepalive (if under the browser's 64 KiB
   * limit, typical for masks: large uniform areas compress ~400x) and beforeunload asks the
   * user to stay while there are unsaved changes.
   */
  saveOnLeave() {
    if (!this.editor || this.saving) return;
    this.save("draft", { keepalive: true }).catch((e) => showError(e));
  }

  async submit() {
    if (!this.editor || this.opening != null) return;
    this.submitBtn.disabled = true;
    try {
      const r = await this.save("submitted", { force: true });
      if (r) {
        const n = r.number ?? r.version;
        toast(`Submitted version ${n}. Press "Next frame" for the next one.`);
        this.frameInfo.replaceChildren(el("span", { class: "frame-name" }, this.frame.name), ` · submitted (version ${n})`);
        this.frame.assignee = null;
        this.setReadOnly(this.readOnlyReason(this.frame));
        this.updateSaveState(`Submitted (version ${n})`);
        this.loadProgress();
      }
    } catch (e) {
      showError(e);
    } finally {
      this.submitBtn.disabled = this.readOnly;
    }
  }

  async prefill() {
    // bound to the frame (and editor) it was asked for: if another frame opens meanwhile,
    // the answer is dropped instead of landing on the new frame
    const ed = this.editor;
    const frame = this.frame;
    if (!ed || !frame || this.opening != null || this.readOnly) return;
    const stale = () => this.editor !== ed || this.frame !== frame;
    this.prefillBtn.disabled = true;
    try {
      this.status("Rendering the lifted 3D labels into this frame…");
      let r;
      try {
        r = await api.blob(`/frames/${frame.id}/prefill`, { allow404: false });
      } catch (e) {
        if (stale() || !(e instanceof ApiError && e.status === 404)) throw e;
        // the 404 says why (no lifted labels yet): said where "Rendering…" was
        const why = `No prefill: ${e.message}. Submit masks of this scene first (the 3D labels are lifted from them), then try again.`;
        this.status(why);
        toast(why);
        return;
      }
      if (stale()) return;
      if (!r) {
        this.status("No 3D labels to prefill from yet.");
        toast("No 3D labels to prefill from yet.");
        return;
      }
      const d = await decodeIdPng(r.blob);
      if (stale()) return;
      const ids = resizeIds(d.ids, d.width, d.height, ed.mask.width, ed.mask.height);
      let n = 0;
      for (let i = 0; i < ids.length; i++) if (ids[i]) n++;
      if (!n) {
        toast("The 3D labels do not cover this frame yet (prefill is empty).");
        this.status("Prefill is empty.");
        return;
      }
      let onlyUnpainted = false;
      if (ed.mask.painted > 0) {
        const c = await dialog({
          title: "Prefill from 3D",
          body: el("p", {}, "This frame already has painted pixels. Fill only the unpainted pixels, or replace everything with the 3D labels? (Undo reverts either.)"),
          buttons: [
            { label: "Fill unpainted only", value: "unpainted", primary: true },
            { label: "Replace everything", value: "all" },
            { label: "Cancel", value: null },
          ],
        });
        if (!c || stale()) return;
        onlyUnpainted = c === "unpainted";
      }
      ed.replaceIds("prefill from 3D", ids, { onlyUnpainted });
      this.prefillCmd = ed.history.undos[ed.history.undos.length - 1] || null;
      this.prefillId = r.prefillId || null; // named on submit while the prefill is not undone
      this.status(`Prefilled ${(100 * (n / ids.length)).toFixed(1)} % of the frame from the 3D labels. Correct it with the tools.`);
      // how much to trust it: from how many submitted masks the 3D labels were lifted
      const st = await api.get(`/scenes/${frame.scene_id ?? this.sceneSel.value}/labels/status`).catch(() => null);
      if (stale() || !st) return;
      const nMasks = Object.keys(st.included_versions || {}).length;
      this.prefillWarning = nMasks < FEW_MASKS
        ? `This prefill comes from only ${nMasks} submitted mask${nMasks === 1 ? "" : "s"}: expect rough borders and missing small objects; check every region.`
        : null;
      this.prefillInfo = `Prefill: ${(100 * (n / ids.length)).toFixed(1)} % of the frame, lifted from ${nMasks} mask${nMasks === 1 ? "" : "s"}.`;
      await this.loadConfidence(frame, ed, ids);
      if (stale()) return;
      this.buildSide();
    } catch (e) {
      if (!stale()) {
        this.status(`Prefill failed: ${e.message}`);
        showError(e);
      }
    } finally {
      if (stale()) this.status(`Prefill of ${frame.name} dropped: another frame was opened meanwhile.`);
      else this.prefillBtn.disabled = this.readOnly;
    }
  }
}
