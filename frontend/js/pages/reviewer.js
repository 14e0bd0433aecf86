// Reviewer page: frames sorted by the ranking score (issue 23: what the other frames
// confidently see that the mask does not reproduce, plus a shift test); image, painted mask,
// rendered 3D labels and the disagreement overlay side by side or blended; leave-one-out
// agreement with independent coverage and painted share; pin a comment to a pixel; accept /
// reject; link to the 3D viewer on this frame. A Suspects tab lists the scene's contested
// regions: each opens the frame that sees it best with the region outlined, or the viewer.

import { api, isAbort } from "../core/api.js";
import { el, showError, toast, pct, table } from "../core/ui.js";
import { decodeIdPng } from "../core/png.js";
import { buildLut } from "../paint/mask.js";
import { drawOutlines } from "./corrections.js";
import { attachReviewEditor } from "./review-editor.js";

const LAYERS = [
  { key: "image", label: "Image" },
  { key: "mask", label: "Painted mask" },
  { key: "render", label: "Rendered 3D labels" },
  { key: "disagreement", label: "Disagreement" },
];

export async function mount(root, ctx) {
  const p = new ReviewerPage(root, ctx);
  await p.start();
  return p;
}

/** An imported mask version (its source "imported from COCO by <author>"): who made it, and
 * the admin who uploaded it, said wherever the version is shown (issue 40, defect 5). */
function isImported(source) {
  return typeof source === "string" && source.startsWith("imported");
}

function importTool(source) {
  const m = /^imported from (\S+)/.exec(source || "");
  return m ? m[1] : "an archive";
}

function importedText(source, uploader) {
  return `${source}${uploader ? `, uploaded by ${uploader}` : ""}`;
}

function idsToCanvas(ids, w, h, lut) {
  const c = document.createElement("canvas");
  c.width = w;
  c.height = h;
  const img = new ImageData(w, h);
  const out = new Int32Array(img.data.buffer);
  for (let i = 0; i < ids.length; i++) out[i] = lut[ids[i]];
  c.getContext("2d").putImageData(img, 0, 0);
  return c;
}

class ReviewerPage {
  constructor(root, ctx) {
    this.root = root;
    this.ctx = ctx;
    this.layers = {};
    this.mode = "side";
    this.pin = null;
    this.opacity = { image: 1, mask: 0.5, render: 0, disagreement: 0.8 };
    this.loadSeq = 0;
    this.view = { z: 1, px: 0, py: 0 }; // linked zoom / pan of every panel (image fractions)
    this.autoAdvance = true;
    this.tab = ctx.params.tab === "suspects" ? "suspects" : "frames";
    this.suspect = null; // the suspect whose region is outlined on the open frame
    window.__occufly_review = this; // for the e2e tests
    this.fixer = attachReviewEditor(this); // "Fix in 2D" / "Propose from 3D" (review-editor.js)
  }

  async start() {
    const scenes = (await api.get("/scenes")) || [];
    this.sceneSel = el("select", { id: "review-scene", "aria-label": "Scene" }, scenes.map((s) => el("option", { value: s.id }, s.name)));
    if (this.ctx.params.scene) this.sceneSel.value = this.ctx.params.scene;
    this.stateSel = el(
      "select",
      { id: "review-state", "aria-label": "Frame state filter" },
      ["", "submitted", "in_progress", "accepted", "rejected"].map((s) => el("option", { value: s }, s || "all states")),
    );
    // what needs review first (issue 40: not all 240 frames, 233 of them unassigned)
    this.stateSel.value = this.ctx.params.state ?? "submitted";
    this.listEl = el("div", { class: "frame-list", id: "frame-list" });
    this.suspectsEl = el("div", { class: "frame-list suspects-list", id: "suspects-list", hidden: true });
    this.tabBtns = ["frames", "suspects"].map((t) =>
      el("button", { type: "button", id: `tab-${t}`, role: "tab", "aria-selected": String(this.tab === t), onclick: () => this.setTab(t) }, t === "frames" ? "Frames" : "Suspects"),
    );
    this.detailEl = el("div", { class: "review-detail", id: "review-detail" }, el("p", { class: "empty-hint" }, "Choose a frame on the left. Frames are sorted by their ranking score: the share of what other frames confidently see in the frame that its mask does not reproduce (wrong class or left unpainted), plus a shift test — highest first."));
    this.sceneSel.addEventListener("change", () => {
      this.ctx.setParams({ scene: this.sceneSel.value, frame: null });
      this.loadList();
      if (this.tab === "suspects") this.loadSuspects();
    });
    this.stateSel.addEventListener("change", () => {
      this.ctx.setParams({ state: this.stateSel.value });
      this.loadList();
    });
    this.root.append(
      el(
        "section",
        { class: "reviewer" },
        el("aside", { class: "list-pane" }, el("h1", {}, "Review"), el("div", { class: "row" }, this.sceneSel, this.stateSel), el("div", { class: "row tabs", role: "tablist" }, this.tabBtns), this.listEl, this.suspectsEl),
        this.detailEl,
      ),
    );
    this._onKey = (e) => this.onKey(e);
    document.addEventListener("keydown", this._onKey);
    if (!scenes.length) {
      this.listEl.replaceChildren(el("p", {}, "No scenes yet."));
      return;
    }
    await this.loadList();
    if (this.tab === "suspects") this.setTab("suspects");
    if (this.ctx.params.frame) await this.openFrame(Number(this.ctx.params.frame));
  }

  setTab(t) {
    this.tab = t;
    this.ctx.setParams({ tab: t === "suspects" ? "suspects" : null });
    for (const b of this.tabBtns) b.setAttribute("aria-selected", String(b.id === `tab-${t}`));
    this.listEl.hidden = t !== "frames";
    this.stateSel.hidden = t !== "frames";
    this.suspectsEl.hidden = t !== "suspects";
    if (t === "suspects") this.loadSuspects();
  }

  // ---- suspects (issue 23): contested regions, worked through like the frame list ----------
  /** Where an earlier version of this page kept this reviewer's marks (localStorage). */
  legacyMarksKey() {
    const se = this.ctx.session;
    const u = (se && se.user && se.user.username) || "anonymous";
    return `occufly.suspects.${u}.${this.sceneSel.value}`;
  }

  /** Marks kept in this browser by the page before they moved to the server: sent once (where
   * the server has none for that suspect), then removed here. */
  async moveLegacyMarks(sid) {
    let local;
    try {
      local = JSON.parse(localStorage.getItem(this.legacyMarksKey()) || "null");
    } catch {
      local = null;
    }
    if (!local || typeof local !== "object") return false;
    let moved = 0;
    for (const s of this.suspects || []) {
      const st = local[s.key];
      if (!s.mark && (st === "done" || st === "dismissed")) {
        const r = await api.put(`/scenes/${sid}/suspects/${encodeURIComponent(s.key)}/mark`, { status: st }).catch(() => null);
        if (r) {
          s.mark = r.mark;
          moved++;
        }
      }
    }
    localStorage.removeItem(this.legacyMarksKey());
    if (moved) toast(`${moved} suspect mark${moved === 1 ? "" : "s"} from this browser moved to the server.`);
    return moved > 0;
  }

  /** Mark suspect `s` done / dismissed, or reopen it (`status` null); shared with the scene's
   * other reviewers. The button is disabled while the request is pending. */
  async mark(s, status, btn) {
    if (btn) btn.disabled = true;
    try {
      const r = await api.put(`/scenes/${this.sceneSel.value}/suspects/${encodeURIComponent(s.key)}/mark`, { status });
      for (const x of this.suspects || []) if (x.key === s.key) x.mark = r.mark;
      this.renderSuspects();
    } catch (e) {
      if (btn) btn.disabled = false;
      toast(`Could not mark the suspect: ${e.message}`);
    }
  }

  async loadSuspects() {
    const sid = this.sceneSel.value;
    this.suspectsEl.replaceChildren(el("p", { class: "loading" }, "Finding contested regions…"));
    try {
      const r = await api.get(`/scenes/${sid}/suspects`);
      if (String(sid) !== String(this.sceneSel.value)) return;
      const sc = await api.get(`/scenes/${sid}`).catch(() => null);
      this.suspectClasses = (sc && sc.taxonomy && sc.taxonomy.classes) || this.classes || [];
      this.suspects = (r && r.suspects) || [];
      await this.moveLegacyMarks(sid);
      this.renderSuspects();
    } catch (e) {
      this.suspects = [];
      this.suspectsEl.replaceChildren(el("p", { class: "error" }, `No suspects: ${e.message}`));
    }
  }

  /** Open suspects first (by rank), then the ones marked done or dismissed. */
  orderedSuspects() {
    const list = this.suspects || [];
    return [...list.filter((s) => !s.mark), ...list.filter((s) => s.mark)];
  }

  renderSuspects() {
    const list = this.orderedSuspects();
    if (!list.length) {
      this.suspectsEl.replaceChildren(el("p", {}, "No contested regions: the frames' votes agree and nothing overrode them."));
      return;
    }
    const cls = (id) => (this.suspectClasses || []).find((c) => String(c.id) === String(id));
    const open = list.filter((s) => !s.mark).length;
    this.suspectsEl.replaceChildren(
      table(
        list,
        [
          { key: "id", label: "#", fmt: (v) => `${v}` },
          {
            key: "kind",
            label: "Kind",
            fmt: (v, r) => (v === "island"
              ? el("span", { class: "suspect-kind island", title: "a small patch of one class surrounded by another (no frame contests it)" }, `island of ${r.island_of_name} in ${r.inside_name}`)
              : el("span", { class: `suspect-kind ${v}`, title: v === "contested" ? "frames' votes disagree here" : "the fill or denoise overrode the votes here" }, v === "contested" ? "votes disagree" : "fill overrode votes")),
          },
          { key: "points", label: "Points", fmt: (v, r) => el("span", { title: `${r.contested} points with contested votes, ${r.overridden} where the fill or denoise overrode the votes` }, Number(v).toLocaleString()) },
          {
            key: "classes",
            label: "Classes",
            fmt: (v) => el("span", { class: "class-cell" }, Object.entries(v || {}).sort((a, b) => b[1] - a[1]).slice(0, 2).map(([id, n]) => {
              const c = cls(id);
              return el("span", { class: "legend-item", title: `${n} points` }, c ? el("span", { class: "swatch", style: { background: `rgb(${c.rgb.join(",")})` } }) : null, c ? c.name : id);
            })),
          },
          { key: "n_frames", label: "Frames", fmt: (v, r) => el("span", { title: `seen by ${v} frames; best: frame index ${r.best_frame}` }, `${v}`) },
          {
            key: "key",
            label: "",
            fmt: (k, r) => el(
              "span",
              { class: "suspect-actions" },
              el("button", { type: "button", class: "link suspect-2d", disabled: r.best_frame_id == null, title: "Open the frame that sees it best, region outlined", onclick: () => this.openSuspect(r) }, "2D"),
              r.best_frame_id != null ? el("a", { class: "suspect-3d", href: `/viewer/?scene=${encodeURIComponent(this.sceneSel.value)}&frame=${r.best_frame_id}&suspect=${encodeURIComponent(r.key)}`, target: "_blank", rel: "noopener", title: "Open the 3D viewer at the camera that sees it best, the region's points selected (relabel them there)" }, "3D") : null,
              r.mark
                ? el("button", { type: "button", class: "link suspect-undo", title: `${r.mark.status} by ${r.mark.by || "a former user"}, ${new Date(r.mark.at).toLocaleString()}; click to reopen`, onclick: (e) => this.mark(r, null, e.currentTarget) }, `${r.mark.status}${r.mark.by ? ` by ${r.mark.by}` : ""} · undo`)
                : [el("button", { type: "button", class: "link suspect-done", title: "Mark done (you looked at it and fixed what was wrong)", onclick: (e) => this.mark(r, "done", e.currentTarget) }, "✓ done"), el("button", { type: "button", class: "link suspect-dismiss", title: "Dismiss (nothing wrong there)", onclick: (e) => this.mark(r, "dismissed", e.currentTarget) }, "✗")],
            ),
          },
        ],
        {
          caption: `${list.length} contested regions, largest first; ${open} open. Done / dismissed marks are shared with the scene's reviewers.`,
          rowAttrs: (r) => ({ "data-suspect": r.key, class: [r.mark ? `marked ${r.mark.status}` : "", this.suspect && this.suspect.key === r.key ? "current" : ""].join(" ").trim() }),
        },
      ),
    );
  }

  /** Open the frame that sees suspect `s` best, its region outlined and zoomed to. */
  async openSuspect(s) {
    this.suspectsEl.querySelectorAll("tr[data-suspect]").forEach((tr) => tr.classList.toggle("current", tr.dataset.suspect === s.key));
    await this.openFrame(s.best_frame_id, { suspect: s });
  }

  /** The next open suspect after the current one (N on the suspects tab). */
  stepSuspect(d) {
    const list = this.orderedSuspects().filter((s) => !s.mark || (this.suspect && s.key === this.suspect.key));
    const i = this.suspect ? list.findIndex((s) => s.key === this.suspect.key) : -1;
    const j = i + d;
    if (j < 0 || j >= list.length) {
      toast(d > 0 ? "That was the last open suspect." : "This is the first suspect.");
      return false;
    }
    this.openSuspect(list[j]);
    return true;
  }

  unmount() {
    this.loadSeq++;
    document.removeEventListener("keydown", this._onKey);
    return this.fixer.leave(); // unsaved painting in the 2D editor: saved or dropped, as asked
  }

  /** A accept, R reject (needs a comment), N / J next and P / K previous frame, 0 reset zoom. */
  onKey(e) {
    if (this.fixer.active) return; // the 2D editor owns the keys while it is open
    const t = e.target;
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    if (t && (t.tagName === "TEXTAREA" || t.tagName === "INPUT" || t.tagName === "SELECT")) {
      if (e.key === "Escape") t.blur();
      return;
    }
    if (e.key === "Escape" && t && t !== document.body && this.detailEl.contains(t)) {
      t.blur(); // leave a button / panel, so that A and R decide again
      return;
    }
    // nothing acts before the frame on screen is fully loaded (openFrame clears this.frame
    // at once) or while a decision is being sent / the page advances after it (issue 40)
    if (document.querySelector("dialog[open]") || !this.frame || this.deciding) return;
    const k = e.key.toLowerCase();
    if ((k === "a" || k === "r") && !this.decisionKeyOk(e)) return;
    if (k === "a") this.decide("accept");
    else if (k === "r") this.decide("reject");
    else if (k === "n" || k === "j") (this.tab === "suspects" ? this.stepSuspect(1) : this.step(1));
    else if (k === "p" || k === "k") (this.tab === "suspects" ? this.stepSuspect(-1) : this.step(-1));
    else if (k === "0") this.resetView();
    else return;
    e.preventDefault();
  }

  /** Whether A / R may decide now: not a held key's repeats, not while a button of the frame's
   * panel or a panel placing a pin has the focus (there a letter is a slip; the hint says
   * how to go on). Links and buttons of the lists are fine: open a frame, then press A. */
  decisionKeyOk(e) {
    if (e.repeat) return false;
    const t = e.target;
    const inDetail = t && this.detailEl.contains(t);
    const slip = inDetail && (t.tagName === "BUTTON" || t.tagName === "A" || (t.tagName === "CANVAS" && this.pin));
    if (!slip) return true;
    e.preventDefault();
    toast(`"${e.key.toUpperCase()}" was not taken as a decision: ${t.tagName === "CANVAS" ? "a pixel is being pinned" : "a button has the focus"}. Press Esc, then ${e.key.toUpperCase()}.`);
    return false;
  }

  /** Open the frame `d` rows below (above) the current one in the list; false at the end. */
  step(d) {
    const rows = this.frames || [];
    const i = rows.findIndex((f) => String(f.id) === String(this.frameId));
    const j = i + d;
    if (j < 0 || j >= rows.length) {
      toast(d > 0 ? "That was the last frame in the list." : "This is the first frame in the list.");
      return false;
    }
    this.openFrame(rows[j].id);
    return true;
  }

  resetView() {
    this.view = { z: 1, px: 0, py: 0 };
    this.paint();
  }

  async loadList() {
    const sid = this.sceneSel.value;
    const q = new URLSearchParams({ sort: "disagreement" });
    if (this.stateSel.value) q.set("state", this.stateSel.value);
    try {
      const frames = (await api.get(`/scenes/${sid}/frames?${q}`)) || [];
      this.frames = frames;
      if (!frames.length) {
        this.listEl.replaceChildren(el("p", {}, "No frames in this state."));
        return;
      }
      this.listEl.replaceChildren(
        table(
          frames,
          [
            { key: "name", label: "Frame", fmt: (v, r) => el("a", { href: `#/review?scene=${sid}&frame=${r.id}`, onclick: (e) => { e.preventDefault(); this.openFrame(r.id); } }, v) },
            // the assignee is cleared on submit: who painted it is last_annotator
            { key: "assignee", label: "Annotator", fmt: (v, r) => (isImported(r.current_source) && !v
              ? el("span", { class: "annotator-name imported", title: importedText(r.current_source, r.current_author) }, `imported (${importTool(r.current_source)})`)
              : el("span", { class: "annotator-name", title: v ? `leased to ${v}` : r.last_annotator ? `painted by ${r.last_annotator}` : "nobody yet" }, (v && typeof v === "object" ? v.username : v) || r.last_annotator || "–")) },
            // the ranking score the list is sorted by (issue 23), then the leave-one-out
            // agreement; frames without enough independent views say so instead of it
            { key: "review_score", label: "Score", fmt: (v) => el("span", { class: "review-score", title: "ranking score: the share of what other frames confidently see in this frame that the mask does not reproduce (wrong class or left unpainted), plus the shift test's gain; highest first" }, v == null ? "–" : Number(v).toFixed(2)) },
            { key: "agreement", label: "LOO agr.", fmt: (v, r) => (v == null && r.independent_coverage != null ? el("span", { class: "not-enough", title: "fewer than the required share of painted pixels have evidence from other frames" }, "not enough independent views") : pct(v)) },
            { key: "state", label: "State" },
            // independent coverage, painted share and the old self-agreement, compact (last:
            // the name, who painted it and the score stay in view in a narrow list)
            { key: "independent_coverage", label: "Coverage · painted · self", fmt: (v, r) => el("span", { class: "loo-figures", title: "independent coverage: share of the painted pixels other frames give evidence for; painted: share of the frame painted; self: agreement with labels that include this mask's own votes" }, `${v == null ? "–" : pct(v)} · ${r.painted_share == null ? "–" : pct(r.painted_share)} · ${r.self_agreement == null ? "–" : pct(r.self_agreement)}`.replace(/ %/g, "\u00a0%")) },
          ],
          { caption: `${frames.length} frames, highest ranking score first (what other frames see that the mask does not reproduce); then frames not scored yet`, rowAttrs: (r) => ({ "data-frame": r.id, class: String(r.id) === String(this.frameId) ? "current" : "" }) },
        ),
      );
    } catch (e) {
      showError(e);
    }
  }

  async openFrame(fid, { suspect = null } = {}) {
    const seq = ++this.loadSeq;
    // opening frame B cancels A's downloads (a 20 MP image keeps downloading otherwise)
    if (this.loadCtl) this.loadCtl.abort();
    const ctl = (this.loadCtl = new AbortController());
    const signal = ctl.signal;
    this.frameId = fid;
    // the frame on screen is gone: no key or button decides anything until B is shown
    this.frame = null;
    this.shownVersion = null;
    this.pin = null;
    this.suspect = suspect;
    this.ctx.setParams({ scene: this.sceneSel.value, frame: fid });
    this.listEl.querySelectorAll("tr[data-frame]").forEach((tr) => tr.classList.toggle("current", tr.dataset.frame === String(fid)));
    this.detailEl.replaceChildren(el("p", { class: "loading" }, "Loading frame…"));
    try {
      const frame = await api.get(`/frames/${fid}`, { signal });
      const sid = frame.scene_id ?? this.sceneSel.value;
      const hasMask = frame.current_version != null; // no mask yet: nothing to fetch or compare
      const none = () => Promise.resolve(null);
      // a layer that fails is shown as failed; a cancelled load is dropped as a whole
      const soft = (e) => (isAbort(e) ? Promise.reject(e) : { error: e.message });
      const [scene, agreement, items, imgR, maskR, renderR, disR] = await Promise.all([
        api.get(`/scenes/${sid}`, { signal }),
        hasMask ? api.get(`/frames/${fid}/agreement`, { signal }).catch(soft) : Promise.resolve({ error: "no mask saved yet" }),
        api.get(`/scenes/${sid}/review-items`, { signal }).catch((e) => (isAbort(e) ? Promise.reject(e) : [])),
        api.blob(`/frames/${fid}/image?size=preview`, { signal }).then((r) => r || api.blob(`/frames/${fid}/image`, { signal })),
        hasMask ? api.blob(`/frames/${fid}/mask`, { signal }).catch(soft) : none(),
        api.blob(`/frames/${fid}/render`, { signal }).catch(soft),
        hasMask ? api.blob(`/frames/${fid}/disagreement`, { signal }).catch(soft) : none(),
      ]);
      if (seq !== this.loadSeq) return;
      // the version on screen: the mask's own (ETag), else the frame's current one
      const shownVersion = maskR && !maskR.error && maskR.etag ? Number(maskR.etag) : frame.current_version;
      const lut = buildLut((scene.taxonomy && scene.taxonomy.classes) || []);
      this.classes = (scene.taxonomy && scene.taxonomy.classes) || [];
      const loaded = frame; // becomes this.frame (decidable) only once everything is drawn
      this.W = frame.width;
      this.H = frame.height;
      this.layers = {};
      this.layerErrors = {};
      this.unreadableMask = null;
      this.layers.image = imgR ? await createImageBitmap(imgR.blob) : null;
      for (const [key, r] of [["mask", maskR], ["render", renderR]]) {
        if (!r) this.layerErrors[key] = key === "mask" ? "no mask saved yet" : "nothing rendered";
        else if (r.error) this.layerErrors[key] = r.error;
        else {
          try {
            const d = await decodeIdPng(r.blob);
            this.layers[key] = idsToCanvas(d.ids, d.width, d.height, lut);
          } catch (e) {
            // a mask the page cannot read as stored is flagged, never shown as something else
            this.layerErrors[key] = `cannot show: ${e.message}`;
            if (key === "mask") this.unreadableMask = e.message;
          }
        }
      }
      if (!disR) this.layerErrors.disagreement = "not available";
      else if (disR.error) this.layerErrors.disagreement = disR.error;
      else this.layers.disagreement = await createImageBitmap(disR.blob);
      this.items = (items || []).filter((it) => String(it.frame_id) === String(fid));
      this.projected = []; // review items selected in 3D that this frame sees (issue 25)
      api.get(`/frames/${fid}/projected-items`).then((p) => seq === this.loadSeq && ((this.projected = p || []), this.paint())).catch(() => {});
      this.agreement = agreement;
      if (seq !== this.loadSeq) return;
      this.view = { z: 1, px: 0, py: 0 };
      this.frame = loaded;
      this.shownVersion = shownVersion;
      if (suspect && suspect.outline && suspect.outline.length >= 3) {
        // zoom to the region: its outline's box fills ~60 % of the panels
        const xs = suspect.outline.map((p) => p[0]), ys = suspect.outline.map((p) => p[1]);
        const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
        const z = Math.min(8, Math.max(1, 0.6 / Math.max((x1 - x0) / this.W, (y1 - y0) / this.H, 1e-3)));
        this.view = z > 1 ? { z, px: (x0 + x1) / 2 / this.W - 0.5, py: (y0 + y1) / 2 / this.H - 0.5 } : this.view;
      }
      this.renderDetail();
    } catch (e) {
      if (isAbort(e) || seq !== this.loadSeq) return; // superseded by another frame
      this.detailEl.replaceChildren(el("p", { class: "error" }, `Could not open frame ${fid}: ${e.message}`));
      showError(e);
    }
  }

  renderDetail() {
    const f = this.frame;
    const a = this.agreement || {};
    const lonely = a.status === "not_enough_independent_views";
    const agreeText = a.error ? `unavailable: ${a.error}` : lonely ? "— not enough independent views" : pct(a.agreement);
    const modeBtns = [
      el("button", { type: "button", "aria-pressed": String(this.mode === "side"), onclick: () => this.setMode("side") }, "Side by side"),
      el("button", { type: "button", "aria-pressed": String(this.mode === "blend"), onclick: () => this.setMode("blend") }, "Blended"),
    ];
    this.panelsEl = el("div", { class: `panels mode-${this.mode}`, id: "panels" });
    this.comment = el("textarea", { id: "review-comment", rows: 3, placeholder: "Comment (click the image to pin it to a pixel)" });
    this.pinText = el("span", { id: "pin-text" }, "No pixel pinned: click on any panel to pin.");
    // per_class is keyed by class name: {id, mask_pixels (seen by others), painted_pixels, rendered_pixels, agree, recall, precision, iou}
    const perClass = a.per_class && typeof a.per_class === "object" ? Object.entries(a.per_class) : [];
    const classOf = (key, v) => this.classes.find((c) => (v && v.id != null ? c.id === v.id : c.name === key)) || null;
    this.detailEl.replaceChildren(
      el(
        "div",
        { class: "review-head" },
        el("h2", {}, f.name),
        el("span", { class: `badge state-${f.state}` }, f.state),
        isImported(f.current_source) ? el("span", { class: "badge imported", id: "version-source" }, importedText(f.current_source, f.current_author)) : null,
        el("span", { class: "agreement", id: "agreement", "data-value": a.agreement ?? "" }, `Agreement ${agreeText}`),
        a.pixels != null && !lonely ? el("span", {}, `over ${Number(a.pixels).toLocaleString()} independent pixels`) : null,
        a.independent_coverage != null ? el("span", { id: "independent-coverage", "data-value": a.independent_coverage }, `independent coverage ${pct(a.independent_coverage)}${lonely ? ` (needs ${pct(a.min_independent_coverage)})` : ""}`) : null,
        a.painted_share != null ? el("span", { id: "painted-share", "data-value": a.painted_share }, `painted ${pct(a.painted_share)} of the frame`) : null,
        a.self_agreement != null ? el("span", { id: "self-agreement", title: "against labels lifted from this mask too (circular)" }, `self ${pct(a.self_agreement)}`) : null,
        a.review_score != null ? el("span", { id: "review-score", "data-value": a.review_score, title: "ranking score: share of what other frames confidently see here that the mask does not reproduce, plus the shift test's gain" }, `score ${Number(a.review_score).toFixed(2)}${a.shift_gain > 0 ? ` (shifted ${Number(a.shift_gain).toFixed(2)})` : ""}`) : null,
        // issue 40: the neighbour whose votes contradict this mask, and whether the others side with it
        a.neighbours && a.neighbours.length ? el("span", { id: "disagreeing-neighbours", title: "frames that painted the points this frame painted differently; 'overruled': share of those points where the other frames' labels are not that neighbour's either (it is the likely wrong one)" }, "disagrees with ", ...a.neighbours.slice(0, 2).flatMap((n, i) => [i ? ", " : "", el("a", { href: `#/review?scene=${this.sceneSel.value}&frame=${n.frame_id}`, "data-frame": n.frame_id, onclick: (e) => { e.preventDefault(); this.openFrame(n.frame_id); } }, n.name), ` on ${pct(n.disagree_share)} of ${Number(n.shared_points).toLocaleString()} shared points${n.overruled_share != null ? ` (other frames overrule it on ${pct(n.overruled_share)})` : ""}`])) : null,
        this.suspect ? el("span", { class: "badge suspect-badge", id: "suspect-badge", title: "the region is outlined on the panels" }, `suspect #${this.suspect.id}: ${Number(this.suspect.points).toLocaleString()} points`) : null,
        // the viewer picks its scene from ?scene=; ?frame= names the frame (contract link)
        el("a", { href: `/viewer/?scene=${f.scene_id ?? this.sceneSel.value}&frame=${f.id}`, target: "_blank", rel: "noopener", id: "open-3d" }, "Open in 3D viewer"),
        ...this.fixer.headButtons(f),
        el("span", { class: "spacer" }),
        ...modeBtns,
      ),
      this.panelsEl,
      this.legend(),
      el(
        "div",
        { class: "review-actions" },
        el("label", { for: "review-comment" }, "Comment"),
        this.comment,
        this.pinText,
        el(
          "div",
          { class: "row" },
          el("button", { type: "button", id: "pin-comment", onclick: () => this.pinComment().then((it) => it && this.renderDetail()).catch(showError) }, "Pin comment"),
          el("button", { type: "button", id: "accept", class: "primary", title: "Accept (A)", disabled: !!this.deciding, onclick: () => this.decide("accept") }, "Accept ", el("kbd", {}, "A")),
          el("button", { type: "button", id: "reject", class: "danger", title: "Reject with comment (R)", disabled: !!this.deciding, onclick: () => this.decide("reject") }, "Reject with comment ", el("kbd", {}, "R")),
          el("button", { type: "button", id: "next-review", title: "Next frame in the list (N)", onclick: () => this.step(1) }, "Next ", el("kbd", {}, "N")),
          el("label", { class: "check" }, (() => {
            const b = el("input", { type: "checkbox", id: "auto-advance" });
            b.checked = this.autoAdvance;
            b.addEventListener("change", () => (this.autoAdvance = b.checked));
            return b;
          })(), " go to the next frame after a decision"),
        ),
        el("p", { class: "muted keys-hint" }, "Keys: A accept · R reject · N / P next / previous frame · wheel zooms all panels together, drag pans them · 0 resets the zoom."),
      ),
      perClass.length
        ? el(
            "details",
            { id: "per-class" },
            el("summary", {}, lonely ? "Agreement per class (not enough independent views)" : "Agreement per class"),
            lonely ? el("p", { class: "muted", id: "per-class-lonely" }, "Other frames see too little of what this frame painted: the figures below compare only the pixels they do see, and a class no other frame sees has none (–).") : null,
            table(
              perClass
                .map(([k, v]) => ({ k, ...(typeof v === "object" && v ? v : { iou: v }), cls: classOf(k, v) }))
                .sort((x, y) => y.painted_pixels - x.painted_pixels),
              [
                { key: "k", label: "Class", fmt: (k, r) => el("span", { class: "class-cell" }, r.cls ? el("span", { class: "swatch", style: { background: `rgb(${r.cls.rgb.join(",")})` } }) : null, r.cls ? r.cls.name : k) },
                { key: "painted_pixels", label: "Painted px", fmt: (v) => Number(v).toLocaleString() },
                { key: "mask_pixels", label: "Seen by others px", fmt: (v) => (v == null ? "–" : Number(v).toLocaleString()) },
                { key: "recall", label: "Recall", fmt: (v) => pct(v) },
                { key: "precision", label: "Precision", fmt: (v) => pct(v) },
                { key: "iou", label: "IoU", fmt: (v) => pct(v) },
              ],
              { caption: "Against the labels the other frames decide (leave-one-out). Seen by others: painted pixels where the other frames give a label. Recall: share of those the 3D labels agree with; precision: share of the rendered pixels of the class the painting agrees with." },
            ),
          )
        : null,
      this.itemsList(),
    );
    this.drawPanels();
  }

  /** Which colour is which class, and what the disagreement overlay's colours mean. */
  legend() {
    const present = new Set(Object.values((this.agreement && this.agreement.per_class) || {}).map((v) => v && v.id).filter((v) => v != null));
    const shown = this.classes.filter((c) => present.size === 0 || present.has(c.id));
    return el(
      "div",
      { class: "legend", id: "legend" },
      el("div", { class: "legend-classes" }, el("strong", {}, present.size ? "Classes in this frame: " : "Classes: "), shown.map((c) => el("span", { class: "legend-item", "data-class": c.id }, el("span", { class: "swatch", style: { background: `rgb(${c.rgb.join(",")})` } }), c.name))),
      el(
        "div",
        { class: "legend-dis" },
        el("strong", {}, "Disagreement panel: "),
        el("span", { class: "legend-item" }, el("span", { class: "swatch dis-class" }), "opaque class colour = the 3D labels' class where it differs from the painting"),
        el("span", { class: "legend-item" }, el("span", { class: "swatch dis-gap" }), "grey = painted, but no 3D label there"),
        el("span", { class: "legend-item" }, el("span", { class: "swatch dis-none" }), "clear = they agree, or nothing painted"),
      ),
    );
  }

  itemsList() {
    if (!this.items.length) return el("p", { id: "review-items" }, "No review items for this frame.");
    return el(
      "ul",
      { class: "comments", id: "review-items" },
      this.items.map((it) =>
        el(
          "li",
          {},
          `${it.status ?? ""} `,
          it.pixel ? el("strong", {}, `(${Math.round(it.pixel[0])}, ${Math.round(it.pixel[1])}) `) : "",
          it.comment ?? it.text ?? "",
          ...(it.comments || []).map((c) => el("div", { class: "reply" }, `${c.author ?? ""}: ${c.text ?? ""}`)),
          it.status !== "resolved"
            ? el("button", { type: "button", class: "link", onclick: () => this.resolve(it) }, "mark resolved")
            : null,
        ),
      ),
    );
  }

  setMode(m) {
    this.mode = m;
    this.renderDetail();
  }

  drawPanels() {
    const panels = this.panelsEl;
    panels.className = `panels mode-${this.mode}`;
    panels.replaceChildren();
    this.canvases = [];
    if (this.mode === "side") {
      for (const L of LAYERS) {
        const c = el("canvas", { class: "panel-canvas", "data-layer": L.key, role: "img", "aria-label": L.label });
        const err = this.layerErrors[L.key];
        panels.append(el("figure", {}, c, el("figcaption", {}, L.label, err ? el("span", { class: "muted" }, ` (${err})`) : null)));
        this.canvases.push({ c, layers: [[L.key, 1]] });
      }
    } else {
      const c = el("canvas", { class: "panel-canvas blend", "data-layer": "blend", role: "img", "aria-label": "Blended layers" });
      const controls = LAYERS.map((L) => {
        const r = el("input", { type: "range", min: 0, max: 100, value: Math.round(this.opacity[L.key] * 100), id: `op-${L.key}` });
        r.addEventListener("input", () => {
          this.opacity[L.key] = Number(r.value) / 100;
          this.paint();
        });
        return el("label", { for: `op-${L.key}` }, `${L.label} `, r);
      });
      panels.append(el("figure", {}, c, el("figcaption", { class: "blend-controls" }, controls)));
      this.canvases.push({ c, layers: null });
    }
    for (const { c } of this.canvases) {
      this.bindZoomPan(c);
      c.addEventListener("click", (e) => {
        if (this._suppressClick) {
          this._suppressClick = false;
          return;
        }
        this.onPick(e, c);
      });
      c.addEventListener("keydown", (e) => this.onPinKey(e));
      c.tabIndex = 0;
      c.title = "Click, or use the arrow keys (Shift = 10 px), to pin a comment to a pixel";
    }
    requestAnimationFrame(() => this.paint());
  }

  /** Fit the W x H frame into the canvas; returns {s, ox, oy}. */
  fitOf(c) {
    const base = Math.min(c.width / this.W, c.height / this.H);
    const { z, px, py } = this.view;
    const s = base * z;
    // (px, py): the image point (as a fraction) at the canvas centre is shifted by that much
    return { s, ox: (c.width - this.W * s) / 2 - px * this.W * s, oy: (c.height - this.H * s) / 2 - py * this.H * s };
  }

  /** Wheel zooms every panel at the cursor; a drag pans them all (a click still pins). */
  bindZoomPan(c) {
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = c.getBoundingClientRect();
      const f = this.fitOf(c);
      const mx = (e.clientX - r.left) * (c.width / r.width), my = (e.clientY - r.top) * (c.height / r.height);
      const ix = (mx - f.ox) / f.s, iy = (my - f.oy) / f.s; // image px under the cursor
      const z = Math.min(40, Math.max(1, this.view.z * (e.deltaY < 0 ? 1.25 : 0.8)));
      const base = f.s / this.view.z;
      const s = base * z;
      // keep (ix, iy) under the cursor
      this.view = { z, px: ((c.width - this.W * s) / 2 - mx + ix * s) / (this.W * s), py: ((c.height - this.H * s) / 2 - my + iy * s) / (this.H * s) };
      if (z === 1) this.view = { z: 1, px: 0, py: 0 };
      this.paint();
    }, { passive: false });
    c.addEventListener("pointerdown", (e) => {
      if (e.button !== 0) return;
      this._drag = { x: e.clientX, y: e.clientY, px: this.view.px, py: this.view.py, moved: false, c };
    });
    c.addEventListener("pointermove", (e) => {
      const d = this._drag;
      if (!d || d.c !== c) return;
      const dx = e.clientX - d.x, dy = e.clientY - d.y;
      if (!d.moved && Math.hypot(dx, dy) < 4) return;
      d.moved = true;
      const r = c.getBoundingClientRect();
      const f = this.fitOf(c);
      this.view = { ...this.view, px: d.px - (dx * (c.width / r.width)) / (this.W * f.s), py: d.py - (dy * (c.height / r.height)) / (this.H * f.s) };
      this.paint();
    });
    c.addEventListener("pointerup", () => {
      if (this._drag && this._drag.moved) this._suppressClick = true;
      this._drag = null;
    });
  }

  paint() {
    for (const entry of this.canvases || []) {
      const c = entry.c;
      const r = c.getBoundingClientRect();
      c.width = Math.max(10, Math.round(r.width));
      c.height = Math.max(10, Math.round((r.width * this.H) / this.W));
      const g = c.getContext("2d");
      g.fillStyle = "#20232a";
      g.fillRect(0, 0, c.width, c.height);
      const { s, ox, oy } = this.fitOf(c);
      const layers = entry.layers || LAYERS.map((L) => [L.key, this.opacity[L.key]]);
      for (const [key, alpha] of layers) {
        const src = this.layers[key];
        if (!src || alpha <= 0) continue;
        g.globalAlpha = alpha;
        g.imageSmoothingEnabled = key === "image";
        g.drawImage(src, ox, oy, this.W * s, this.H * s);
      }
      g.globalAlpha = 1;
      const pins = this.items.filter((it) => it.pixel).map((it) => it.pixel);
      if (this.pin) pins.push(this.pin);
      for (const p of pins) {
        g.fillStyle = p === this.pin ? "#ffcc00" : "#ff3b30";
        g.strokeStyle = "#000";
        g.beginPath();
        g.arc(ox + (p[0] + 0.5) * s, oy + (p[1] + 0.5) * s, 6, 0, Math.PI * 2);
        g.fill();
        g.stroke();
      }
      drawOutlines(g, this.projected, (x, y) => [ox + x * s, oy + y * s]);
      if (this.suspect && this.suspect.outline) drawOutlines(g, [{ outline: this.suspect.outline, comments: [{ text: `suspect #${this.suspect.id}` }] }], (x, y) => [ox + x * s, oy + y * s]);
    }
  }

  onPick(e, c) {
    const r = c.getBoundingClientRect();
    const { s, ox, oy } = this.fitOf(c);
    const x = Math.floor(((e.clientX - r.left) * (c.width / r.width) - ox) / s);
    const y = Math.floor(((e.clientY - r.top) * (c.height / r.height) - oy) / s);
    if (x < 0 || y < 0 || x >= this.W || y >= this.H) return;
    this.pin = [x, y];
    this.pinText.textContent = `Pinned pixel (${x}, ${y}).`;
    this.comment.focus();
    this.paint();
  }

  /** Keyboard pinning: arrows move the pin (from the centre), Shift moves 10 px. */
  onPinKey(e) {
    const d = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] }[e.key];
    if (!d) return;
    e.preventDefault();
    const step = e.shiftKey ? 10 : 1;
    const p = this.pin || [Math.floor(this.W / 2), Math.floor(this.H / 2)];
    this.pin = [Math.min(this.W - 1, Math.max(0, p[0] + d[0] * step)), Math.min(this.H - 1, Math.max(0, p[1] + d[1] * step))];
    this.pinText.textContent = `Pinned pixel (${this.pin[0]}, ${this.pin[1]}).`;
    this.paint();
  }

  async pinComment() {
    const text = this.comment.value.trim();
    if (!text) {
      showError("Write a comment first.");
      this.comment.focus();
      return null;
    }
    const body = { frame_id: this.frame.id, comment: text };
    if (this.pin) body.pixel = this.pin;
    const item = await api.post(`/scenes/${this.frame.scene_id ?? this.sceneSel.value}/review-items`, body);
    this.items.push(item || body);
    this.pin = null;
    toast("Comment pinned.");
    return item;
  }

  /** Accept / reject the frame on screen: the frame and mask version are captured when the
   * key or button is pressed (never the frame being loaded next); one request at a time (a
   * double press is one decision); the toast offers Undo. */
  async decide(decision) {
    const f = this.frame;
    const version = this.shownVersion;
    if (!f || this.deciding || version == null) return;
    this.deciding = true;
    const prevState = f.state;
    this.setDecisionButtons(false);
    try {
      if (decision === "accept" && this.unreadableMask) {
        showError(`This mask cannot be shown as stored (${this.unreadableMask}); it cannot be accepted from this page. Reject it, or ask an admin.`);
        return;
      }
      const text = this.comment.value.trim();
      if (decision === "reject" && !text) {
        showError("A rejection needs a comment so the annotator knows what to fix.");
        this.comment.focus();
        return;
      }
      // a pinned pixel becomes its own review item carrying the comment, so the decision is
      // then sent without it (else the annotator reads it twice: pinned and "[reject] ...");
      // an unpinned comment is recorded by the review call itself
      let pinned = false;
      if (text && this.pin) pinned = !!(await this.pinComment());
      const out = await api.post(`/frames/${f.id}/review`, { decision, version, comment: (!pinned && text) || undefined });
      const decided = { ...f, ...(out || {}), state: (out && out.state) || (decision === "accept" ? "accepted" : "rejected") };
      const still = this.frame === f; // nothing else was opened meanwhile
      if (still) {
        this.frame = decided;
        this.comment.value = "";
        // the decision may have filed a comment item: show the frame's items as stored
        const sid = f.scene_id ?? this.sceneSel.value;
        const fresh = await api.get(`/scenes/${sid}/review-items?frame_id=${f.id}`).catch(() => null);
        if (fresh && this.frame === decided) this.items = fresh;
      }
      const undo = prevState !== decided.state ? { id: "undo-decision", label: "Undo", run: () => this.undoDecision(decided, decision, version, prevState) } : null;
      toast(decision === "accept" ? `Accepted ${f.name}.` : `Rejected ${f.name}; it goes back to its annotator.`, { action: undo });
      if (!still || this.frame !== decided) return;
      this.renderDetail();
      // auto-advance: the next frame still waiting for review, after this one in the list
      // (wrapping around to the top), else stay
      const before = (this.frames || []).map((r) => String(r.id));
      const i = before.indexOf(String(f.id));
      await this.loadList();
      if (this.autoAdvance && this.frame === decided) {
        const waiting = (this.frames || []).filter((r) => r.state === "submitted" && String(r.id) !== String(f.id));
        const pos = (r) => { const k = before.indexOf(String(r.id)); return k < 0 ? Infinity : (k - i + before.length) % before.length; };
        const nextRow = waiting.sort((x, y) => pos(x) - pos(y))[0];
        if (nextRow) await this.openFrame(nextRow.id);
        else toast("No other frame is waiting for review.", { action: undo });
      }
    } catch (e) {
      showError(e);
    } finally {
      this.deciding = false;
      this.setDecisionButtons(true);
    }
  }

  /** Accept / Reject buttons: off while a decision is pending (and before a frame is shown). */
  setDecisionButtons(on) {
    for (const id of ["accept", "reject"]) {
      const b = this.detailEl.querySelector(`#${id}`);
      if (b) b.disabled = !on || !this.frame;
    }
  }

  /** Undo (the toast's button): the frame's state before the decision, through the API
   * (audited): submitted again, or the earlier decision made again. */
  async undoDecision(decided, decision, version, prevState) {
    try {
      const out = prevState === "accepted" || prevState === "rejected"
        ? await api.post(`/frames/${decided.id}/review`, { decision: prevState === "accepted" ? "accept" : "reject", version })
        : await api.post(`/frames/${decided.id}/review/undo`, { decision, version });
      toast(`Undone: ${decided.name} is ${out ? out.state : prevState} again.`);
      await this.loadList();
      if (String(this.frameId) === String(decided.id) && this.frame) {
        this.frame = { ...this.frame, ...(out || {}) };
        this.renderDetail();
      }
    } catch (e) {
      showError(e);
    }
  }

  async resolve(it) {
    try {
      await api.patch(`/review-items/${it.id}`, { status: "resolved" });
      it.status = "resolved";
      this.renderDetail();
    } catch (e) {
      showError(e);
    }
  }
}
