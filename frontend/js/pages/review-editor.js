// The reviewer's editor (issue 40): a reviewer who finds a wrong region fixes the mask on the
// spot with the annotator's painting tools (the shared paint/editor.js + paint/workbench.js),
// saved as a version marked as the reviewer's correction (PUT /frames/{fid}/reviewer-correction:
// it votes at once, is queued for lifting, and the frame's annotator is notified); and
// "Propose from 3D": an active 3D relabel's projection into the frame becomes a proposed mask
// change that the annotator takes (T) or declines on their page.
//
// The reviewer page keeps one controller (attachReviewEditor) and asks it for the head's
// buttons; while the editor is open it owns the keyboard (A / R / N wait) and the frame list is
// hidden, so nothing moves the page to another frame under unsaved painting. After a save the
// page opens the frame again: its current version is the correction, and a decision names it.

import { api, ApiError } from "../core/api.js";
import { el, showError, toast, dialog, downloadBlob } from "../core/ui.js";
import { encodeGreyPngOffThread } from "../core/png.js";
import { Editor } from "../paint/editor.js";
import { buildLut, decodeMaskOffThread } from "../paint/mask.js";
import { Workbench, bindSmartTools, TOOL_KEYS, keysTable } from "../paint/workbench.js";

const PREFS_KEY = "occufly.reviewer.prefs";
const LIFT_POLL_MS = 1000;
const LIFT_WAIT_MS = 120000; // stop watching the 3D labels after this long (the lag shows it)
const KEYS = [...TOOL_KEYS, ["Ctrl+S", "save the correction"], ["?", "this help"]];

/** The controller the reviewer page keeps as `page.fixer`. */
export function attachReviewEditor(page) {
  return new ReviewEditor(page);
}

function isField(t) {
  return !!t && ((t.tagName === "INPUT" && t.type !== "range") || t.tagName === "TEXTAREA" || t.tagName === "SELECT");
}

class ReviewEditor {
  constructor(page) {
    this.page = page;
    this.state = null; // null | "opening" | "open"
    this.seq = 0;
    this.ed = null;
    this.frame = null;
    this.base = null; // {version, number}: the mask version being corrected (null: none yet)
    this.editSeq = this.savedSeq = 0;
    this.saving = false;
    this.saved = null; // {frameId, version, number, lifted}: the last correction saved here
    this._onKey = (e) => this.onKey(e);
    document.addEventListener("keydown", this._onKey);
    document.addEventListener("keyup", this._onKey);
    this._onUnload = (e) => {
      if (this.dirty) {
        e.preventDefault();
        e.returnValue = "";
      }
    };
    window.addEventListener("beforeunload", this._onUnload);
  }

  /** True from "Fix in 2D" until the editor is closed: the page's decision keys wait. */
  get active() {
    return this.state !== null;
  }

  get dirty() {
    return this.state === "open" && this.editSeq !== this.savedSeq;
  }

  /** Why frame `f`'s mask cannot be fixed here now (null: it can). */
  whyNot(f) {
    if (f.state === "in_progress") return `${f.assignee ? (typeof f.assignee === "object" ? f.assignee.username : f.assignee) : "An annotator"} is painting this frame now; comment on it, or fix it once it is submitted.`;
    if (f.current_version == null) return "No mask is saved for this frame yet: there is nothing to correct.";
    if (this.page.unreadableMask) return `The stored mask cannot be read here (${this.page.unreadableMask}).`;
    return null;
  }

  /** The review head's buttons for frame `f` (and the note on a correction saved here). */
  headButtons(f) {
    const why = this.whyNot(f);
    const out = [
      el("button", { type: "button", id: "fix-2d", disabled: !!why, title: why || "Fix the mask here with the annotator's painting tools; saved as your correction (it votes at once, and the annotator is told)", onclick: () => this.open() }, "Fix in 2D"),
      el("button", { type: "button", id: "propose-3d", title: "Turn a 3D relabel's projection into this frame into a proposed mask change for its annotator", onclick: () => this.propose() }, "Propose from 3D…"),
    ];
    const s = this.saved;
    if (s && s.frameId === f.id && String(s.version) === String(f.current_version)) {
      out.push(el("span", { class: "badge fix-note", id: "fix-note", "data-version": s.version, "data-lifted": String(!!s.lifted), title: "This version is your correction: it votes, and the frame's annotator was notified" }, `your correction (version ${s.number ?? s.version}) · ${s.lifted ? "in the 3D labels" : "3D labels updating…"}`));
    }
    return out;
  }

  // ---- the editor ---------------------------------------------------------------------------
  async open() {
    const page = this.page;
    const frame = page.frame;
    if (!frame || this.state) return;
    const why = this.whyNot(frame);
    if (why) {
      showError(why);
      return;
    }
    const token = ++this.seq;
    this.state = "opening";
    this.frame = frame;
    this.section()?.classList.add("editing");
    this.box = el("section", { class: "review-editor", id: "review-editor", "aria-label": `Fix the mask of ${frame.name}` }, el("p", { class: "loading" }, `Opening ${frame.name} at full resolution… `, el("button", { type: "button", id: "fix-cancel", onclick: () => this.close() }, "Cancel")));
    page.detailEl.replaceChildren(this.box);
    try {
      const fid = frame.id;
      const W = frame.width, H = frame.height;
      const lut = buildLut(page.classes || []);
      const [bitmap, maskRes] = await Promise.all([
        api.send("GET", `/frames/${fid}/image`).then((r) => r.blob()).then((b) => createImageBitmap(b)),
        api.blob(`/frames/${fid}/mask`).then(async (r) => (r ? { version: r.etag, number: r.number, decoded: await decodeMaskOffThread(r.blob, W, H, lut) } : null)),
      ]);
      if (token !== this.seq || this.state !== "opening") {
        bitmap.close?.();
        return;
      }
      this.build(frame, bitmap, maskRes);
    } catch (e) {
      if (token !== this.seq) return;
      this.teardown();
      page.renderDetail();
      showError(e);
    }
  }

  build(frame, bitmap, maskRes) {
    const page = this.page;
    this.base = maskRes ? { version: maskRes.version, number: maskRes.number } : null;
    const host = el("div", { class: "canvas-host", id: "fix-canvas-host" });
    const toolsEl = el("div", { class: "tools", role: "toolbar", "aria-label": "Painting tools" });
    const paletteEl = el("div", { class: "palette", role: "radiogroup", "aria-label": "Class palette" });
    this.stateEl = el("span", { class: "save-state", id: "fix-state", role: "status" }, "");
    this.statusEl = el("div", { class: "statusline", id: "fix-status" }, "");
    this.saveBtn = el("button", { type: "button", class: "primary", id: "fix-save", title: "Save as your correction (Ctrl+S)", onclick: () => this.save() }, "Save correction ", el("kbd", {}, "Ctrl+S"));
    const who = frame.last_annotator || (frame.assignee && (typeof frame.assignee === "object" ? frame.assignee.username : frame.assignee)) || null;
    const baseText = this.base ? `correcting version ${this.base.number ?? this.base.version}${who ? ` by ${who}` : ""}` : "no mask yet";
    this.box.replaceChildren(
      el(
        "div",
        { class: "toolbar fix-toolbar" },
        el("strong", { class: "frame-name" }, `Fix ${frame.name}`),
        el("span", { id: "fix-base", "data-version": this.base ? this.base.version : "" }, baseText),
        el("span", { class: "spacer" }),
        this.stateEl,
        el("button", { type: "button", id: "fix-help", title: "Keyboard shortcuts (?)", onclick: () => this.help() }, "?"),
        el("button", { type: "button", id: "fix-cancel", title: "Close the editor (asks before dropping unsaved painting)", onclick: () => this.close() }, "Cancel"),
        this.saveBtn,
      ),
      el("p", { class: "muted fix-hint" }, `Saved as your correction: a new version of ${frame.name} marked as yours that votes at once (the 3D labels follow), waits for review again, and its annotator is told.`),
      el("div", { class: "workspace" }, el("aside", { class: "left" }, toolsEl), host, el("aside", { class: "right", "aria-label": "Classes" }, el("h2", {}, "Classes"), paletteEl)),
      this.statusEl,
    );
    const ed = new Editor(host, { width: frame.width, height: frame.height, classes: page.classes });
    this.ed = ed;
    ed.setPhoto(bitmap);
    if (maskRes) ed.mask.adopt(maskRes.decoded.ids, maskRes.decoded.rgba, maskRes.decoded.painted);
    bindSmartTools(ed, frame.id, () => this.ed === ed);
    this.bench = new Workbench({ toolsEl, paletteEl, prefsKey: PREFS_KEY, readOnly: () => false });
    this.bench.attach(ed);
    this.bench.applyPrefs();
    this.editSeq = this.savedSeq = 0;
    ed.signals.edited.add(() => {
      this.editSeq++;
      this.updateState();
    });
    ed.signals.status.add((m) => this.status(m));
    ed.mask.changed.add(() => this.scheduleMinimap());
    this.state = "open";
    this.updateState();
    ed.view.overlay.focus({ preventScroll: true });
    this.status("Paint the fix: B brush, E eraser, P polygon, F flood fill, R region fill, G GrabCut, I scissors, 1–0 classes, Ctrl+Z undo; Ctrl+S saves it as your correction.");
  }

  scheduleMinimap() {
    if (this._mmPending) return;
    this._mmPending = true;
    setTimeout(() => {
      this._mmPending = false;
      this.bench?.drawMinimap();
    }, 200);
  }

  section() {
    return this.page.root.querySelector("section.reviewer");
  }

  status(msg) {
    if (this.statusEl) this.statusEl.textContent = msg;
  }

  updateState() {
    if (!this.stateEl) return;
    const s = this.saving ? "saving" : this.dirty ? "unsaved" : "clean";
    this.stateEl.dataset.state = s;
    this.stateEl.textContent = { saving: "Saving…", unsaved: "Unsaved changes", clean: "No changes yet" }[s];
    if (this.saveBtn) this.saveBtn.disabled = this.saving;
  }

  help() {
    return dialog({ title: "Keyboard shortcuts (fixing a mask)", body: keysTable(KEYS), buttons: [{ label: "Close", value: null, primary: true }] });
  }

  /** The editor owns the keyboard while it is open (the page's A / R / N wait). */
  onKey(e) {
    if (!this.state) return;
    const t = e.target;
    if (isField(t) || document.querySelector("dialog[open]")) return;
    if (this.state !== "open") {
      // still loading: nothing acts yet (and Ctrl+S is not the browser's "save page")
      if (e.type === "keydown" && (e.ctrlKey || e.metaKey) && (e.key === "s" || e.key === "S")) e.preventDefault();
      return;
    }
    if (e.type === "keydown" && (e.ctrlKey || e.metaKey) && (e.key === "s" || e.key === "S")) {
      e.preventDefault();
      this.save();
      return;
    }
    if (t && t.tagName === "BUTTON" && (e.key === " " || e.key === "Enter")) return;
    if (e.type === "keydown" && e.key === "?") {
      e.preventDefault();
      this.help();
      return;
    }
    if (this.bench.handleKey(e)) e.preventDefault();
  }

  /** Save the painting as the reviewer's correction, then show the frame with it current. */
  async save() {
    if (this.state !== "open" || this.saving) return;
    if (!this.dirty) {
      toast("Nothing changed yet: paint the fix, then save it.");
      return;
    }
    const ed = this.ed;
    const frame = this.frame;
    const seq = this.editSeq;
    this.saving = true;
    this.updateState();
    let v = null;
    try {
      const blob = await encodeGreyPngOffThread(ed.mask.ids, ed.mask.width, ed.mask.height);
      v = await this.put(frame, blob, this.base ? String(this.base.version) : "none");
    } catch (e) {
      showError(e);
    } finally {
      this.saving = false;
      this.updateState();
    }
    if (!v || this.ed !== ed) return;
    this.savedSeq = seq;
    this.saved = { frameId: frame.id, version: v.version, number: v.number, lifted: false };
    toast(`Saved your correction of ${frame.name} as version ${v.number ?? v.version}: it votes now, and the annotator was told.`);
    this.teardown();
    await this.page.openFrame(frame.id); // the correction is the frame's current version now
    this.watchLift(frame, v);
  }

  /** PUT the correction; on 409 (the mask changed meanwhile) let the reviewer choose. */
  async put(frame, blob, base) {
    for (;;) {
      try {
        const res = await api.send("PUT", `/frames/${frame.id}/reviewer-correction`, { body: blob, headers: { "Content-Type": "image/png", "If-Match": base } });
        return await res.json();
      } catch (e) {
        if (!(e instanceof ApiError) || e.status !== 409) throw e;
        const b = e.body || {};
        const theirs = b.current_number ?? b.current_version ?? "?";
        const choice = await dialog({
          title: "This mask was changed meanwhile",
          body: el(
            "div",
            {},
            el("p", {}, `While you were fixing it, version ${theirs} of ${frame.name} was saved by someone else.`),
            el("p", {}, `Nothing is lost: your painting is still in the editor${b.conflict_version != null ? `, and the server kept it as conflict version ${b.conflict_version}` : ""}.`),
            el("p", { class: "muted" }, e.message),
          ),
          buttons: [
            { label: "Save mine on top of theirs", value: "mine", primary: true },
            { label: "Download mine", value: "download" },
            { label: "Keep editing", value: "keep" },
          ],
          cancelValue: "keep",
        });
        if (choice === "mine") {
          base = b.current_version != null ? String(b.current_version) : "none";
          continue;
        }
        if (choice === "download") {
          downloadBlob(blob, `${frame.name.replace(/\.[^.]+$/, "")}_correction.png`);
          continue;
        }
        this.status("Not saved: your painting is still here.");
        return null;
      }
    }
  }

  /** Follow the lifting until the 3D labels include the correction; then show them. */
  async watchLift(frame, v) {
    const t_end = Date.now() + LIFT_WAIT_MS;
    const mine = () => this.saved && this.saved.frameId === frame.id && this.saved.version === v.version;
    while (Date.now() < t_end && mine()) {
      await new Promise((r) => setTimeout(r, LIFT_POLL_MS));
      const st = await api.get(`/scenes/${frame.scene_id}/labels/status`).catch(() => null);
      const key = String(frame.id);
      if (!st || !mine() || st.filled_versions?.[key] !== v.version) continue;
      this.saved.lifted = true;
      const page = this.page;
      if (this.state || String(page.frameId) !== key || !page.frame || String(page.frame.current_version) !== String(v.version)) return;
      // the rendered 3D labels, the disagreement and the agreement now include the correction;
      // reopen the frame unless the reviewer has started a comment or a pin (kept then: say so)
      if (!page.pin && !(page.comment && page.comment.value.trim())) await page.openFrame(frame.id);
      else {
        page.renderDetail?.();
        toast("The 3D labels now include your correction: open the frame again to see them.");
      }
      return;
    }
  }

  /** Close the editor (asks first when there is unsaved painting); true when closed. */
  async close() {
    if (!this.state) return true;
    if (this.saving) {
      toast("Saving your correction…");
      return false;
    }
    if (this.dirty) {
      const c = await dialog({
        title: "Drop your unsaved fix?",
        body: el("p", {}, `Your painting on ${this.frame.name} is not saved.`),
        buttons: [
          { label: "Save correction", value: "save", primary: true },
          { label: "Drop it", value: "drop" },
          { label: "Keep editing", value: "keep" },
        ],
        cancelValue: "keep",
      });
      if (c === "keep") return false;
      if (c === "save") {
        await this.save();
        return !this.state;
      }
    }
    const frame = this.frame;
    const stale = this.base && this.page.frame && String(this.page.frame.current_version) !== String(this.base.version);
    this.teardown();
    if (stale && frame) await this.page.openFrame(frame.id);
    else this.page.renderDetail();
    return true;
  }

  teardown() {
    this.seq++;
    this.state = null;
    this.ed?.destroy();
    this.ed = null;
    this.bench = null;
    this.stateEl = this.statusEl = this.saveBtn = null;
    this.editSeq = this.savedSeq = 0;
    this.section()?.classList.remove("editing");
  }

  /** The page leaves (route change): unsaved painting is saved or dropped as the reviewer says. */
  async leave() {
    if (this.dirty) await this.close();
    this.teardown();
    document.removeEventListener("keydown", this._onKey);
    document.removeEventListener("keyup", this._onKey);
    window.removeEventListener("beforeunload", this._onUnload);
  }

  // ---- proposals from 3D ---------------------------------------------------------------------
  /** List the active 3D corrections this frame sees; each can become a proposed mask change. */
  async propose() {
    const frame = this.page.frame;
    if (!frame) return;
    const body = el("div", { class: "propose-3d", id: "propose-list" }, el("p", { class: "loading" }, "Finding the 3D corrections this frame sees…"));
    const done = dialog({ title: `Propose from 3D: ${frame.name}`, body, buttons: [{ label: "Close", value: null, primary: true }] });
    this.renderProposals(frame, body).catch((e) => body.replaceChildren(el("p", { class: "error" }, `Could not list the 3D corrections: ${e.message}`)));
    await done;
    const p = this.page;
    if (!this.state && p.frame && p.frame.id === frame.id) p.renderDetail();
  }

  async renderProposals(frame, body) {
    const [edits, props] = await Promise.all([api.get(`/frames/${frame.id}/corrections`), api.get(`/frames/${frame.id}/proposals`)]);
    const classes = this.page.classes || [];
    const cls = (id) => classes.find((c) => c.id === id);
    const blocked = frame.state === "accepted" ? "This frame is accepted: its annotator cannot take a proposal unless the frame is reopened. Fix it in 2D instead." : frame.current_version == null ? "This frame has no submitted mask to propose a change to." : null;
    const rows = (edits || []).map((e) => {
      const c = cls(e.to_class);
      const why = blocked || (e.open_proposal ? `proposal ${e.open_proposal} is open` : e.proposable_px === 0 ? "the mask already agrees" : e.proposable_px == null ? "no submitted mask to compare" : null);
      const btn = el("button", { type: "button", class: "primary propose-btn", "data-edit": e.id, disabled: !!why, title: why || `Propose setting about ${e.proposable_px.toLocaleString()} px (grown by 1 px) to ${c ? c.name : e.to_class}` }, e.open_proposal ? "Proposed" : "Propose");
      btn.addEventListener("click", async () => {
        btn.disabled = true;
        try {
          const p = await api.post(`/scenes/${frame.scene_id}/corrections/${e.id}/proposals`, { frame_id: frame.id, dilate: 1 });
          toast(`Proposed a change of ${p.changed_px.toLocaleString()} px to ${frame.name}; its annotator was told.`);
          await this.renderProposals(frame, body);
        } catch (err) {
          btn.disabled = false;
          showError(err);
        }
      });
      return el(
        "tr",
        { "data-edit": e.id },
        el("td", {}, `#${e.id}`),
        el("td", { class: "class-cell" }, c ? el("span", { class: "swatch", style: { background: `rgb(${c.rgb.join(",")})` } }) : null, ` ${c ? c.name : e.to_class === 0 ? "unlabelled" : e.to_class}`),
        el("td", {}, `${e.author || "?"}${e.comment ? `: ${e.comment}` : ""}`),
        el("td", { "data-px": e.proposable_px ?? "" }, e.proposable_px == null ? `${e.pixels.toLocaleString()} px` : `${e.pixels.toLocaleString()} px, ${e.proposable_px.toLocaleString()} of another class`),
        el("td", {}, btn),
      );
    });
    const propRows = (props || []).slice().reverse().map((p) =>
      el("li", { "data-proposal": p.id, "data-status": p.status }, `#${p.id} from correction ${p.edit_id ?? "?"}: ${p.changed_px.toLocaleString()} px, ${p.status}${p.decided_by ? ` by ${p.decided_by}` : ""}${p.reply ? ` — “${p.reply}”` : ""}`),
    );
    const parts = [
      blocked ? el("p", { class: "notice", id: "propose-blocked" }, blocked) : null,
      rows.length
        ? el("table", { class: "propose-table" }, el("thead", {}, el("tr", {}, ["", "Relabel to", "By", "Its points here", ""].map((h) => el("th", {}, h)))), el("tbody", {}, rows))
        : el("p", { id: "propose-none" }, "No active 3D correction touches what this frame sees. Relabel points in the 3D viewer first (Open in 3D viewer), then propose it here."),
      el("p", { class: "muted" }, "A proposal sets the pixels the relabelled points fall on (gaps closed, grown by 1 px, only where the mask differs) to the new class; the annotator sees it as an overlay and takes it (T) or declines with a reply."),
      propRows.length ? el("div", {}, el("h3", {}, "Proposals for this frame"), el("ul", { class: "proposal-list", id: "proposal-list" }, propRows)) : null,
    ];
    body.replaceChildren(...parts.filter(Boolean));
  }
}
