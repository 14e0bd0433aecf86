// Reviewers' corrections on the annotator page (issue 25): a proposed mask change shown as an
// overlay, taken with one key (T: a new draft = current mask + proposal) or declined with a
// reply; review items selected in 3D drawn as the outline of their points in this frame.
// Also the notification badge of the top bar (notificationBadge).

import { api } from "../core/api.js";
import { el, showError, toast, dialog } from "../core/ui.js";

/** Load and draw this frame's open proposals and projected 3D items; returns the controller
 * the page keeps as `page.corrections` (its onKey handles T). */
export async function attachCorrections(page, ed, frame) {
  const ctl = new FrameCorrections(page, ed, frame);
  page.corrections = ctl;
  await ctl.load();
  return ctl;
}

class FrameCorrections {
  constructor(page, ed, frame) {
    this.page = page;
    this.ed = ed;
    this.frame = frame;
    this.proposal = null;
    this.overlay = null;
    this.items = [];
    this.bar = el("div", { class: "proposal-bar", id: "proposal-bar", role: "status", hidden: true });
    this.page.host.append(this.bar);
    ed.view.overlayPainters.push((c, v) => this.draw(c, v));
  }

  get alive() {
    return this.page.editor === this.ed;
  }

  async load() {
    const fid = this.frame.id;
    const [props, items] = await Promise.all([
      api.get(`/frames/${fid}/proposals?status=open`).catch(() => []),
      api.get(`/frames/${fid}/projected-items`).catch(() => []),
    ]);
    if (!this.alive) return;
    this.items = (items || []).filter((it) => it.status !== "resolved");
    this.proposal = (props || [])[0] || null;
    if (this.proposal) {
      const res = await api.send("GET", `/frames/${fid}/proposals/${this.proposal.id}/overlay`);
      this.overlay = await createImageBitmap(await res.blob());
    }
    this.renderBar();
    this.ed.view.invalidate();
  }

  renderBar() {
    const p = this.proposal;
    const n3d = this.items.length;
    const parts = [];
    if (p) {
      parts.push(
        el("span", { id: "proposal-text" }, `${p.author || "A reviewer"} proposes to change ${p.changed_px.toLocaleString()} px (from a 3D correction). `),
        // a submitted frame is reopened as part of taking; otherwise say why Take is off
        this.page.readOnlyWhy === "submitted"
          ? el("button", { type: "button", id: "proposal-take", class: "primary", "data-reopen": "1", onclick: () => this.take().catch(showError), title: "You submitted this frame: taking the proposal reopens it for editing (while no reviewer has decided), then makes a new draft with the proposal (T)" }, "Reopen and take (T)")
          : el("button", { type: "button", id: "proposal-take", class: "primary", disabled: this.page.readOnly, onclick: () => this.take().catch(showError), title: this.page.readOnly ? this.whyNoTake() : "Take it: a new draft of the current mask with the proposal (T)" }, "Take (T)"),
        el("button", { type: "button", id: "proposal-decline", onclick: () => this.decline().catch(showError) }, "Decline…"),
      );
      if (this.page.readOnly && this.page.readOnlyWhy !== "submitted") parts.push(el("span", { id: "proposal-why", class: "muted" }, ` ${this.whyNoTake()}`));
    }
    if (n3d) parts.push(el("span", { id: "projected-items", "data-count": String(n3d) }, ` ${n3d} review item${n3d > 1 ? "s" : ""} selected in 3D (outlined).`));
    this.bar.replaceChildren(...parts);
    this.bar.hidden = !parts.length;
  }

  draw(c, v) {
    if (this.overlay) {
      const [x0, y0] = v.toScreen(0, 0);
      const [x1, y1] = v.toScreen(this.frame.width, this.frame.height);
      c.save();
      c.imageSmoothingEnabled = false;
      c.globalAlpha = 0.85;
      c.drawImage(this.overlay, x0, y0, x1 - x0, y1 - y0);
      c.restore();
    }
    drawOutlines(c, this.items, (x, y) => v.toScreen(x, y));
  }

  /** Why this person cannot take the proposal here (the frame is read-only for them). */
  whyNoTake() {
    return {
      accepted: "Take is off: a reviewer accepted this frame, so its mask is not edited any more.",
      other: `Take is off: the frame is leased to ${this.page.frame?.assignee || "someone else"}.`,
      free: 'Take is off: this frame is not leased to you; press "Next frame" or ask for it.',
    }[this.page.readOnlyWhy] || "Take is off: the frame is read-only for you.";
  }

  onKey(e) {
    if (e.type !== "keydown" || e.ctrlKey || e.metaKey || e.altKey) return false;
    if ((e.key === "t" || e.key === "T") && this.proposal) {
      if (this.page.readOnly && this.page.readOnlyWhy !== "submitted") toast(this.whyNoTake());
      else this.take().catch(showError);
      return true;
    }
    return false;
  }

  async take() {
    const p = this.proposal;
    if (!p || this.taking) return;
    this.taking = true;
    try {
      // taking on a submitted frame reopens it first (the server refuses once a reviewer decided)
      if (this.page.readOnlyWhy === "submitted") await api.post(`/frames/${this.frame.id}/reopen`);
      else if (this.page.unsaved) await this.page.save("draft", { force: true });
      const v = this.page.version;
      const headers = v && v !== "none" ? { "If-Match": `"${v}"` } : {};
      await api.send("POST", `/frames/${this.frame.id}/proposals/${p.id}/take`, { headers });
      toast(`Proposal taken: ${p.changed_px.toLocaleString()} px changed in a new draft.`);
      await this.page.open(this.frame.id); // the new draft is the current mask now
    } finally {
      this.taking = false;
    }
  }

  async decline() {
    const p = this.proposal;
    if (!p) return;
    const reply = await askReply();
    if (!reply) return;
    await api.post(`/frames/${this.frame.id}/proposals/${p.id}/decline`, { reply });
    this.proposal = null;
    this.overlay = null;
    this.renderBar();
    this.ed.view.invalidate();
    toast("Proposal declined; the reviewer sees your reply.");
  }
}

/** Draw review items' outlines (image pixel polygons) with their first comment; `toScreen`
 * maps image pixels to canvas pixels. Shared by the annotator and reviewer pages. */
export function drawOutlines(c, items, toScreen) {
  for (const it of items || []) {
    const pts = it.outline || [];
    if (pts.length < 2) continue;
    c.save();
    c.strokeStyle = "#00e5ff";
    c.lineWidth = 2;
    c.setLineDash([6, 4]);
    c.beginPath();
    pts.forEach(([x, y], i) => {
      const [sx, sy] = toScreen(x, y);
      if (i === 0) c.moveTo(sx, sy);
      else c.lineTo(sx, sy);
    });
    c.closePath();
    c.stroke();
    const [lx, ly] = toScreen(pts[0][0], pts[0][1]);
    c.setLineDash([]);
    c.fillStyle = "#00e5ff";
    c.font = "12px sans-serif";
    const text = (it.comments && it.comments[0] && it.comments[0].text) || `item ${it.id}`;
    c.fillText(text.slice(0, 60), lx + 4, ly - 4);
    c.restore();
  }
}

async function askReply() {
  const input = el("textarea", { id: "decline-reply", rows: 3, cols: 40, "aria-label": "Reply to the reviewer" });
  const ok = await dialog({ title: "Decline the proposal", body: el("div", {}, el("p", {}, "Tell the reviewer why:"), input), buttons: [{ label: "Decline", value: true, primary: true }, { label: "Cancel", value: false }] }).catch(() => false);
  return ok ? input.value.trim() : null;
}

/** The notification badge + list for the top bar; polls every 30 s. */
export function notificationBadge() {
  const count = el("span", { class: "badge", id: "notif-count", hidden: true }, "");
  const list = el("div", { class: "notif-list", id: "notif-list", hidden: true });
  const btn = el("button", { type: "button", class: "notif-btn", id: "notif-btn", title: "Notifications", onclick: () => toggle() }, el("span", { class: "notif-icon", "aria-hidden": "true" }, "✉"), el("span", { class: "sr-only" }, "Notifications"), count);
  const box = el("span", { class: "notifications" }, btn, list);
  async function refresh() {
    try {
      const n = await api.get("/notifications");
      count.textContent = String(n.unread);
      count.hidden = !n.unread;
      list.replaceChildren(
        n.items.length ? el("ul", {}, n.items.map((x) => el("li", { class: x.read_at ? "read" : "unread", "data-kind": x.kind }, el("a", { href: x.frame_id ? `#/annotate?scene=${x.scene_id}&frame=${x.frame_id}` : "#/" }, x.text)))) : el("p", {}, "No notifications."),
      );
    } catch {
      /* logged out: nothing to show */
    }
  }
  async function toggle() {
    list.hidden = !list.hidden;
    if (!list.hidden) {
      await refresh();
      await api.post("/notifications/read", {}).catch(() => {});
      count.hidden = true;
    }
  }
  refresh();
  const timer = setInterval(() => (document.body.contains(box) ? refresh() : clearInterval(timer)), 30000);
  return box;
}
